"""The standalone HTML recording, checked as a user sees it: in a headless Chromium."""

import base64
import re

import numpy as np
import pytest
from matplotlib.image import imread

from ditch_drake.cli import main
from ditch_drake.diagrams.ditch_scene import SceneConfig
from ditch_drake.diagrams.replay import ReplayConfig, ReplayOutputError, record_replay
from ditch_drake.diagrams.rollout import ExpertConfig, RolloutConfig
from ditch_drake.docs_tools.browser import find_chromium, screenshot
from ditch_drake.systems.episode_monitor import EpisodeConfig
from ditch_drake.world.environments import ConfigError


@pytest.fixture(scope="module")
def replay(tmp_path_factory):
    scene = SceneConfig(environment="wide", task=1, episode=EpisodeConfig(time_limit_s=4.0))
    out = tmp_path_factory.mktemp("replay") / "replay.html"
    return record_replay(ReplayConfig(rollout=RolloutConfig(scene=scene, controller=ExpertConfig()), out=str(out)))


def _embedded_commands(html: str) -> list[bytes]:
    """The meshcat commands StaticHtml embeds, each a msgpack message in a base64 data URI."""
    return [base64.b64decode(data) for data in re.findall(r"data:application/octet-binary;base64,([A-Za-z0-9+/=]+)", html)]


def test_the_recording_is_a_standalone_page_with_the_animation(replay):
    assert replay.outcome.status == "timeout" and replay.outcome.path_length_m > 2.0
    assert replay.snapshots == 9  # 0.5 s snapshots over 4 s, plus the one at the end.
    html = replay.html_path.read_text()
    assert html.startswith("<!DOCTYPE html>") and html.rstrip().endswith("</html>")
    assert replay.html_bytes > 1_000_000  # The ditch's geometry and the animation are embedded.
    assert not list(replay.html_path.parent.glob(".*.tmp"))


def test_the_page_embeds_the_animation_of_robot_and_lidar_and_the_path(replay):
    commands = _embedded_commands(replay.html_path.read_text())
    animations = [command for command in commands if b"set_animation" in command]
    assert len(animations) == 1
    assert b"/drake/illustration/husky/chassis" in animations[0]  # The robot moves in the animation,
    for index in range(replay.snapshots):  # and each lidar snapshot is switched on and off in it.
        assert f"/replay/lidar/{index:04d}".encode() in animations[0]
    drawn = b"".join(command for command in commands if b"set_object" in command)
    assert b"/replay/path" in drawn and b"/replay/lidar/0000" in drawn
    assert b"/drake/illustration/terrain_wall" in drawn and b"/drake/illustration/terrain_floor" in drawn  # The ditch.


def test_the_recording_renders_in_a_headless_browser(replay, tmp_path):
    if find_chromium() is None:
        pytest.skip("no chromium on this machine (.ci/run installs Debian's chromium package)")
    pixels = imread(screenshot(replay.html_path, tmp_path / "shot.png"))[..., :3]
    assert pixels.shape[:2] == (600, 800)
    colours = np.unique((pixels * 255).astype(np.uint8).reshape(-1, 3), axis=0)
    assert len(colours) > 500  # A lit 3-D scene, not a blank or single-colour page.
    red, green, blue = pixels[..., 0], pixels[..., 1], pixels[..., 2]
    lidar_orange = (red > 0.8) & (green > 0.2) & (green < 0.6) & (blue < 0.2)
    assert lidar_orange.sum() > 20  # The lidar's points are drawn.


def test_a_bad_environment_is_refused_before_anything_is_written(tmp_path):
    out = tmp_path / "bad.html"
    with pytest.raises(ConfigError, match="'moon'"):
        record_replay(ReplayConfig(rollout=RolloutConfig(scene=SceneConfig(environment="moon")), out=str(out)))
    assert not out.exists() and not list(tmp_path.iterdir())


@pytest.mark.parametrize("make_bad_path", [lambda tmp: tmp / "a_file" / "replay.html", lambda tmp: tmp])
def test_an_unwritable_output_is_refused_naming_the_path(tmp_path, make_bad_path):
    (tmp_path / "a_file").write_text("not a folder")
    out = make_bad_path(tmp_path)
    scene = SceneConfig(environment="wide", task=1, episode=EpisodeConfig(time_limit_s=60.0))
    with pytest.raises(ReplayOutputError, match=re.escape(str(out))):
        record_replay(ReplayConfig(rollout=RolloutConfig(scene=scene, controller=ExpertConfig()), out=str(out)))
    assert sorted(path.name for path in tmp_path.iterdir()) == ["a_file"]


def test_the_cli_reports_a_bad_environment_or_output_without_a_traceback(tmp_path, capsys):
    (tmp_path / "a_file").write_text("not a folder")
    assert main(["replay", "--env", "moon", "--out", str(tmp_path / "x.html")]) == 2
    assert "ditch-drake: error:" in capsys.readouterr().err
    bad = tmp_path / "a_file" / "x.html"
    assert main(["replay", "--env", "wide", "--time-limit", "60", "--out", str(bad)]) == 2
    assert f"cannot write the recording to {bad}" in capsys.readouterr().err
    assert main(["replay", "--controller", "learned", "--checkpoint", "no_such_model", "--out", str(tmp_path / "x.html")]) == 2
    assert "checkpoint 'no_such_model'" in capsys.readouterr().err
    assert sorted(path.name for path in tmp_path.iterdir()) == ["a_file"]
