"""A policy exported to ONNX (`ditch-drake export-policy`) and run by ONNX Runtime: the round trip,
the policy block on either runtime, and the bad files and missing packages refused with exit 2."""

import json
import sys

import numpy as np
import pytest
import torch

from ditch_drake.cli.main import main
from ditch_drake.common.errors import CheckpointError, ConfigError
from ditch_drake.learning.checkpoint import load_checkpoint, resolve_checkpoint_path
from ditch_drake.learning.config import ModelConfig
from ditch_drake.learning.onnx_policy import (
    INPUT_NAMES,
    METADATA_KEY,
    OPSET,
    example_inputs,
    export_policy,
    file_sha256,
    read_onnx_policy,
)

onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

# A side-free model of one environment and the canonical-side generalist.
MODELS = ("wide_bc40", "generalist")


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> dict:
    """Each of `MODELS` written by `export_policy` into a temporary folder: name -> path."""
    folder = tmp_path_factory.mktemp("onnx")
    return {name: export_policy(name, folder / f"{name}.onnx")["out"] for name in MODELS}


def _inputs(batch: int, seed: int) -> dict[str, np.ndarray]:
    """Seeded inputs in the ports' ranges, as float32 arrays by input name."""
    return {name: value.numpy() for name, value in zip(INPUT_NAMES, example_inputs(ModelConfig(), batch, seed),
                                                       strict=True)}


@pytest.mark.parametrize("name", MODELS)
def test_the_export_gives_torch_s_labels_and_logits(exported, name):
    checkpoint = load_checkpoint(resolve_checkpoint_path(name))
    session = ort.InferenceSession(exported[name], providers=["CPUExecutionProvider"])
    inputs = _inputs(32, seed=1)
    with torch.inference_mode():
        expected = checkpoint.build_model()(*(torch.from_numpy(inputs[n]) for n in INPUT_NAMES)).numpy()
    logits = session.run(["logits"], inputs)[0]
    assert logits.shape == (32, 17) and logits.dtype == np.float32
    np.testing.assert_allclose(logits, expected, atol=1e-4)
    assert (logits.argmax(axis=1) == expected.argmax(axis=1)).all()
    # The batch axis is free: one sample alone gives its row of the batch.
    single = session.run(["logits"], {n: value[:1] for n, value in inputs.items()})[0]
    np.testing.assert_allclose(single[0], logits[0], atol=1e-5)


def test_the_file_carries_what_a_robot_needs(exported):
    policy = read_onnx_policy(exported["generalist"])
    checkpoint = load_checkpoint(resolve_checkpoint_path("generalist"))
    metadata = policy.metadata
    assert policy.opset == OPSET == metadata["opset"]
    np.testing.assert_array_equal(policy.action_commands, checkpoint.action_commands)
    assert policy.model_config == checkpoint.model_config and metadata["canonical_side"] is True
    assert "reflection" in metadata["mirror"]
    assert metadata["source_checkpoint_sha256"] == file_sha256(resolve_checkpoint_path("generalist"))
    assert metadata["control_period_s"] == 0.1 and metadata["schema_version"] == 1
    assert metadata["inputs"]["image"]["shape"] == ["batch", 4, 128, 128]
    names = [i.name for i in ort.InferenceSession(exported["generalist"]).get_inputs()]
    assert names == list(INPUT_NAMES)
    assert not read_onnx_policy(exported["wide_bc40"]).metadata["canonical_side"]


@pytest.mark.parametrize("name", MODELS)
def test_the_policy_block_chooses_the_same_label_on_either_runtime(exported, name):
    from ditch_drake.learning.inference import load_policy
    from ditch_drake.systems.policy import LearnedPolicy

    torch_policy = LearnedPolicy(load_checkpoint(resolve_checkpoint_path(name)))
    from_file = LearnedPolicy(load_policy(exported[name], "onnxruntime"))
    in_memory = LearnedPolicy(load_policy(name, "onnxruntime"))
    assert (torch_policy.runtime, from_file.runtime, in_memory.runtime) == ("torch", "onnxruntime", "onnxruntime")
    inputs = _inputs(6, seed=2)
    for row in range(6):
        for side in (1.0, -1.0):  # -1 reflects the generalist's view and answer; the other ignores it.
            sample = [inputs[n][row].ravel() for n in INPUT_NAMES]
            label, probabilities = torch_policy.infer(*sample, crossing_side=side)
            for policy in (from_file, in_memory):
                other_label, other = policy.infer(*sample, crossing_side=side)
                assert other_label == label
                np.testing.assert_allclose(other, probabilities, atol=1e-5)
    np.testing.assert_array_equal(from_file.action_commands, torch_policy.action_commands)


def _labels(controller, seconds: float) -> tuple[str, list[float]]:
    """The policy's runtime and its label at each control step of a rollout in Wide (task 1, seed 3)."""
    from pydrake.systems.analysis import Simulator

    from ditch_drake.diagrams.ditch_scene import SceneConfig
    from ditch_drake.diagrams.rollout import MakeRolloutDiagram, RolloutConfig, RunEpisode

    diagram, scene = MakeRolloutDiagram(RolloutConfig(scene=SceneConfig(environment="wide", task=1),
                                                      controller=controller))
    policy = diagram.GetSubsystemByName("learned_policy")
    labels = []

    def watch(context):
        labels.append(float(policy.GetOutputPort("label").Eval(policy.GetMyContextFromRoot(context))[0]))

    RunEpisode(Simulator(diagram), diagram, scene, 3, watch=watch, watch_period_s=0.1, end_time_s=seconds)
    return policy.runtime, labels


def test_a_short_rollout_gives_the_same_labels_on_either_runtime(exported):
    from ditch_drake.diagrams.rollout import LearnedPolicyConfig

    runtime, labels = _labels(LearnedPolicyConfig(checkpoint="wide_bc40"), 4.0)
    assert runtime == "torch" and len(labels) == 40 and len(set(labels)) > 1
    assert _labels(LearnedPolicyConfig(checkpoint=exported["wide_bc40"], runtime="onnxruntime"), 4.0) == (
        "onnxruntime", labels)


def test_the_runtime_is_in_the_records_and_a_onnx_checkpoint_chooses_it(exported):
    from ditch_drake.diagrams.controllers import controller_config
    from ditch_drake.diagrams.rollout import LearnedPolicyConfig
    from ditch_drake.evaluation.batch import make_specs
    from ditch_drake.learning.checkpoint import checkpoint_digest

    (torch_spec,) = make_specs("learned", "wide_bc40", "wide", [1], rollouts=1)
    (onnx_spec,) = make_specs(LearnedPolicyConfig(checkpoint="wide_bc40", runtime="onnxruntime"), "", "wide", [1],
                              rollouts=1)
    assert "runtime: torch" in torch_spec.controller_config
    assert "runtime: onnxruntime" in onnx_spec.controller_config and onnx_spec.key != torch_spec.key
    path = exported["wide_bc40"]
    assert controller_config("learned", path).runtime == "onnxruntime"
    (file_spec,) = make_specs("learned", path, "wide", [1], rollouts=1)
    assert "runtime: onnxruntime" in file_spec.controller_config
    assert file_spec.checkpoint_sha256 == checkpoint_digest(path) == file_sha256(path)[:16]
    with pytest.raises(ConfigError, match="is an ONNX model with runtime='torch'; expected runtime 'onnxruntime'"):
        LearnedPolicyConfig(checkpoint=path).validate()
    with pytest.raises(ConfigError, match=r"runtime='tensorrt': expected one of \['torch', 'onnxruntime'\]"):
        LearnedPolicyConfig(runtime="tensorrt").validate()


def test_export_policy_writes_a_file_onnxruntime_loads(tmp_path, capsys):
    out = tmp_path / "sub" / "P.onnx"
    assert main(["export-policy", "wide", "--format", "onnx", "--out", str(out)]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["opset"] == OPSET and report["inputs"] == list(INPUT_NAMES) and report["output"] == "logits"
    assert [p.name for p in out.parent.iterdir()] == ["P.onnx"]  # Written atomically: no temporary left.
    session = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    assert METADATA_KEY in session.get_modelmeta().custom_metadata_map


# Bad input: exit 2, one message naming the file and what was expected.


def _edited(source: str, folder, name: str, edit) -> str:
    proto = onnx.load(source)
    edit(proto)
    path = folder / name
    onnx.save(proto, str(path))
    return str(path)


def _rename_input(proto):
    proto.graph.input[1].name = "roll_pitch"


def _other_image_size(proto):
    proto.graph.input[0].type.tensor_type.shape.dim[3].dim_value = 64


def _double_imu(proto):
    proto.graph.input[1].type.tensor_type.elem_type = onnx.TensorProto.DOUBLE


def _old_opset(proto):
    proto.opset_import[0].version = 11


def _no_metadata(proto):
    del proto.metadata_props[:]


def _foreign_metadata(proto):
    proto.metadata_props[0].value = json.dumps({"schema": "someone.else"})


@pytest.mark.parametrize("edit, named", [
    (_rename_input, "inputs ['bearing', 'distance', 'image', 'roll_pitch']"),
    (_other_image_size, "input 'image' is FLOAT of shape ['batch', 4, 128, 64]"),
    (_double_imu, "input 'imu' is DOUBLE"),
    (_old_opset, "ONNX opset 11; expected an opset in 17.."),
    (_no_metadata, f"no '{METADATA_KEY}' metadata"),
    (_foreign_metadata, "has schema 'someone.else'"),
])
def test_a_mismatched_onnx_file_is_refused_with_exit_2(exported, tmp_path, capsys, edit, named):
    bad = _edited(exported["wide_bc40"], tmp_path, "bad.onnx", edit)
    with pytest.raises(CheckpointError, match="bad.onnx"):
        read_onnx_policy(bad)
    assert main(["evaluate", "--checkpoint", bad, "--env", "wide", "--task", "1", "--rollouts", "1", "--workers", "0",
                 "--out", str(tmp_path / "r.jsonl")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"ditch-drake: error: {bad}") and named in err and "Traceback" not in err
    assert not (tmp_path / "r.jsonl").exists()


def test_bytes_that_are_not_onnx_are_refused(tmp_path):
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"not a model at all" * 10)
    with pytest.raises(CheckpointError, match="garbage.onnx: not a readable ONNX model"):
        read_onnx_policy(garbage)


@pytest.mark.parametrize("arguments, named", [
    (["wide", "--format", "tflite"], "--format 'tflite': expected one of ['onnx']"),
    (["{tmp}/missing.pt"], "missing.pt': no such file"),
    (["wide", "--out", "{tmp}/file/P.onnx"], "--out {tmp}/file/P.onnx: cannot create the folder"),
    (["{tmp}/P.onnx"], "is already an ONNX model; expected a .pt checkpoint"),
])
def test_export_policy_refuses_bad_arguments_with_exit_2(tmp_path, capsys, arguments, named):
    (tmp_path / "file").write_text("a file, not a folder")
    (tmp_path / "P.onnx").write_bytes(b"")
    arguments = [a.replace("{tmp}", str(tmp_path)) for a in arguments]
    if "--out" not in arguments:
        arguments += ["--out", str(tmp_path / "out.onnx")]
    assert main(["export-policy", *arguments]) == 2
    err = capsys.readouterr().err
    assert err.startswith("ditch-drake: error: ") and named.replace("{tmp}", str(tmp_path)) in err
    assert not (tmp_path / "out.onnx").exists()


def test_a_missing_onnx_extra_names_the_install_command(monkeypatch, tmp_path, capsys):
    import importlib.util

    from ditch_drake.diagrams.rollout import LearnedPolicyConfig

    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "onnxruntime" else
                        find_spec(name, *a))
    with pytest.raises(ConfigError, match=r"needs \['onnxruntime'\], not installed; .*pip install -e '.\[onnx\]'"):
        LearnedPolicyConfig(runtime="onnxruntime").validate()
    monkeypatch.setitem(sys.modules, "onnx", None)  # `import onnx` now raises ImportError.
    assert main(["export-policy", "wide", "--out", str(tmp_path / "P.onnx")]) == 2
    assert "needs the 'onnx' package, which is not installed; expected the onnx extra: pip install -e '.[onnx]'" in (
        capsys.readouterr().err)
