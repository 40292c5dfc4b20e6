"""The `shared` controller wired: ensembles in the policy block (mean-probability label, the
uncertainty output, the mirror per member), the gate in a built diagram, a short rollout through
the batch path with its handover fields, and bad configs refused with exit 2."""

import dataclasses
import importlib.util
import json
import re

import numpy as np
import pytest
import torch
from pydrake.systems.analysis import Simulator

from ditch_drake.cli import main
from ditch_drake.common.errors import ConfigError
from ditch_drake.diagrams.controllers import controller_config, get_controller
from ditch_drake.diagrams.ditch_scene import SceneConfig
from ditch_drake.diagrams.rollout import MakeRolloutDiagram, RolloutConfig
from ditch_drake.diagrams.shared_controller import SharedControlControllerConfig
from ditch_drake.evaluation.batch import evaluate, make_specs
from ditch_drake.evaluation.results import read_records
from ditch_drake.evaluation.rollout_worker import error_record
from ditch_drake.learning.checkpoint import checkpoint_digest, load_checkpoint, resolve_checkpoint_path
from ditch_drake.learning.ensemble import EnsembleCheckpoint, save_ensemble
from ditch_drake.learning.inference import check_runtime, is_ensemble, load_policy
from ditch_drake.learning.uncertainty import UNCERTAINTY_SIGNALS, angular_rate_spread, mean_softmax_entropy
from ditch_drake.spec import actions
from ditch_drake.spec.observation_layout import IMAGE_STACK_SIZE
from ditch_drake.systems.policy import LearnedPolicy
from ditch_drake.systems.shared_control import FALLBACK

PAIR = ("wide_bc40", "wide")


@pytest.fixture(scope="module")
def pair_file(tmp_path_factory):
    """Two shipped clones of one shape as an ensemble file (not a bootstrap: a test's K = 2)."""
    path = tmp_path_factory.mktemp("ensemble") / "wide_pair.pt"
    save_ensemble(EnsembleCheckpoint([load_checkpoint(resolve_checkpoint_path(name)) for name in PAIR]), path)
    return path


def _observation(seed: int = 0) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    return rng.random(IMAGE_STACK_SIZE), rng.normal(0.0, 0.2, 8), rng.uniform(2.0, 9.0, 4), rng.normal(0.0, 0.5, 4)


def _update(policy: LearnedPolicy, observation, side: float | None = None):
    context = policy.CreateDefaultContext()
    for name, value in zip(("image_stack", "imu_stack", "distance_stack", "bearing_stack"), observation, strict=True):
        policy.GetInputPort(name).FixValue(context, value)
    if side is not None:
        policy.GetInputPort("crossing_side").FixValue(context, [side])
    state = policy.AllocateDiscreteVariables()
    policy.CalcForcedDiscreteVariableUpdate(context, state)
    context.SetDiscreteState(state)
    return {name: policy.GetOutputPort(name).Eval(context).copy()
            for name in ("label", "probabilities", "command", "uncertainty")}


def test_an_ensemble_chooses_by_the_members_mean_probabilities_and_reports_their_uncertainty(pair_file):
    assert is_ensemble(pair_file) and not is_ensemble("wide")
    rates = actions.COMMANDS[:, 1]
    singles = [LearnedPolicy(load_policy(name)) for name in PAIR]
    for signal in UNCERTAINTY_SIGNALS:
        policy = LearnedPolicy(load_policy(pair_file), uncertainty_signal=signal)
        assert policy.members == 2 and policy.uncertainty_signal == signal
        for seed in range(3):
            observation = _observation(seed)
            members = np.stack([single.infer(*observation)[1] for single in singles])
            out = _update(policy, observation)
            decision = policy.decide(*observation)
            np.testing.assert_allclose(decision.member_probabilities, members, atol=1e-5)
            np.testing.assert_allclose(out["probabilities"], members.mean(axis=0), atol=1e-5)
            assert out["label"][0] == decision.label == int(np.argmax(decision.probabilities))
            np.testing.assert_array_equal(out["command"], actions.COMMANDS[decision.label])
            expected = UNCERTAINTY_SIGNALS[signal](decision.member_probabilities, rates)
            assert out["uncertainty"][0] == pytest.approx(float(expected), abs=1e-12)
    # One clone's uncertainty: its own softmax entropy, the default signal.
    single = _update(singles[1], _observation())
    assert single["uncertainty"][0] == pytest.approx(float(mean_softmax_entropy(single["probabilities"][None])))


def test_a_canonical_side_ensemble_reflects_each_members_answer_back(tmp_path):
    generalist = load_checkpoint(resolve_checkpoint_path("generalist"))
    torch.manual_seed(0)
    other = dataclasses.replace(generalist, state_dict={
        name: value + 0.05 * value.std() * torch.randn_like(value) if value.is_floating_point() and value.numel() > 1
        else value for name, value in generalist.state_dict.items()})
    path = save_ensemble(EnsembleCheckpoint([generalist, other]), tmp_path / "sided.pt")
    policy = LearnedPolicy(load_policy(path), uncertainty_signal="angular_rate_spread")
    singles = [LearnedPolicy(member) for member in (generalist, other)]
    observation = _observation(4)
    for side in (1.0, -1.0):
        members = np.stack([single.infer(*observation, crossing_side=side)[1] for single in singles])
        out = _update(policy, observation, side)
        np.testing.assert_allclose(out["probabilities"], members.mean(axis=0), atol=1e-5)
        assert out["uncertainty"][0] == pytest.approx(float(angular_rate_spread(members, actions.COMMANDS[:, 1])))


def test_a_disagreement_signal_needs_an_ensemble(pair_file):
    for signal in ("angular_rate_spread", "vote_entropy"):
        with pytest.raises(ConfigError, match=f"{signal}.*K = 1"):
            LearnedPolicy(load_policy("wide"), uncertainty_signal=signal)
        config = controller_config("shared", "wide")
        gated = dataclasses.replace(config, gate=dataclasses.replace(config.gate, signal=signal, upper_threshold=0.5,
                                                                     lower_threshold=0.4))
        with pytest.raises(ConfigError, match=f"{signal}.*K = 1"):
            gated.validate()
        gated.with_checkpoint(str(pair_file)).validate()
        dataclasses.replace(controller_config("shared"), gate=gated.gate).validate()  # The shipped ensemble.
    with pytest.raises(ConfigError, match="uncertainty signal 'spread'"):
        LearnedPolicy(load_policy("wide"), uncertainty_signal="spread")
    if all(importlib.util.find_spec(name) is not None for name in ("onnxruntime", "onnx")):
        with pytest.raises(ConfigError, match="ensemble with runtime='onnxruntime'"):
            check_runtime("onnxruntime", str(pair_file))


def test_a_batch_takes_an_ensemble_file_as_a_checkpoint(pair_file):
    (spec,) = make_specs("learned", str(pair_file), "wide", [1], rollouts=1)
    assert spec.checkpoint_sha256 == checkpoint_digest(str(pair_file))
    (shared,) = make_specs("shared", str(pair_file), "wide", [1], rollouts=1)
    assert (shared.checkpoint, shared.checkpoint_sha256) == (str(pair_file), spec.checkpoint_sha256)


def _handing_over(fallback: str = "expert") -> SharedControlControllerConfig:
    """The shared controller on its members' spread with an upper threshold of 0 and no warm-up: it
    hands over at the first tick."""
    config = controller_config("shared")
    return dataclasses.replace(config, gate=dataclasses.replace(
        config.gate, signal="angular_rate_spread", upper_threshold=0.0, lower_threshold=0.0, warmup_steps=0,
        fallback=fallback))


@pytest.mark.parametrize("fallback, privileged", [("expert", ("terrain",)), ("mppi", ())])
def test_who_drives_switches_to_the_fallback_in_a_built_shared_diagram(fallback, privileged):
    config = _handing_over(fallback)
    assert get_controller("shared").privileged_inputs(config) == privileged
    diagram, scene = MakeRolloutDiagram(RolloutConfig(scene=SceneConfig(environment="wide", task=1),
                                                      controller=get_controller("shared").for_seed(config, 3)))
    assert not diagram.HasSubsystemNamed("mppi_lidar")  # The planner reads the policy's lidar.
    gate = diagram.GetSubsystemByName("shared_control")
    simulator = Simulator(diagram)
    simulator.AdvanceTo(0.05)
    gate_context = gate.GetMyContextFromRoot(simulator.get_context())
    assert gate.GetOutputPort("who_drives").Eval(gate_context)[0] == FALLBACK
    assert gate.GetOutputPort("switches").Eval(gate_context)[0] == 1
    fallback_command = gate.GetInputPort("fallback_command").Eval(gate_context)
    np.testing.assert_array_equal(gate.GetOutputPort("command").Eval(gate_context), fallback_command)
    drive = scene.drive.GetInputPort("command").Eval(scene.drive.GetMyContextFromRoot(simulator.get_context()))
    np.testing.assert_array_equal(drive, fallback_command)


def test_a_short_shared_rollout_through_the_batch_path_records_its_handovers(tmp_path):
    out = tmp_path / "shared.jsonl"
    specs = make_specs(_handing_over(), "", "wide", [1], rollouts=1, time_limit_s=2.0)
    evaluate(specs, out, workers=0, progress=False)
    code = main(["evaluate", "--controller", "shared", "--env", "wide", "--task", "1", "--rollouts", "1",
                 "--time-limit", "2", "--workers", "0", "--out", str(out)])
    assert code == 0
    (handing, default), _ = read_records(out)
    assert (handing.status, handing.checkpoint, handing.privileged) == ("timeout", "generalist_k5", ["terrain"])
    assert (handing.handover_fraction, handing.switches, handing.handover_regions) == (1.0, 1, ["approach"])
    line = json.loads(out.read_text().splitlines()[1])
    assert line["schema_version"] == 7 and {"handover_fraction", "switches", "handover_regions"} <= line.keys()
    # The default thresholds hand over rarely: not in 2 s of the approach.
    assert (default.handover_fraction, default.switches, default.handover_regions) == (0.0, 0, [])
    # Other controllers' records carry no gate.
    (learned,) = make_specs("learned", "", "wide", [1], rollouts=1, time_limit_s=2.0)
    record = error_record(learned, "boom")
    assert (record.handover_fraction, record.switches, record.handover_regions) == (0.0, 0, [])


@pytest.mark.parametrize("override, message", [
    ("{gate: {fallback: person}}", "fallback 'person'"),
    ("{gate: {fallback: teleop}}", "fallback 'teleop' without a Meshcat"),
    ("{gate: {budget: 0.05}}", "budget 0.05 without a calibration"),
    ("{policy: {checkpoint: wide}, gate: {signal: vote_entropy, upper_threshold: 0.5, lower_threshold: 0.4}}",
     "vote_entropy.*K = 1"),
    ("{gate: {signal: vote_entropy}}", "upper_threshold -6.826 with signal 'vote_entropy', which is never negative"),
])
def test_bad_shared_configs_exit_2_naming_the_value(tmp_path, capsys, override, message):
    out = tmp_path / "r.jsonl"
    code = main(["evaluate", "--override", f"{{controller: !SharedControlControllerConfig {override}}}",
                 "--env", "wide", "--task", "1", "--rollouts", "1", "--workers", "0", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1 and re.search(message, err), err
    assert not out.exists() or out.read_text() == ""
