"""The reversals of the policy's commanded turn over the last second: the count, the block that
gives it a gate, and `gate-signals`, which records the same count."""

import dataclasses

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator

from ditch_drake.cli import main
from ditch_drake.common.errors import ConfigError
from ditch_drake.diagrams.controllers import controller_config, get_controller
from ditch_drake.diagrams.ditch_scene import SceneConfig
from ditch_drake.diagrams.rollout import MakeRolloutDiagram, RolloutConfig
from ditch_drake.diagrams.shared_controller import SharedControlControllerConfig
from ditch_drake.learning.gate_calibration import FALLBACK, POLICY, load_signals, save_signals
from ditch_drake.learning.uncertainty import PROGRESS_SIGNAL, REGRESS_SIGNAL, REVERSAL_SIGNAL
from ditch_drake.systems.command_reversals import REVERSAL_WINDOW_STEPS, CommandReversals, count_reversals
from ditch_drake.systems.shared_control import SharedControlConfig


@pytest.mark.parametrize("rates, expected", [
    ([], 0), ([0.0, 0.0], 0), ([0.3, 0.6, 0.3], 0),
    ([0.3, -0.3, 0.3, -0.3], 3),
    ([0.3, 0.0, -0.3], 1),  # A straight-ahead command between two turns is skipped.
    ([-0.6, 0.0, 0.0, -0.3, 0.6], 1),
])
def test_a_reversal_is_a_change_of_the_turns_sign_straight_commands_skipped(rates, expected):
    assert count_reversals(rates) == expected


def test_the_block_counts_over_the_window_ending_with_the_last_command(tick_block):
    block = CommandReversals()
    context = block.CreateDefaultContext()
    assert block.GetOutputPort(REVERSAL_SIGNAL).Eval(context)[0] == 0  # Before any command.
    rates = [0.3, -0.3] * 8 + [0.3] * 12 + [0.0, -0.3]
    seen = [tick_block(block, context, "command", [0.5, rate], REVERSAL_SIGNAL) for rate in rates]
    assert seen == [count_reversals(rates[max(0, step + 1 - REVERSAL_WINDOW_STEPS):step + 1])
                    for step in range(len(rates))]
    # Alternating turns fill the 1 s window with 9 reversals; 10 steps of one turn clear it; left,
    # straight, right is one.
    assert max(seen) == REVERSAL_WINDOW_STEPS - 1 and seen[16 + REVERSAL_WINDOW_STEPS - 1] == 0
    assert seen[-3:] == [0, 0, 1]
    # The count holds between ticks, whatever the command does meanwhile.
    block.GetInputPort("command").FixValue(context, [0.5, 0.6])
    assert block.GetOutputPort(REVERSAL_SIGNAL).Eval(context)[0] == 1


def _reversal_gate(upper: float, lower: float) -> SharedControlControllerConfig:
    config = controller_config("shared")
    return dataclasses.replace(config, policy=dataclasses.replace(config.policy, checkpoint="wide_bc40"),
                               gate=dataclasses.replace(config.gate, signal=REVERSAL_SIGNAL, upper_threshold=upper,
                                                        lower_threshold=lower, fallback="expert"))


def test_a_reversal_gate_reads_the_count_gate_signals_records_at_each_step(watched_gate_drive):
    # Thresholds above any count: the policy drives throughout, as in an ungated recording.
    # This drive's turn first reverses after about 20 s.
    recorder, read, commanded = watched_gate_drive(_reversal_gate(upper=100.0, lower=50.0), REVERSAL_SIGNAL,
                                                   REVERSAL_SIGNAL, end_time_s=25.0)
    recorded = recorder.values[REVERSAL_SIGNAL]
    assert len(recorded) == len(recorder.time_s) >= 200 and max(recorded) >= 1
    # The watch sees the gate's input once its tick has passed: what it recorded at each step.
    assert recorded == read[-len(recorded):]
    assert recorded == [count_reversals(commanded[-len(recorded):][max(0, k + 1 - REVERSAL_WINDOW_STEPS):k + 1])
                        for k in range(len(recorded))]


def test_a_reversal_gate_hands_over_once_the_turn_reverses():
    with pytest.raises(ConfigError, match="upper_threshold -0.5 with signal 'command_reversals'"):
        SharedControlConfig(signal=REVERSAL_SIGNAL, upper_threshold=-0.5, lower_threshold=-1.0).validate()
    # Above 0: the first reversal hands over.
    config = _reversal_gate(upper=0.0, lower=0.0)
    diagram, _ = MakeRolloutDiagram(RolloutConfig(scene=SceneConfig(environment="wide", task=1),
                                                  controller=get_controller("shared").for_seed(config, 4)))
    gate, reversals = diagram.GetSubsystemByName("shared_control"), diagram.GetSubsystemByName(REVERSAL_SIGNAL)
    simulator = Simulator(diagram)
    steps = []
    for t in np.arange(0.1, 30.0, 0.1):  # This drive's turn first reverses after about 20 s.
        simulator.AdvanceTo(t)
        root = simulator.get_context()
        steps.append((reversals.GetOutputPort(REVERSAL_SIGNAL).Eval(reversals.GetMyContextFromRoot(root))[0],
                      gate.GetOutputPort("who_drives").Eval(gate.GetMyContextFromRoot(root))[0]))
    first = next(k for k, (count, _) in enumerate(steps) if count > 0)
    assert all(driver == POLICY for _, driver in steps[:first]) and steps[first][1] == FALLBACK, steps


def test_gate_signals_records_the_reversals_of_a_single_clone(tmp_path):
    out = tmp_path / "signals.npz"
    assert main(["gate-signals", "--workers", "0", "--checkpoint", "wide_bc40", "--env", "wide", "--task", "1",
                 "--rollouts", "1", "--seed", "4", "--time-limit", "4", "--out", str(out)]) == 0
    signals = load_signals(out)
    assert signals["signals"] == ["mean_softmax_entropy", REVERSAL_SIGNAL, PROGRESS_SIGNAL, REGRESS_SIGNAL]
    counts = signals[REVERSAL_SIGNAL]
    assert counts.shape == signals["time_s"].shape
    assert np.all((counts >= 0) & (counts <= REVERSAL_WINDOW_STEPS - 1) & (counts == np.round(counts)))


def test_a_reversal_gate_on_a_recording_made_before_the_signal_is_refused_naming_it(tmp_path):
    # A file as gate-signals wrote them before it recorded the reversals: the uncertainty signal only.
    older = save_signals(tmp_path / "older.npz", "wide_bc40", "0" * 16, {"mean_softmax_entropy": [0.1, 0.2]},
                         {"time_s": [0.003, 0.103], "episode": [0, 0]},
                         {"episode_environment": ["wide"], "episode_task": [1], "episode_seed": [4],
                          "episode_status": ["timeout"], "episode_end_time_s": [0.2]})
    gate = SharedControlConfig(signal=REVERSAL_SIGNAL, budget=0.05, calibration=str(older))
    with pytest.raises(ConfigError, match="has no signal 'command_reversals'.*record it again"):
        gate.resolved()
