"""Recording with the shared controller: a person (a scripted teleop input) as the gate's fallback
with the page's help marker, `collect --shared` storing each step's driver, and the replay's path
coloured by who drove."""

import base64
import dataclasses
import json
import re

import numpy as np
import pytest
from pydrake.geometry import Meshcat

from ditch_drake.cli import main
from ditch_drake.demos.collect import MakeDemonstrationDiagram, record_shared_demonstration
from ditch_drake.demos.store import DatasetStore
from ditch_drake.diagrams.controllers import controller_config
from ditch_drake.diagrams.ditch_scene import SceneConfig
from ditch_drake.diagrams.replay import ReplayConfig, driven_segments, record_replay
from ditch_drake.diagrams.rollout import RolloutConfig
from ditch_drake.diagrams.shared_controller import CHASSIS_MESHCAT_PATH
from ditch_drake.learning.checkpoint import load_checkpoint, resolve_checkpoint_path
from ditch_drake.learning.ensemble import EnsembleCheckpoint, save_ensemble
from ditch_drake.spec import actions
from ditch_drake.systems.driver_indicator import HELP_BUTTON
from ditch_drake.systems.episode_monitor import EpisodeConfig
from ditch_drake.systems.shared_control import FALLBACK, POLICY

# The shipped wide clone's mean softmax entropy has its median near 1.05 nats: a threshold of 1
# with one calm step switches many times in a few seconds.
SWITCHING = {"upper_threshold": 1.0, "lower_threshold": 1.0, "calm_steps": 1}


def _shared(fallback: str, checkpoint: str = "", signal: str = "mean_softmax_entropy", **gate):
    config = controller_config("shared").with_checkpoint(checkpoint)
    return dataclasses.replace(config, gate=dataclasses.replace(config.gate, fallback=fallback, signal=signal,
                                                                **gate))


def _teleop_demonstration(gate: dict, meshcat: Meshcat, time_limit_s: float = 2.0):
    """A shared episode whose fallback is the Meshcat teleop, no one pressing a key: the
    scripted person drives straight ahead at the demonstrations' speed."""
    shared = _shared("teleop", **gate)
    scene = SceneConfig(environment="wide", task=1, episode=EpisodeConfig(time_limit_s=time_limit_s))
    rig = MakeDemonstrationDiagram(scene, 0, meshcat=meshcat, shared=shared)
    return rig, record_shared_demonstration("wide", 1, 0, shared, rig=rig, meshcat=meshcat)


def test_the_person_steers_where_the_gate_hands_over_and_the_page_says_so():
    meshcat = Meshcat()
    # Above any entropy: the policy drives every step, the page stays calm.
    rig, calm = _teleop_demonstration({"upper_threshold": 10.0, "lower_threshold": 10.0}, meshcat)
    assert rig.diagram.HasSubsystemNamed("driver_indicator") and rig.diagram.HasSubsystemNamed("meshcat_teleop")
    assert len(calm) == 20 and not calm.arrays["intervention"].any()
    assert calm.metadata["intervened_steps"] == 0 and calm.metadata["switches"] == 0
    assert HELP_BUTTON not in meshcat.GetButtonNames()
    assert meshcat.HasPath(f"{CHASSIS_MESHCAT_PATH}/driver_marker")
    # Below any entropy, with no warm-up: the gate hands over at its first tick and never back.
    rig, helped = _teleop_demonstration({"upper_threshold": 0.0, "lower_threshold": 0.0, "warmup_steps": 0}, meshcat)
    assert helped.arrays["intervention"].all() and helped.metadata["switches"] == 1
    # The person's (scripted) command is what was executed and recorded: straight ahead.
    assert set(helped.arrays["label"].tolist()) == {actions.STRAIGHT_LABEL}
    np.testing.assert_allclose(helped.arrays["raw_command"], [[actions.SPEED_MPS, 0.0]] * len(helped), atol=1e-6)
    assert HELP_BUTTON in meshcat.GetButtonNames()  # Shown while the person drives.
    assert helped.metadata["driver"].endswith("fallback teleop") and helped.metadata["learner"] == "wide"
    # Between: the gate switches both ways, and each step carries its driver.
    _, mixed = _teleop_demonstration(SWITCHING, meshcat, time_limit_s=4.0)
    flags = mixed.arrays["intervention"]
    assert 0 < flags.sum() < len(flags) and mixed.metadata["switches"] >= 2
    assert set(mixed.arrays["label"][flags].tolist()) == {actions.STRAIGHT_LABEL}


def test_collect_shared_stores_each_step_with_its_driver(tmp_path, capsys):
    out = tmp_path / "shared"
    options = ["collect", "--shared", "--env", "wide", "--demos", "1", "--seed", "3", "--workers", "0",
               "--out", str(out), "--checkpoint", "wide", "--signal", "mean_softmax_entropy", "--upper-threshold", "1.0",
               "--lower-threshold", "1.0", "--calm-steps", "1"]
    assert main(options) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["recorded"] == 1 and report["unfilled_slots"] == []
    store = DatasetStore.open(out)
    (episode,) = store.episodes()
    arrays = store.read(episode, ["intervention", "label"])
    flags = np.asarray(arrays["intervention"])
    assert 0 < flags.sum() < len(flags)
    metadata = episode.metadata
    assert metadata["intervened_steps"] == int(flags.sum()) and metadata["switches"] >= 2
    assert metadata["shared_gate"]["upper_threshold"] == 1.0 and metadata["shared_labels"] == "executed"
    assert metadata["learner"] == "wide" and metadata["expert_style"]["reaction_delay_steps"] == 0
    print(f"collect --shared: {len(flags)} steps, {int(flags.sum())} interventions, "
          f"{metadata['switches']} switches, {metadata['outcome']['status']}")


@pytest.mark.parametrize("extra, message", [
    (["--learner", "wide"], "--learner wide with --shared"),
    (["--fallback", "mppi", "--shared-labels", "expert"], "shared_labels 'expert' with fallback 'mppi'"),
    (["--upper-threshold", "0.5", "--lower-threshold", "0.9"], "lower_threshold 0.9 > upper_threshold 0.5"),
    (["--signal", "random", "--upper-threshold", "2.55"], "upper_threshold 2.55 with signal 'random': expected a number in"),
    (["--progress-limit", "-4"], "progress_limit_s -4.0: expected a number of seconds > 0"),
    (["--regress-limit", "0"], "regress_limit_m 0.0: expected a number of metres > 0"),
])
def test_bad_shared_collections_exit_2_naming_the_value(tmp_path, capsys, extra, message):
    code = main(["collect", "--shared", "--env", "wide", "--demos", "1", "--workers", "0",
                 "--out", str(tmp_path / "d"), *extra])
    err = capsys.readouterr().err
    assert code == 2 and message in err, err
    assert not (tmp_path / "d" / "episodes").exists() or not list((tmp_path / "d" / "episodes").iterdir())


def test_the_random_gate_is_offered_to_recording_commands():
    from ditch_drake.cli.main import build_parser
    from ditch_drake.cli.shared_options import shared_config_from_options

    for command in (["collect", "--shared", "--out", "d"], ["teleop", "--shared", "--out", "d"]):
        args = build_parser().parse_args([*command, "--signal", "random", "--upper-threshold", "0.95",
                                          "--lower-threshold", "0.8"])
        gate = shared_config_from_options(args, "wide", fallback="expert").gate
        assert (gate.signal, gate.upper_threshold, gate.lower_threshold) == ("random", 0.95, 0.8)
        assert gate.progress_limit_s is None and gate.regress_limit_m is None
        args = build_parser().parse_args([*command, "--progress-limit", "12", "--regress-limit", "3"])
        gate = shared_config_from_options(args, "wide", fallback="expert").gate
        assert (gate.progress_limit_s, gate.regress_limit_m) == (12.0, 3.0)


def test_recording_commands_take_the_gate_from_a_budget(tmp_path):
    from ditch_drake.cli.main import build_parser
    from ditch_drake.cli.shared_options import shared_config_from_options
    from ditch_drake.learning.checkpoint import checkpoint_digest
    from ditch_drake.learning.gate_calibration import save_signals

    values = np.linspace(0.0, 1.0, 101)
    signals = tmp_path / "signals.npz"
    save_signals(signals, "wide", checkpoint_digest("wide"), {"mean_softmax_entropy": values},
                 {"time_s": values, "episode": [0] * 101},
                 {"episode_environment": ["wide"], "episode_task": [1], "episode_seed": [0],
                  "episode_status": ["timeout"], "episode_end_time_s": [10.0]})
    for command in (["collect", "--shared", "--out", "d"], ["teleop", "--shared", "--out", "d"]):
        args = build_parser().parse_args([*command, "--signal", "mean_softmax_entropy", "--budget", "0.1",
                                          "--calibration", str(signals), "--calm-steps", "1"])
        gate = shared_config_from_options(args, "wide", fallback="expert").gate
        assert (gate.budget, gate.calibration) == (0.1, str(signals))
        resolved = gate.resolved()
        assert resolved.upper_threshold == pytest.approx(0.9) and resolved.lower_threshold == pytest.approx(0.8)


@pytest.mark.parametrize("extra, message", [
    (["--budget", "0.1"], "budget 0.1 without a calibration"),
    (["--budget", "1.5", "--calibration", "x.npz"], "budget 1.5: expected a share of control steps in (0, 1)"),
    (["--calibration", "x.npz"], "calibration 'x.npz' without a budget"),
    (["--budget", "0.1", "--calibration", "missing.npz"], "missing.npz: cannot read it"),
])
def test_bad_budgets_of_a_shared_collection_exit_2(tmp_path, capsys, extra, message):
    code = main(["collect", "--shared", "--env", "wide", "--demos", "1", "--workers", "0",
                 "--out", str(tmp_path / "d"), *extra])
    err = capsys.readouterr().err
    assert code == 2 and message in err, err
    assert not (tmp_path / "d").exists()


def test_a_checkpoint_without_shared_is_refused(tmp_path, capsys):
    assert main(["collect", "--checkpoint", "wide", "--out", str(tmp_path / "d"), "--demos", "1"]) == 2
    assert "--checkpoint wide: a gated policy drives only with --shared" in capsys.readouterr().err


def test_driven_segments_share_their_ends():
    assert driven_segments([0, 0, 1, 1, 1, 0]) == [(0, 0, 2), (1, 2, 5), (0, 5, 6)]
    assert driven_segments([1]) == [(1, 0, 1)] and driven_segments([]) == []


def _embedded_commands(html: str) -> list[bytes]:
    pattern = r"data:application/octet-binary;base64,([A-Za-z0-9+/=]+)"
    return [base64.b64decode(data) for data in re.findall(pattern, html)]


def test_the_replay_colours_a_shared_path_by_who_drove(tmp_path):
    # A tiny ensemble: two shipped clones of one shape in one file (K = 2), gated by its entropy.
    pair = tmp_path / "pair.pt"
    save_ensemble(EnsembleCheckpoint([load_checkpoint(resolve_checkpoint_path(name))
                                      for name in ("wide_bc40", "wide")]), pair)
    scene = SceneConfig(environment="wide", task=1, episode=EpisodeConfig(time_limit_s=4.0))
    shared = _shared("expert", str(pair), **SWITCHING)
    replay = record_replay(ReplayConfig(rollout=RolloutConfig(scene=scene, controller=shared), seed=3,
                                        out=str(tmp_path / "shared.html")))
    drivers = replay.drivers
    assert len(drivers) == 40 and set(drivers) == {POLICY, FALLBACK}
    html = replay.html_path.read_text()
    drawn = b"".join(command for command in _embedded_commands(html) if b"set_object" in command)
    names = re.findall(rb"/replay/path/(\d{3})_(policy|fallback)", drawn)
    segments = driven_segments(drivers)
    assert len(set(names)) == len(segments) >= 3
    assert {kind for _, kind in names} == {b"policy", b"fallback"}
    assert "path the policy drove" in html and "path the fallback drove" in html
    assert "shared control: learned policy, checkpoint" in html
    print(f"replay of a shared rollout: {len(drivers)} steps, {sum(drivers)} by the fallback, "
          f"{len(segments)} path segments")


def test_a_replay_of_another_controller_draws_one_path(tmp_path):
    scene = SceneConfig(environment="wide", task=1, episode=EpisodeConfig(time_limit_s=1.0))
    replay = record_replay(ReplayConfig(rollout=RolloutConfig(scene=scene, controller=controller_config("expert")),
                                        out=str(tmp_path / "expert.html")))
    assert replay.drivers is None
    html = replay.html_path.read_text()
    assert "driven path" in html and "path the fallback drove" not in html
