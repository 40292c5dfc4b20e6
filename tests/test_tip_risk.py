"""The tip-risk block: minus the tip margin of the chassis now and along the commanded arc;
`gate-signals --risk`, which records it beside the uncertainty signals without changing the run;
and a shared-control gate that reads it."""

import dataclasses
import math

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.systems.analysis import Simulator

from ditch_drake.cli import main
from ditch_drake.common.errors import ConfigError
from ditch_drake.diagrams.controllers import controller_config, get_controller
from ditch_drake.diagrams.ditch_scene import SceneConfig
from ditch_drake.diagrams.rollout import MakeRolloutDiagram, RolloutConfig
from ditch_drake.learning.gate_calibration import FALLBACK, POLICY, load_signals
from ditch_drake.learning.uncertainty import RISK_SIGNALS
from ditch_drake.planning.elevation_map import ElevationGrid
from ditch_drake.spec import robot
from ditch_drake.systems.tip_risk import TipRisk, TipRiskConfig

FORE_AFT_TIP_DEG = math.degrees(robot.tip_angle_fore_aft_rad())
SIDEWAYS_TIP_DEG = math.degrees(robot.tip_angle_sideways_rad())


def _risk(heights_of_xy, X_WB: RigidTransform, command, config: TipRiskConfig | None = None) -> np.ndarray:
    """The block's output with its map made of `heights_of_xy(x, y)` around the robot."""
    grid = ElevationGrid()
    origin = grid.window_origin(X_WB.translation()[:2])
    xs, ys = grid.cell_centers(origin)
    heights = heights_of_xy(xs[None, :], ys[:, None]) + np.zeros(grid.shape)
    block = TipRisk(0, grid, config)
    context = block.CreateDefaultContext()
    block.GetInputPort("elevation_map").FixValue(context, grid.pack(grid.origin_m(origin), heights))
    block.GetInputPort("body_poses").FixValue(context, [X_WB])
    block.GetInputPort("command").FixValue(context, np.asarray(command, dtype=float))
    return np.array([block.GetOutputPort(name).Eval(context)[0] for name in RISK_SIGNALS])


def flat(x, y):
    return 0.0 * x


def wall_ahead(x, y):
    """Flat to x = 1 m, then falling away at 55 deg (a ditch's wall)."""
    return -np.tan(np.radians(55.0)) * np.clip(x - 1.0, 0.0, None) + 0.0 * y


def test_on_flat_ground_both_are_minus_the_smaller_tip_angle():
    risk = _risk(flat, RigidTransform(), [1.0, 0.0])
    np.testing.assert_allclose(risk, [-FORE_AFT_TIP_DEG] * 2, atol=1e-6)


def test_now_is_the_chassis_attitude_and_ahead_the_arc_into_a_wall():
    # Rolled 30 deg, the sideways margin is what is left of the tip angle.
    rolled = RigidTransform(RollPitchYaw(math.radians(30.0), 0.0, 0.0), [0.0, 0.0, 0.0])
    assert _risk(flat, rolled, [1.0, 0.0])[0] == pytest.approx(30.0 - SIDEWAYS_TIP_DEG, abs=1e-6)
    # Straight at the wall, the arc ends on it head-on: 55 deg of the fore-aft tip angle used.
    now, ahead = _risk(wall_ahead, RigidTransform(), [1.0, 0.0])
    assert now == pytest.approx(-FORE_AFT_TIP_DEG, abs=1e-6)
    assert ahead == pytest.approx(55.0 - FORE_AFT_TIP_DEG, abs=0.5)
    # Turning away at the largest label rate, the arc only grazes the edge, either way.
    left, right = (_risk(wall_ahead, RigidTransform(), [1.0, w])[1] for w in (0.85, -0.85))
    assert left == pytest.approx(right, abs=1e-6) and 10.0 - FORE_AFT_TIP_DEG < left < ahead - 5.0
    # A shorter horizon stops short of the wall.
    short = _risk(wall_ahead, RigidTransform(), [1.0, 0.0], TipRiskConfig(horizon_s=0.3))[1]
    assert short == pytest.approx(-FORE_AFT_TIP_DEG, abs=1e-6)


def test_an_unknown_map_leaves_the_current_margin():
    risk = _risk(lambda x, y: np.nan * x, RigidTransform(), [1.0, 0.0])
    np.testing.assert_allclose(risk, [-FORE_AFT_TIP_DEG] * 2, atol=1e-6)


def test_a_horizon_shorter_than_a_control_period_is_refused():
    with pytest.raises(ConfigError, match="tip_risk horizon_s=0.01"):
        TipRisk(0, ElevationGrid(), TipRiskConfig(horizon_s=0.01))


def test_gate_signals_risk_records_two_more_signals_and_changes_nothing_else(tmp_path, capsys):
    argv = ["gate-signals", "--workers", "0", "--checkpoint", "wide_bc40", "--env", "wide", "--task", "1",
            "--rollouts", "1", "--seed", "4", "--time-limit", "8"]
    assert main([*argv, "--out", str(tmp_path / "plain.npz")]) == 0
    assert main([*argv, "--risk", "--out", str(tmp_path / "risk.npz")]) == 0
    assert "tip_risk_ahead" in capsys.readouterr().out
    plain, risk = load_signals(tmp_path / "plain.npz"), load_signals(tmp_path / "risk.npz")
    assert risk["signals"] == ["mean_softmax_entropy", "command_reversals", "seconds_without_progress",
                               "metres_regressed", "tip_risk_now", "tip_risk_ahead"]
    for name in ("mean_softmax_entropy", "command_reversals", "seconds_without_progress", "metres_regressed", "time_s",
                 "episode", "episode_status", "episode_end_time_s"):
        np.testing.assert_array_equal(risk[name], plain[name], err_msg=name)
    for name in ("tip_risk_now", "tip_risk_ahead"):
        values = risk[name]
        assert values.shape == (80,) and np.all(np.isfinite(values)) and np.all(values <= 0.0), name
    # On the flat start the chassis is level; the arc reaches the presumed drop at the edge later.
    assert risk["tip_risk_now"][10] == pytest.approx(-FORE_AFT_TIP_DEG, abs=1.0)
    # A longer arc covers the shorter one: its least margin ahead is no larger, on the same drive.
    assert main([*argv, "--risk", "--risk-horizon", "4", "--out", str(tmp_path / "risk4.npz")]) == 0
    longer = load_signals(tmp_path / "risk4.npz")
    assert (risk["tip_risk_horizon_s"], longer["tip_risk_horizon_s"]) == (2.0, 4.0)
    for name in ("mean_softmax_entropy", "tip_risk_now", "time_s"):
        np.testing.assert_array_equal(longer[name], risk[name], err_msg=name)
    assert np.all(longer["tip_risk_ahead"] >= risk["tip_risk_ahead"] - 1e-9)
    assert np.any(longer["tip_risk_ahead"] > risk["tip_risk_ahead"] + 1.0)


def test_a_risk_gate_reads_the_tip_risk_of_the_policys_command_and_hands_over_near_the_edge():
    config = controller_config("shared")
    # Calm while the arc keeps 30 deg of margin, handed over once it would keep less than 20.
    config = dataclasses.replace(config, gate=dataclasses.replace(
        config.gate, signal="tip_risk_ahead", upper_threshold=-20.0, lower_threshold=-30.0, fallback="expert"))
    diagram, _ = MakeRolloutDiagram(RolloutConfig(scene=SceneConfig(environment="wide", task=1),
                                                  controller=get_controller("shared").for_seed(config, 3)))
    gate, risk, policy = (diagram.GetSubsystemByName(name) for name in ("shared_control", "tip_risk", "learned_policy"))
    simulator = Simulator(diagram)
    drivers = []
    for t in np.arange(0.5, 12.0, 0.5):
        simulator.AdvanceTo(t)
        root = simulator.get_context()
        gate_context, risk_context = gate.GetMyContextFromRoot(root), risk.GetMyContextFromRoot(root)
        np.testing.assert_array_equal(gate.GetInputPort("uncertainty").Eval(gate_context),
                                      risk.GetOutputPort("tip_risk_ahead").Eval(risk_context))
        np.testing.assert_array_equal(risk.GetInputPort("command").Eval(risk_context),
                                      policy.GetOutputPort("command").Eval(policy.GetMyContextFromRoot(root)))
        drivers.append(gate.GetOutputPort("who_drives").Eval(gate_context)[0])
    # Far from the edge the policy drives; its arc nears the wall within the first 12 s.
    assert drivers[0] == POLICY and FALLBACK in drivers, drivers


def test_a_risk_gate_on_a_recording_without_risk_signals_is_refused_naming_the_option(tmp_path, capsys):
    out = tmp_path / "plain.npz"
    argv = ["gate-signals", "--workers", "0", "--checkpoint", "wide_bc40", "--env", "wide", "--task", "1",
            "--rollouts", "1", "--seed", "4", "--time-limit", "1", "--out", str(out)]
    assert main(argv) == 0
    override = ("{controller: !SharedControlControllerConfig {policy: {checkpoint: wide_bc40}, gate: {signal: "
                f"tip_risk_ahead, budget: 0.05, calibration: {out}}}}}}}")
    capsys.readouterr()
    assert main(["evaluate", "--override", override, "--env", "wide", "--task", "1", "--rollouts", "1",
                 "--out", str(tmp_path / "r.jsonl")]) == 2
    err = capsys.readouterr().err
    assert "has no signal 'tip_risk_ahead'" in err and "gate-signals --risk" in err, err


def test_a_tip_risk_config_beside_a_gate_that_does_not_read_it_is_refused(tmp_path, capsys):
    override = ("{controller: !SharedControlControllerConfig {policy: {tip_risk: {horizon_s: 3.0}}, gate: {signal: "
                "angular_rate_spread, upper_threshold: 0.5, lower_threshold: 0.4}}}")
    assert main(["evaluate", "--override", override, "--env", "wide", "--task", "1", "--rollouts", "1",
                 "--out", str(tmp_path / "r.jsonl")]) == 2
    err = capsys.readouterr().err
    assert "policy.tip_risk with signal 'angular_rate_spread'" in err, err
    assert not (tmp_path / "r.jsonl").exists()
