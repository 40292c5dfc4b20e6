"""The seconds without progress toward the goal and the metres fallen back since: the counts, the
block that gives them a gate, the gate's watchdogs beside another signal, and `gate-signals`,
which records the same counts."""

import dataclasses
import math

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator

from ditch_drake.common.config_yaml import config_to_yaml
from ditch_drake.common.errors import ConfigError
from ditch_drake.diagrams.controllers import controller_config, get_controller
from ditch_drake.diagrams.ditch_scene import SceneConfig
from ditch_drake.diagrams.rollout import MakeRolloutDiagram, RolloutConfig, RunEpisode
from ditch_drake.diagrams.shared_controller import SharedControlControllerConfig
from ditch_drake.learning.gate_calibration import FALLBACK, POLICY, gate_step
from ditch_drake.learning.uncertainty import PROGRESS_SIGNAL, REGRESS_SIGNAL
from ditch_drake.spec import robot
from ditch_drake.spec.observation_layout import STACK_DEPTH
from ditch_drake.systems.goal_progress import PROGRESS_STEP_M, GoalProgress, Progress, progress_step
from ditch_drake.systems.shared_control import SharedControl, SharedControlConfig

PERIOD = robot.CONTROL_PERIOD_S


def _states(distances) -> list[Progress]:
    """`progress_step` over `distances`, from no anchor: the state after each step."""
    state, states = Progress(), []
    for distance in distances:
        state = progress_step(state, distance, PERIOD)
        states.append(state)
    return states


def _fold(distances) -> list[float]:
    """The seconds without progress after each step."""
    return [state.stalled_s for state in _states(distances)]


def _regress(distances) -> list[float]:
    """The metres fallen back after each step."""
    return [state.regressed_m for state in _states(distances)]


def test_progress_is_a_fall_of_a_quarter_metre_below_where_it_was_last_seen():
    assert PROGRESS_STEP_M == 0.25
    # 0.1 m nearer each step: progress every third step.
    np.testing.assert_allclose(_fold([10.0, 9.9, 9.8, 9.7, 9.6, 9.5, 9.4]), [0, 0.1, 0.2, 0, 0.1, 0.2, 0])
    # Past the goal and back: the count grows until the robot is nearer than the anchor by the step.
    counts = _fold([2.0, 1.0, 1.5, 2.0, 1.5, 1.0, 0.8, 0.7])
    np.testing.assert_allclose(counts, [0, 0, 0.1, 0.2, 0.3, 0.4, 0.5, 0])
    # Circling at a constant distance never progresses.
    assert _fold([3.0] * 11)[-1] == pytest.approx(1.0)


def test_the_metres_fallen_back_hold_their_peak_until_progress():
    # Past the goal and back: they rise with the distance above the anchor (2.0 after the second
    # step's 1.0), hold their peak on the way back, and restart with progress.
    np.testing.assert_allclose(_regress([2.0, 1.0, 1.5, 2.0, 1.5, 1.0, 0.8, 0.7]), [0, 0, 0.5, 1.0, 1.0, 1.0, 1.0, 0])
    # A distance below the anchor by less than the progress step is no fall back, and no progress.
    np.testing.assert_allclose(_regress([3.0, 2.9, 2.8, 2.7]), [0, 0, 0, 0])
    assert _states([3.0])[0] == Progress(3.0, 0.0, 0.0)


def test_the_block_counts_from_the_newest_distance_and_holds_between_ticks(tick_block):
    block = GoalProgress()
    context = block.CreateDefaultContext()
    assert block.GetOutputPort(PROGRESS_SIGNAL).Eval(context)[0] == 0  # Before any tick.
    assert block.GetOutputPort(REGRESS_SIGNAL).Eval(context)[0] == 0
    distances = [5.0, 4.9, 4.8, 4.7, 4.9, 5.2, 5.0, 4.6, 4.4]
    stacks = [[distance] + [99.0] * (STACK_DEPTH - 1) for distance in distances]  # Newest first.
    assert [tick_block(block, context, "distance_stack", stack, PROGRESS_SIGNAL) for stack in stacks] == _fold(distances)
    block.GetInputPort("distance_stack").FixValue(context, [0.0] * STACK_DEPTH)
    assert block.GetOutputPort(PROGRESS_SIGNAL).Eval(context)[0] == _fold(distances)[-1]
    assert block.GetOutputPort(REGRESS_SIGNAL).Eval(context)[0] == 0  # 4.4: progress.
    fresh = block.CreateDefaultContext()
    regressed = [tick_block(block, fresh, "distance_stack", stack, REGRESS_SIGNAL) for stack in stacks]
    assert regressed == _regress(distances)
    np.testing.assert_allclose(regressed, [0, 0, 0, 0, 0.2, 0.5, 0.5, 0.5, 0], atol=1e-12)  # 5.2 above 4.7.


def test_the_watchdog_hands_over_past_the_limit_whatever_the_signal_and_back_once_within_it():
    config = SharedControlConfig(upper_threshold=0.5, lower_threshold=0.2, calm_steps=2, warmup_steps=0,
                                 progress_limit_s=1.0)
    gate = SharedControl(config)
    context = gate.CreateDefaultContext()
    gate.GetInputPort("policy_command").FixValue(context, [1.0, 0.1])
    gate.GetInputPort("fallback_command").FixValue(context, [0.5, -0.3])
    state = gate.AllocateDiscreteVariables()
    script = [  # (uncertainty, seconds without progress, who drives after the step)
        (0.1, 0.0, POLICY),
        (0.1, 1.0, POLICY),  # At the limit, not past it.
        (0.1, 1.1, FALLBACK),  # Past it: handover, the signal calm.
        (0.1, 1.2, FALLBACK),  # Still past it: not a calm step.
        (0.1, 0.0, FALLBACK),  # Calm 1.
        (0.1, 0.1, POLICY),  # Calm 2: handback.
        (0.9, 0.0, FALLBACK),  # The signal alone still hands over.
    ]
    for step, (uncertainty, stalled, driver) in enumerate(script):
        gate.GetInputPort("uncertainty").FixValue(context, [uncertainty])
        gate.GetInputPort(PROGRESS_SIGNAL).FixValue(context, [stalled])
        gate.CalcForcedDiscreteVariableUpdate(context, state)
        context.SetDiscreteState(state)
        assert gate.GetOutputPort("who_drives").Eval(context)[0] == driver, f"step {step}"
    assert gate.GetOutputPort("switches").Eval(context)[0] == 3
    # The same rule for replays: forced hands over, and is never calm.
    assert gate_step(POLICY, 0, 0.0, 0.5, 0.2, 2, forced=True) == (FALLBACK, 0, True)
    assert gate_step(FALLBACK, 1, 0.0, 0.5, 0.2, 2, forced=True) == (FALLBACK, 0, False)
    # Without a limit the gate has no such input, and its config's text is as before the watchdog.
    assert not SharedControl(SharedControlConfig()).HasInputPort(PROGRESS_SIGNAL)
    assert not SharedControl(config).HasInputPort(REGRESS_SIGNAL)
    assert "progress_limit_s" not in config_to_yaml(SharedControlConfig())
    assert "regress_limit_m" not in config_to_yaml(config)
    assert "progress_limit_s: 1.0" in config_to_yaml(config)


def test_either_watchdog_hands_over_and_the_fallback_keeps_the_robot_until_both_are_within():
    config = SharedControlConfig(upper_threshold=0.5, lower_threshold=0.2, calm_steps=2, warmup_steps=0,
                                 progress_limit_s=10.0, regress_limit_m=2.0)
    gate = SharedControl(config)
    context = gate.CreateDefaultContext()
    gate.GetInputPort("policy_command").FixValue(context, [1.0, 0.1])
    gate.GetInputPort("fallback_command").FixValue(context, [0.5, -0.3])
    gate.GetInputPort("uncertainty").FixValue(context, [0.1])
    state = gate.AllocateDiscreteVariables()
    script = [  # (seconds without progress, metres fallen back, who drives after the step)
        (1.0, 2.0, POLICY),  # Both at their limits, not past them.
        (1.1, 2.1, FALLBACK),  # The metres past theirs: handover.
        (1.2, 2.1, FALLBACK),  # Held at their peak until progress: not calm.
        (0.0, 0.0, FALLBACK),  # Progress: calm 1.
        (0.1, 0.0, POLICY),  # Calm 2: handback.
        (10.1, 0.0, FALLBACK),  # The seconds alone still hand over.
    ]
    for step, (stalled, regressed, driver) in enumerate(script):
        gate.GetInputPort(PROGRESS_SIGNAL).FixValue(context, [stalled])
        gate.GetInputPort(REGRESS_SIGNAL).FixValue(context, [regressed])
        gate.CalcForcedDiscreteVariableUpdate(context, state)
        context.SetDiscreteState(state)
        assert gate.GetOutputPort("who_drives").Eval(context)[0] == driver, f"step {step}"
    assert gate.GetOutputPort("switches").Eval(context)[0] == 3
    assert "regress_limit_m: 2.0" in config_to_yaml(config)
    # The metres alone, without the seconds: the gate has that input only.
    alone = SharedControl(dataclasses.replace(config, progress_limit_s=None))
    assert alone.HasInputPort(REGRESS_SIGNAL) and not alone.HasInputPort(PROGRESS_SIGNAL)


@pytest.mark.parametrize("fields, message", [
    ({"progress_limit_s": 0.0}, r"progress_limit_s 0.0: expected a number of seconds > 0"),
    ({"progress_limit_s": math.inf}, r"progress_limit_s inf: expected"),
    ({"progress_limit_s": True}, r"progress_limit_s True: expected"),
    ({"progress_limit_s": 5.0, "signal": PROGRESS_SIGNAL},
     r"progress_limit_s 5.0 with signal 'seconds_without_progress': the gate already reads"),
    ({"signal": PROGRESS_SIGNAL, "upper_threshold": -1.0, "lower_threshold": -2.0},
     r"upper_threshold -1.0 with signal 'seconds_without_progress', which is never negative"),
    ({"regress_limit_m": -3.0}, r"regress_limit_m -3.0: expected a number of metres > 0"),
    ({"regress_limit_m": math.nan}, r"regress_limit_m nan: expected"),
    ({"regress_limit_m": 3.0, "signal": REGRESS_SIGNAL},
     r"regress_limit_m 3.0 with signal 'metres_regressed': the gate already reads"),
    ({"signal": REGRESS_SIGNAL, "upper_threshold": 1.0, "lower_threshold": -0.5},
     r"lower_threshold -0.5 with signal 'metres_regressed', which is never negative"),
])
def test_bad_progress_settings_are_refused_naming_the_value(fields, message):
    with pytest.raises(ConfigError, match=message):
        SharedControlConfig(**fields).validate()


def _shared(**gate) -> SharedControlControllerConfig:
    config = controller_config("shared")
    return dataclasses.replace(config, policy=dataclasses.replace(config.policy, checkpoint="wide_bc40"),
                               gate=dataclasses.replace(config.gate, fallback="expert", **gate))


@pytest.mark.parametrize("signal, end_time_s, peak_range", [
    # The crossing's run along the ditch holds the robot at one distance for more than a second ...
    (PROGRESS_SIGNAL, 20.0, (1.0, 100.0)),
    # ... and after 23 s its turn along the ditch takes it a few centimetres farther from the goal.
    (REGRESS_SIGNAL, 25.0, (0.0, 0.5)),
])
def test_a_gate_on_either_count_reads_what_gate_signals_records_at_each_step(watched_gate_drive, signal, end_time_s,
                                                                             peak_range):
    # Thresholds above any count in the drive: the policy drives throughout, as in an ungated recording.
    config = _shared(signal=signal, upper_threshold=100.0, lower_threshold=50.0)
    recorder, read, _ = watched_gate_drive(config, "goal_progress", signal, end_time_s=end_time_s)
    recorded = recorder.values[signal]
    assert len(recorded) == len(recorder.time_s) >= 10 * (end_time_s - 1.0)
    assert recorded == read[-len(recorded):]
    assert peak_range[0] < max(recorded) < peak_range[1] and min(recorded) == 0.0


@pytest.mark.parametrize("watched, limit, end_time_s", [
    # Limits that the approach's steps between progress cross, and the turn along the ditch after 23 s.
    ({"progress_limit_s": 0.15}, 0.15, 3.0),
    ({"progress_limit_s": 60.0, "regress_limit_m": 0.05}, 0.05, 25.0),
])
def test_a_watchdog_in_a_built_diagram_hands_over_at_the_first_step_past_its_limit(watched, limit, end_time_s):
    # A signal that never hands over; the watchdog named last is the one that fires.
    config = _shared(signal="mean_softmax_entropy", upper_threshold=100.0, lower_threshold=50.0, **watched)
    signal = PROGRESS_SIGNAL if len(watched) == 1 else REGRESS_SIGNAL
    diagram, built = MakeRolloutDiagram(RolloutConfig(scene=SceneConfig(environment="wide", task=1),
                                                      controller=get_controller("shared").for_seed(config, 4)))
    gate, progress = diagram.GetSubsystemByName("shared_control"), diagram.GetSubsystemByName("goal_progress")
    steps = []

    def watch(root) -> bool:
        steps.append((progress.GetOutputPort(signal).Eval(progress.GetMyContextFromRoot(root))[0],
                      gate.GetOutputPort("who_drives").Eval(gate.GetMyContextFromRoot(root))[0]))
        return False

    RunEpisode(Simulator(diagram), diagram, built, 4, watch=watch, watch_period_s=PERIOD, end_time_s=end_time_s)
    warmup = config.gate.warmup_steps
    first = next(k for k, (value, _) in enumerate(steps) if k >= warmup and value > limit)
    assert all(driver == POLICY for _, driver in steps[:first]) and steps[first][1] == FALLBACK, steps


def test_gate_peaks_prints_each_outcomes_peaks_past_the_warm_up(tmp_path, capsys):
    from ditch_drake.cli import main
    from ditch_drake.learning.gate_calibration import episode_peaks, load_signals, save_signals

    # Three episodes of four steps: two that reached the goal, one that timed out circling.
    stalled = [9.0, 0.0, 0.5, 1.0, 9.0, 0.2, 2.0, 0.1, 9.0, 3.0, 6.0, 9.5]
    path = save_signals(tmp_path / "s.npz", "wide_bc40", "0" * 16, {PROGRESS_SIGNAL: stalled},
                        {"time_s": [0.003, 0.103, 0.203, 0.303] * 3, "episode": [0] * 4 + [1] * 4 + [2] * 4},
                        {"episode_environment": ["wide"] * 3, "episode_task": [1] * 3, "episode_seed": [0, 1, 2],
                         "episode_status": ["reached_goal", "reached_goal", "timeout"],
                         "episode_end_time_s": [0.4, 0.4, 120.0]})
    rows = episode_peaks(load_signals(path), PROGRESS_SIGNAL, warmup_steps=1)
    assert [(row["status"], row["episodes"], row["least_peak"], row["median_peak"], row["largest_peak"])
            for row in rows] == [("reached_goal", 2, 1.0, 1.5, 2.0), ("timeout", 1, 9.5, 9.5, 9.5)]
    assert episode_peaks(load_signals(path), PROGRESS_SIGNAL)[0]["least_peak"] == 9.0  # The first steps counted.
    assert main(["gate-peaks", str(path), "--warmup-steps", "1"]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert printed[1].split() == [PROGRESS_SIGNAL, "reached_goal", "2", "1", "1.5", "2"]
    assert main(["gate-peaks", str(path), "--signal", "tip_risk_ahead"]) == 2
    assert "--signal tip_risk_ahead" in capsys.readouterr().err
