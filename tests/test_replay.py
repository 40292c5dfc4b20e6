"""The standalone HTML recording, checked as a user sees it: in a headless Chromium."""

import numpy as np
import pytest
from matplotlib.image import imread

from ditch_drake.browser import find_chromium, screenshot
from ditch_drake.diagrams.ditch_scene import SceneConfig
from ditch_drake.diagrams.replay import ReplayConfig, record_replay
from ditch_drake.diagrams.rollout import ExpertConfig, RolloutConfig
from ditch_drake.environments import ConfigError
from ditch_drake.systems.episode_monitor import EpisodeConfig


@pytest.fixture(scope="module")
def replay(tmp_path_factory):
    scene = SceneConfig(environment="wide", task=1, episode=EpisodeConfig(time_limit_s=4.0))
    out = tmp_path_factory.mktemp("replay") / "replay.html"
    return record_replay(ReplayConfig(rollout=RolloutConfig(scene=scene, controller=ExpertConfig()), out=str(out)))


def test_the_recording_is_a_standalone_page_with_the_animation(replay):
    assert replay.outcome.status == "timeout" and replay.outcome.path_length_m > 2.0
    assert replay.snapshots == 9  # 0.5 s snapshots over 4 s, plus the one at the end.
    html = replay.html_path.read_text()
    assert html.startswith("<!DOCTYPE html>") and html.rstrip().endswith("</html>")
    assert replay.html_bytes > 1_000_000  # The ditch's geometry and the animation are embedded.
    assert not list(replay.html_path.parent.glob(".*.tmp"))


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
    assert not out.exists()
