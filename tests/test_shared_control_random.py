"""The random-handover control of the shared gate (signal "random"): its thresholds from a
budget, its bad values, the fallback's share with hysteresis, the seeded draw in a built
shared diagram (same seed, same handovers; another seed, or another ditch or task, others), the
keyed draw's uniformity, and a short rollout through the batch path."""

import dataclasses
import re

import numpy as np
import pytest
import yaml
from pydrake.common import RandomGenerator
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource
from scipy import stats

from ditch_drake.cli import main
from ditch_drake.common.errors import ConfigError
from ditch_drake.diagrams.controllers import controller_config, get_controller
from ditch_drake.diagrams.ditch_scene import SceneConfig
from ditch_drake.diagrams.rollout import MakeRolloutDiagram, RolloutConfig, StartEpisode
from ditch_drake.diagrams.shared_controller import AddRandomHandoverDraw, SharedControlControllerConfig
from ditch_drake.evaluation.batch import evaluate, make_specs
from ditch_drake.evaluation.results import read_records
from ditch_drake.spec import robot
from ditch_drake.systems.keyed_uniform import KeyedUniform
from ditch_drake.systems.shared_control import (
    FALLBACK,
    GATE_OFFSET_S,
    POLICY,
    RANDOM_SIGNAL,
    SharedControl,
    SharedControlConfig,
    random_fallback_share,
)

DRAW = "random_handover_draw"


def _random_shared(budget: float = 0.5, lower_threshold: float = 0.5, calm_steps: int = 1,
                   ) -> SharedControlControllerConfig:
    """The shared controller handing over at random; by default each step's driver is its own
    draw's (a fair coin: the fallback where the draw is above 0.5)."""
    config = controller_config("shared")
    return dataclasses.replace(config, gate=dataclasses.replace(
        config.gate, signal=RANDOM_SIGNAL, budget=budget, lower_threshold=lower_threshold, calm_steps=calm_steps))


def test_a_budget_sets_the_upper_threshold_of_the_draw_without_a_calibration():
    # Without hysteresis the draw is above 1 - budget on the budget's share of the steps.
    assert SharedControlConfig(signal="random", budget=0.05, lower_threshold=0.95, calm_steps=1).resolved(
        ).upper_threshold == pytest.approx(0.95)
    gate = SharedControlConfig(signal="random", budget=0.05, lower_threshold=0.9, calm_steps=5).resolved()
    # Five calm draws below 0.9 hold the fallback (1 - 0.9^5) / (0.1 x 0.9^5) = 6.935 steps on
    # average, so a handover may come with chance 0.05 / (0.95 x 6.935) = 0.00759 a step.
    assert gate.upper_threshold == pytest.approx(1.0 - 0.05 / (0.95 * 6.9351), abs=1e-5)
    assert random_fallback_share(gate.upper_threshold, 0.9, 5) == pytest.approx(0.05)
    assert (gate.lower_threshold, gate.calm_steps, gate.budget, gate.calibration) == (0.9, 5, 0.05, "")
    assert gate.resolved() == gate
    fixed = SharedControlConfig(signal="random", upper_threshold=0.8, lower_threshold=0.3)
    assert fixed.resolved() is fixed
    # The other signals' budget still needs its calibration file.
    with pytest.raises(ConfigError, match="budget 0.05 without a calibration"):
        SharedControlConfig(signal="mean_softmax_entropy", budget=0.05).validate()
    # The controller's config resolves with no file to check against the policy.
    shared = dataclasses.replace(_random_shared(0.05, 0.9), policy=controller_config("shared").policy.with_checkpoint(
        "wide"))
    assert shared.resolved().gate.upper_threshold == pytest.approx(1.0 - 0.05 * 0.9 / 0.95)  # Spells of 1 / 0.9.


@pytest.mark.parametrize("gate, message", [
    ({"calibration": "signals.npz", "budget": 0.05, "lower_threshold": 0.9},
     "calibration 'signals.npz' with signal 'random'"),
    ({"budget": 0.05, "lower_threshold": 2.3}, r"lower_threshold 2.3 with signal 'random': expected a number in \[0, 1\]"),
    ({"budget": 0.5, "lower_threshold": 0.9, "calm_steps": 1},
     r"lower_threshold 0.9 > the budget 0.5's upper threshold 0.1 with signal 'random'"),
    ({"budget": 0.9, "lower_threshold": 0.5, "calm_steps": 1},
     r"budget 0.9 with signal 'random', lower_threshold 0.5 and calm_steps 1: .* expected a budget of at most 0.667"),
    ({"upper_threshold": 1.5, "lower_threshold": 0.5}, "upper_threshold 1.5 with signal 'random'"),
    ({"upper_threshold": 0.4, "lower_threshold": 0.5}, "lower_threshold 0.5 > upper_threshold 0.4"),
    ({"budget": 1.0, "lower_threshold": 0.5}, r"budget 1.0: expected a share of control steps in \(0, 1\)"),
    ({"budget": 0.05, "lower_threshold": float("nan")}, "lower_threshold nan: expected a number"),
])
def test_bad_random_gates_are_refused_naming_the_value(gate, message):
    with pytest.raises(ConfigError, match=message):
        SharedControlConfig(signal="random", **gate).resolved()


def test_a_random_gate_with_a_threshold_outside_0_1_exits_2(tmp_path, capsys):
    out = tmp_path / "r.jsonl"
    override = "{controller: !SharedControlControllerConfig {gate: {signal: random, budget: 0.05, lower_threshold: 2.3}}}"
    code = main(["evaluate", "--override", override, "--env", "wide", "--task", "1", "--rollouts", "1", "--workers",
                 "0", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1 and re.search(r"lower_threshold 2\.3 with signal 'random'", err), err
    assert not out.exists() or out.read_text() == ""


def _gate_with_draws(gate_config: SharedControlConfig, seed: int, steps: int) -> list[int]:
    """Who drives after each of `steps` ticks of the gate fed the random draw and two fixed
    commands, the diagram seeded with `seed`."""
    builder = DiagramBuilder()
    gate = builder.AddNamedSystem("shared_control", SharedControl(gate_config))
    for port, command in (("policy_command", [1.0, 0.0]), ("fallback_command", [0.5, 0.3])):
        source = builder.AddSystem(ConstantVectorSource(command))
        builder.Connect(source.get_output_port(), gate.GetInputPort(port))
    AddRandomHandoverDraw(builder, gate, robot.CONTROL_PERIOD_S, "wide/task1")
    diagram = builder.Build()
    simulator = Simulator(diagram)
    diagram.SetRandomContext(simulator.get_mutable_context(), RandomGenerator(seed))
    simulator.Initialize()
    gate_context = gate.GetMyContextFromRoot(simulator.get_context())
    drivers = []
    for k in range(steps):
        simulator.AdvanceTo(GATE_OFFSET_S + (k + 0.5) * robot.CONTROL_PERIOD_S)
        drivers.append(int(gate.GetOutputPort("who_drives").Eval(gate_context)[0]))
    return drivers


@pytest.mark.parametrize("budget, lower, calm_steps", [(0.05, 0.95, 1), (0.05, 0.9, 5), (0.2, 0.8, 3)])
def test_the_fallbacks_share_of_random_handovers_is_the_expected_one(budget, lower, calm_steps):
    gate = SharedControlConfig(signal="random", budget=budget, lower_threshold=lower, calm_steps=calm_steps)
    drivers = _gate_with_draws(gate, seed=11, steps=4000)
    # 4000 steps hold tens of handover cycles or more: the share within a few points of the budget.
    assert np.mean(drivers) == pytest.approx(budget, abs=0.03)
    assert set(drivers) == {POLICY, FALLBACK}


def test_the_expected_share_is_the_budget_only_without_hysteresis():
    assert random_fallback_share(0.95, 0.95, 1) == pytest.approx(0.05)
    assert random_fallback_share(0.95, 0.9, 5) == pytest.approx(0.2575, abs=1e-4)
    # p = q = 1/2, two calm steps: fallback spells of (1 - 1/4) / (1/2 * 1/4) = 6 steps, policy ones of 2.
    assert random_fallback_share(0.5, 0.5, 2) == pytest.approx(0.75)
    assert (random_fallback_share(1.0, 0.5, 1), random_fallback_share(0.5, 0.0, 1)) == (0.0, 1.0)
    with pytest.raises(ConfigError, match="calm_steps 0"):
        random_fallback_share(0.95, 0.9, 0)


def _drivers_and_draws(simulator: Simulator, diagram, seed: int, steps: int) -> tuple[list[int], list[float]]:
    """Who drives and the draw the gate read, at each of the first `steps` gate ticks of the
    episode of `seed` (started as every rollout is, `StartEpisode`)."""
    gate, draw = diagram.GetSubsystemByName("shared_control"), diagram.GetSubsystemByName(DRAW)
    StartEpisode(simulator, diagram, seed)
    context = simulator.get_context()
    gate_context, draw_context = gate.GetMyContextFromRoot(context), draw.GetMyContextFromRoot(context)
    drivers, draws = [], []
    for k in range(steps):
        tick = (k + 0.5) * robot.CONTROL_PERIOD_S + GATE_OFFSET_S
        simulator.AdvanceTo(tick)
        drivers.append(int(gate.GetOutputPort("who_drives").Eval(gate_context)[0]))
        draws.append(float(draw.get_output_port().Eval(draw_context)[0]))
    return drivers, draws


def test_the_seed_decides_the_random_handovers_in_a_built_shared_diagram():
    shared = get_controller("shared")
    scene = SceneConfig(environment="wide", task=1)
    default, _ = MakeRolloutDiagram(RolloutConfig(scene=scene, controller=shared.for_seed(controller_config("shared"),
                                                                                         0)))
    assert not default.HasSubsystemNamed(DRAW)  # Only the random gate has the draw.
    diagram, _ = MakeRolloutDiagram(RolloutConfig(scene=scene, controller=shared.for_seed(_random_shared(), 0)))
    simulator = Simulator(diagram)
    first, draws = _drivers_and_draws(simulator, diagram, seed=0, steps=10)
    again, draws_again = _drivers_and_draws(simulator, diagram, seed=0, steps=10)
    other, other_draws = _drivers_and_draws(simulator, diagram, seed=1, steps=10)
    assert (again, draws_again) == (first, draws)
    assert other != first and other_draws != draws
    # Upper = lower = 0.5, one calm step: after the warm-up's three ticks, when the policy
    # drives whatever the draw, each tick's driver is its own draw's.
    warmup = SharedControlConfig().warmup_steps
    for drivers, values in ((first, draws), (other, other_draws)):
        assert all(0.0 <= value < 1.0 for value in values)
        assert drivers == [POLICY] * warmup + [FALLBACK if value > 0.5 else POLICY for value in values[warmup:]]


def test_a_keyed_draw_is_uniform_repeatable_and_the_keys_own():
    draws = np.random.default_rng(5).random(4000)
    one, other = KeyedUniform("ditch_2000/task0"), KeyedUniform("ditch_2001/task0")
    keyed = np.array([one.keyed(draw) for draw in draws])
    assert np.all((keyed >= 0.0) & (keyed < 1.0))
    assert stats.kstest(keyed, "uniform").pvalue > 1e-3
    assert abs(stats.pearsonr(keyed[:-1], keyed[1:]).statistic) < 0.1  # Step to step, as the input.
    assert [one.keyed(draw) for draw in draws[:5]] == list(keyed[:5])
    others = np.array([other.keyed(draw) for draw in draws])
    assert abs(stats.pearsonr(keyed, others).statistic) < 0.1  # Another key: unrelated draws.
    assert np.mean((keyed > 0.95) & (others > 0.95)) < 0.01  # Not handing over together.


def test_one_seed_draws_differently_in_another_ditch_or_task():
    shared = get_controller("shared")
    results = {}
    for environment, task in (("wide", 1), ("wide", 2), ("narrow", 1)):
        scene = SceneConfig(environment=environment, task=task)
        diagram, _ = MakeRolloutDiagram(RolloutConfig(scene=scene, controller=shared.for_seed(_random_shared(), 0)))
        assert diagram.GetSubsystemByName(DRAW).key == f"{environment}/task{task}"
        results[environment, task] = _drivers_and_draws(Simulator(diagram), diagram, seed=0, steps=6)[1]
    assert len({tuple(draws) for draws in results.values()}) == 3


def test_a_short_random_shared_rollout_through_the_batch_path_records_its_handover_fraction(tmp_path):
    out = tmp_path / "random.jsonl"
    specs = make_specs(_random_shared(), "", "wide", [1], rollouts=2, time_limit_s=2.0)
    evaluate(specs, out, workers=0, progress=False)
    records, _ = read_records(out)
    assert [record.seed for record in records] == [0, 1]
    for record in records:
        assert record.controller == "shared" and record.status == "timeout"
        assert 0.0 < record.handover_fraction < 1.0 and record.switches >= 1
        gate = yaml.safe_load(record.controller_config)["gate"]
        assert (gate["signal"], gate["budget"], gate["upper_threshold"], gate["lower_threshold"]) == (
            "random", 0.5, 0.5, 0.5)
        assert "calibration" not in gate
