"""The uncertainty gate: hysteresis on a scripted uncertainty, its switch count, the executed
command, `who_drives` in a simulated diagram, and its config's bad values."""

import math

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource, TrajectorySource
from pydrake.trajectories import PiecewisePolynomial

from ditch_drake.common.errors import ConfigError
from ditch_drake.learning.gate_calibration import replay_fallback_share, save_signals
from ditch_drake.spec import robot
from ditch_drake.systems.shared_control import FALLBACK, GATE_OFFSET_S, POLICY, SharedControl, SharedControlConfig

POLICY_COMMAND = [1.0, 0.15]
FALLBACK_COMMAND = [0.5, -0.35]
CONFIG = SharedControlConfig(upper_threshold=0.5, lower_threshold=0.2, calm_steps=3, warmup_steps=0)
# A scripted uncertainty, and who drives after each step under CONFIG.
SCRIPT = [
    (0.1, POLICY),
    (0.5, POLICY),  # At the upper threshold, not above it: no handover.
    (0.6, FALLBACK),  # Handover 1.
    (0.3, FALLBACK),  # Below upper but not below lower: not calm.
    (0.1, FALLBACK),  # Calm 1.
    (0.1, FALLBACK),  # Calm 2.
    (0.3, FALLBACK),  # The count starts again.
    (math.nan, FALLBACK),  # Neither: the count stays at 0.
    (0.1, FALLBACK),
    (0.1, FALLBACK),
    (0.15, POLICY),  # Calm 3: handback, switch 2.
    (0.4, POLICY),
    (0.9, FALLBACK),  # Switch 3.
    (0.0, FALLBACK),
]


def test_the_gate_hands_over_holds_and_hands_back_after_the_calm_steps():
    gate = SharedControl(CONFIG)
    context = gate.CreateDefaultContext()
    gate.GetInputPort("policy_command").FixValue(context, POLICY_COMMAND)
    gate.GetInputPort("fallback_command").FixValue(context, FALLBACK_COMMAND)
    uncertainty = gate.GetInputPort("uncertainty")
    # Before the first update: the policy drives and the command is to stand still.
    assert gate.GetOutputPort("who_drives").Eval(context)[0] == POLICY
    np.testing.assert_array_equal(gate.GetOutputPort("command").Eval(context), [0.0, 0.0])
    state = gate.AllocateDiscreteVariables()
    switches = 0
    for step, (value, driver) in enumerate(SCRIPT):
        uncertainty.FixValue(context, [value])
        gate.CalcForcedDiscreteVariableUpdate(context, state)
        context.SetDiscreteState(state)
        who = gate.GetOutputPort("who_drives").Eval(context)[0]
        assert who == driver, f"step {step}: uncertainty {value}"
        switches += step > 0 and driver != SCRIPT[step - 1][1]
        assert gate.GetOutputPort("switches").Eval(context)[0] == switches
        expected = POLICY_COMMAND if driver == POLICY else FALLBACK_COMMAND
        np.testing.assert_array_equal(gate.GetOutputPort("command").Eval(context), expected)
    assert switches == 3


def _drivers(config: SharedControlConfig, uncertainties: list[float]) -> list[int]:
    """Who drives after each forced update of a gate fed `uncertainties` in turn."""
    gate = SharedControl(config)
    context = gate.CreateDefaultContext()
    gate.GetInputPort("policy_command").FixValue(context, POLICY_COMMAND)
    gate.GetInputPort("fallback_command").FixValue(context, FALLBACK_COMMAND)
    state = gate.AllocateDiscreteVariables()
    drivers = []
    for value in uncertainties:
        gate.GetInputPort("uncertainty").FixValue(context, [value])
        gate.CalcForcedDiscreteVariableUpdate(context, state)
        context.SetDiscreteState(state)
        drivers.append(int(gate.GetOutputPort("who_drives").Eval(context)[0]))
    return drivers


def test_the_gate_ignores_the_signal_while_the_stacks_fill():
    # The policy's members disagree on partly empty observation stacks: the default gate reads
    # nothing over its first STACK_DEPTH - 1 = 3 updates, then gates as usual.
    assert SharedControlConfig().warmup_steps == 3
    script = [0.9, 0.9, 0.9, 0.1, 0.9, 0.1]
    config = SharedControlConfig(upper_threshold=0.5, lower_threshold=0.2, calm_steps=2)
    assert _drivers(config, script) == [POLICY, POLICY, POLICY, POLICY, FALLBACK, FALLBACK]
    assert _drivers(SharedControlConfig(upper_threshold=0.5, lower_threshold=0.2, calm_steps=2, warmup_steps=0),
                    script) == [FALLBACK, FALLBACK, FALLBACK, FALLBACK, FALLBACK, FALLBACK]
    # The replay that sets a budget's thresholds ignores the same steps.
    assert replay_fallback_share([script], 0.5, 0.2, 2, warmup_steps=3) == pytest.approx(2 / 6)
    assert replay_fallback_share([script], 0.5, 0.2, 2) == pytest.approx(1.0)
    with pytest.raises(ConfigError, match="warmup_steps -1: expected an integer >= 0"):
        SharedControlConfig(warmup_steps=-1).validate()


def test_who_drives_in_a_simulated_diagram_changes_at_the_gates_ticks():
    period = robot.CONTROL_PERIOD_S
    # The uncertainty is high during [0.25, 0.45) s, low afterwards.
    breaks = [0.0, 0.25, 0.45, 5.0]
    values = np.array([[0.0, 1.0, 0.0, 0.0]])
    builder = DiagramBuilder()
    uncertainty = builder.AddNamedSystem("uncertainty", TrajectorySource(PiecewisePolynomial.ZeroOrderHold(breaks,
                                                                                                          values)))
    policy = builder.AddNamedSystem("policy", ConstantVectorSource(POLICY_COMMAND))
    fallback = builder.AddNamedSystem("fallback", ConstantVectorSource(FALLBACK_COMMAND))
    gate = builder.AddNamedSystem("shared_control", SharedControl(CONFIG))
    builder.Connect(uncertainty.get_output_port(), gate.GetInputPort("uncertainty"))
    builder.Connect(policy.get_output_port(), gate.GetInputPort("policy_command"))
    builder.Connect(fallback.get_output_port(), gate.GetInputPort("fallback_command"))
    builder.ExportOutput(gate.GetOutputPort("who_drives"), "who_drives")
    builder.ExportOutput(gate.GetOutputPort("command"), "command")
    diagram = builder.Build()
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    ticks = GATE_OFFSET_S + period * np.arange(12)
    drivers = []
    for tick in ticks:
        simulator.AdvanceTo(tick + period / 2)
        drivers.append(int(diagram.GetOutputPort("who_drives").Eval(context)[0]))
        expected = POLICY_COMMAND if drivers[-1] == POLICY else FALLBACK_COMMAND
        np.testing.assert_array_equal(diagram.GetOutputPort("command").Eval(context), expected)
    # High at ticks 3 and 4 (0.3035, 0.4035 s); calm from tick 5, three calm ticks: back at tick 7.
    assert drivers == [0, 0, 0, 1, 1, 1, 1, 0, 0, 0, 0, 0]
    assert gate.GetOutputPort("switches").Eval(gate.GetMyContextFromRoot(context))[0] == 2


def test_bad_configs_are_refused_naming_the_value():
    SharedControlConfig().validate()
    bad = {
        "lower_threshold 0.6 > upper_threshold 0.5": {"upper_threshold": 0.5, "lower_threshold": 0.6},
        "calm_steps 0: expected an integer >= 1": {"calm_steps": 0},
        r"budget 1.5: expected a share of control steps in \(0, 1\)": {"budget": 1.5, "calibration": "s.npz"},
        r"budget -0.1": {"budget": -0.1, "calibration": "s.npz"},
        r"budget 0: expected": {"budget": 0, "calibration": "s.npz"},
        r"budget 1.0: expected": {"budget": 1.0, "calibration": "s.npz"},
        "budget 0.05 without a calibration": {"budget": 0.05},
        "calibration 's.npz' without a budget": {"calibration": "s.npz"},
        "signal 'spread': expected one of": {"signal": "spread"},
        "fallback 'person': expected one of": {"fallback": "person"},
        "upper_threshold nan: expected a number": {"upper_threshold": math.nan},
    }
    for message, fields in bad.items():
        with pytest.raises(ConfigError, match=message):
            SharedControlConfig(**fields).validate()
        with pytest.raises(ConfigError, match=message):
            SharedControl(SharedControlConfig(**fields))


def test_a_budget_sets_the_thresholds_from_its_calibration_file(tmp_path):
    values = np.linspace(0.0, 1.0, 101)
    path = tmp_path / "signals.npz"
    save_signals(path, "wide", "0" * 16, {"angular_rate_spread": values}, {"time_s": values, "episode": [0] * 101},
                 {"episode_environment": ["wide"], "episode_task": [1], "episode_seed": [0],
                  "episode_status": ["timeout"], "episode_end_time_s": [10.0]})
    config = SharedControlConfig(budget=0.1, calibration=str(path), lower_threshold=0.95, upper_threshold=0.0)
    config.validate()  # The fixed thresholds' order does not matter: the budget sets both.
    resolved = config.resolved()
    assert resolved.upper_threshold == pytest.approx(0.9) and resolved.lower_threshold == pytest.approx(0.8)
    assert (resolved.budget, resolved.calibration) == (0.1, str(path))  # It says where they came from.
    assert resolved.resolved() == resolved
    assert SharedControl(config).config == resolved
    fixed = SharedControlConfig()
    assert fixed.resolved() is fixed
    with pytest.raises(ConfigError, match="gate.calibration .*missing.npz: cannot read it"):
        SharedControl(SharedControlConfig(budget=0.05, calibration=str(tmp_path / "missing.npz")))
    with pytest.raises(ConfigError, match="gate.calibration .* has no signal 'vote_entropy': it recorded "
                                          r"\['angular_rate_spread'\]"):
        SharedControlConfig(signal="vote_entropy", budget=0.05, calibration=str(path)).resolved()