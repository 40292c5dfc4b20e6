"""Shared fixtures: scenes are built once per test session where tests only read them."""

from pathlib import Path

import numpy as np
import pytest

from ditch_drake.demos.dataset import Demonstration, standard_metadata
from ditch_drake.diagrams.ditch_scene import MakeDitchDiagram, SceneConfig
from ditch_drake.evaluation import batch, rollout_worker
from ditch_drake.spec import actions


@pytest.fixture(scope="session")
def wide_diagram():
    return MakeDitchDiagram(SceneConfig(environment="wide"))


@pytest.fixture
def recorded_pools(monkeypatch) -> list[tuple[int, int]]:
    """Replaces the batch evaluation's worker pools by a stub that records (rollouts, workers)
    of each pool started and keeps a "not run" error record for every rollout."""
    pools = []

    def fake_pool(specs, workers, keep):
        pools.append((len(specs), workers))
        for spec in specs:
            keep(rollout_worker.error_record(spec, "not run", 0.0))
        return []

    monkeypatch.setattr(batch, "_run_pool", fake_pool)
    return pools


@pytest.fixture
def session_processes():
    """A function: the processes of a session (its leader's pid) still alive, "pid command" each
    (Linux /proc); a signal test asserts that none outlived the command."""
    return _session_processes


def _session_processes(session: int) -> list[str]:
    """The processes of `session` still alive (Linux /proc): "pid command" each."""
    alive = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rpartition(")")[2].split()
            command = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
        except OSError:
            continue
        if int(fields[3]) == session and fields[0] != "Z":
            alive.append(f"{entry.name} {command[:80]}")
    return alive


def _random_demonstration(seed: int, steps: int) -> Demonstration:
    rng = np.random.default_rng(seed)
    labels = np.where(rng.random(steps) < 0.6, actions.STRAIGHT_LABEL, rng.integers(0, actions.NUM_LABELS, steps))
    arrays = {
        "image": rng.integers(0, 256, (steps, 128, 128), dtype=np.uint8),
        "imu_stack": rng.normal(size=(steps, 8)).astype(np.float32),
        "distance_stack": rng.uniform(0, 20, (steps, 4)).astype(np.float32),
        "bearing_stack": rng.uniform(-3, 3, (steps, 4)).astype(np.float32),
        "label": labels.astype(np.int16),
        "time_s": np.arange(steps) * 0.1,
        "pose": rng.normal(size=(steps, 6)).astype(np.float32),
        "raw_command": rng.normal(size=(steps, 2)).astype(np.float32),
    }
    metadata = standard_metadata(environment="wide", task={"index": seed % 3, "name": "t"}, seed=seed,
                                 outcome={"status": "reached_goal"}, control_period_s=0.1)
    return Demonstration(arrays, metadata)


@pytest.fixture
def random_demonstration():
    """`random_demonstration(seed, steps)`: a seeded Demonstration of `steps` random frames and
    scalars, 60 % of its labels straight ahead, for the training and dataset tests."""
    return _random_demonstration


@pytest.fixture
def tick_block():
    """A function that fixes `value` at a block's `input_name`, runs its one periodic update on
    `context` and returns its `output_name` after it: one control step of a signal block."""
    def tick(block, context, input_name: str, value, output_name: str) -> float:
        block.GetInputPort(input_name).FixValue(context, value)
        context.SetDiscreteState(block.EvalUniquePeriodicDiscreteUpdate(context).value())
        return block.GetOutputPort(output_name).Eval(context)[0]
    return tick


@pytest.fixture
def watched_gate_drive():
    """A function that drives a `shared` controller config whose gate never hands over, on wide
    task 1 with seed 4, for `end_time_s`, with `gate-signals`' watch (`SignalWatch`) beside it.
    At every control step it checks that the gate's `uncertainty` input is the output `signal`
    of the block named `block_name` and that the policy drives. Returns the watch, the gate's
    input at each step and the policy's commanded turn rate at each step."""
    from pydrake.systems.analysis import Simulator

    from ditch_drake.diagrams.controllers import get_controller
    from ditch_drake.diagrams.rollout import MakeRolloutDiagram, RolloutConfig, RunEpisode
    from ditch_drake.evaluation.gate_signals import SignalWatch
    from ditch_drake.learning.gate_calibration import POLICY

    def drive(config, block_name: str, signal: str, end_time_s: float):
        diagram, built = MakeRolloutDiagram(RolloutConfig(scene=SceneConfig(environment="wide", task=1),
                                                          controller=get_controller("shared").for_seed(config, 4)))
        gate, block = diagram.GetSubsystemByName("shared_control"), diagram.GetSubsystemByName(block_name)
        policy = diagram.GetSubsystemByName("learned_policy")
        recorder = SignalWatch(policy, built.schedule)
        read, commanded = [], []

        def watch(root) -> bool:
            recorder(root)
            commanded.append(policy.GetOutputPort("command").Eval(policy.GetMyContextFromRoot(root))[1])
            gate_context = gate.GetMyContextFromRoot(root)
            np.testing.assert_array_equal(gate.GetInputPort("uncertainty").Eval(gate_context),
                                          block.GetOutputPort(signal).Eval(block.GetMyContextFromRoot(root)))
            read.append(gate.GetInputPort("uncertainty").Eval(gate_context)[0])
            assert gate.GetOutputPort("who_drives").Eval(gate_context)[0] == POLICY
            return False

        RunEpisode(Simulator(diagram), diagram, built, 4, watch=watch, watch_period_s=built.schedule.control_period_s,
                   end_time_s=end_time_s)
        return recorder, read, commanded
    return drive
