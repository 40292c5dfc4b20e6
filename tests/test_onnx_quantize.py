"""An int8 ONNX policy (`ditch-drake export-policy --quantize int8`): calibrated on the
checkpoint's own training demonstrations, its convolutions in QDQ int8, readable wherever a
.onnx policy is, and the bad arguments refused with exit 2."""

import numpy as np
import pytest
import torch

from ditch_drake.cli.main import main
from ditch_drake.common.errors import ConfigError
from ditch_drake.demos.dataset import save_demonstration
from ditch_drake.demos.training_set import load_training_set
from ditch_drake.learning.checkpoint import load_checkpoint, resolve_checkpoint_path
from ditch_drake.learning.config import ModelConfig
from ditch_drake.learning.inference import load_policy
from ditch_drake.learning.onnx_policy import INPUT_NAMES, METADATA_KEY, example_inputs, read_onnx_policy
from ditch_drake.learning.onnx_quantize import calibration_batches, calibration_rows

onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

# wide_bc40 validated on demonstrations 0, 1, 2, 9, ...: of a folder of five, 3 and 4 calibrate.
CHECKPOINT = "wide_bc40"


@pytest.fixture
def demos(tmp_path_factory, random_demonstration) -> str:
    folder = tmp_path_factory.mktemp("demos")
    for index in range(5):
        save_demonstration(folder / f"demo_{index:03d}.npz", random_demonstration(index, 12))
    return str(folder)


@pytest.fixture
def int8_file(demos, tmp_path_factory) -> str:
    out = tmp_path_factory.mktemp("int8") / "P.onnx"
    assert main(["export-policy", CHECKPOINT, "--quantize", "int8", "--calibration-data", demos,
                 "--calibration-samples", "16", "--out", str(out)]) == 0
    return str(out)


def test_calibration_draws_only_training_demonstrations_with_its_seed(demos):
    arrays = load_training_set([demos])
    val = load_checkpoint(resolve_checkpoint_path(CHECKPOINT)).training["val_demo_ids"]
    rows = calibration_rows(arrays, val, 10, seed=3)
    assert len(rows) == 10 and set(arrays.demo_id[rows]) <= {3, 4}
    np.testing.assert_array_equal(rows, calibration_rows(arrays, val, 10, seed=3))
    assert not np.array_equal(rows, calibration_rows(arrays, val, 10, seed=4))
    # Asked for more than there are: every training sample, once.
    assert len(calibration_rows(arrays, val, 1000, seed=0)) == int(np.isin(arrays.demo_id, [3, 4]).sum()) == 24
    with pytest.raises(ConfigError, match="all among the checkpoint's validation demonstrations"):
        calibration_rows(arrays, [0, 1, 2, 3, 4], 10, seed=0)


def test_a_canonical_side_model_calibrates_on_each_sample_and_its_reflection(demos):
    arrays = load_training_set([demos])
    plain = calibration_batches(arrays, np.arange(20), reflect=False)
    both = calibration_batches(arrays, np.arange(20), reflect=True)
    assert [len(b["image"]) for b in plain] == [16, 4] and len(both) == 4
    np.testing.assert_array_equal(both[1]["image"], plain[0]["image"][..., ::-1])
    np.testing.assert_array_equal(both[1]["bearing"], -plain[0]["bearing"])


def test_the_int8_file_quantizes_the_convolutions_and_records_its_calibration(int8_file, demos):
    path = int8_file
    policy = read_onnx_policy(path)
    quantization = policy.metadata["quantization"]
    assert quantization["scheme"] == "int8" and quantization["format"] == "QDQ"
    assert quantization["calibration_data"] == [demos] and quantization["calibration_samples"] == 16
    assert quantization["calibration_seed"] == 0 and quantization["calibration_reflected"] is False
    proto = onnx.load(path)
    kinds = [node.op_type for node in proto.graph.node]
    assert kinds.count("Conv") == 2 and "QuantizeLinear" in kinds and "DequantizeLinear" in kinds
    # Each convolution's weight is stored as int8, one scale per output channel.
    int8_weights = [t for t in proto.graph.initializer if t.data_type == onnx.TensorProto.INT8 and len(t.dims) == 4]
    assert sorted(t.dims[0] for t in int8_weights) == [32, 64]
    # Only the standard operator set, and only the policy's metadata: another runtime reads it.
    assert {entry.domain for entry in proto.opset_import} == {""}
    assert [entry.key for entry in proto.metadata_props] == [METADATA_KEY]


def test_the_int8_model_runs_as_a_policy_and_stays_close_to_the_float_network(int8_file):
    path = int8_file
    inputs = {name: value.numpy() for name, value in zip(INPUT_NAMES, example_inputs(ModelConfig(), 64, seed=5),
                                                         strict=True)}
    with torch.inference_mode():
        reference = load_checkpoint(resolve_checkpoint_path(CHECKPOINT)).build_model()(
            *(torch.from_numpy(inputs[name]) for name in INPUT_NAMES)).numpy()
    logits = ort.InferenceSession(path, providers=["CPUExecutionProvider"]).run(["logits"], inputs)[0]
    assert logits.shape == (64, 17) and not np.array_equal(logits, reference)
    spread = reference.max() - reference.min()
    assert np.abs(logits - reference).max() < 0.1 * spread
    assert (logits.argmax(axis=1) == reference.argmax(axis=1)).mean() >= 0.9
    inference = load_policy(path, runtime="onnxruntime")
    assert inference.runtime == "onnxruntime"


@pytest.mark.parametrize("arguments, named", [
    (["--quantize", "int4"], "--quantize 'int4': expected one of ['none', 'int8']"),
    (["--quantize", "int8"], "--quantize int8 without --calibration-data"),
    (["--calibration-data", "{demos}"], "without --quantize int8"),
    (["--quantize", "int8", "--calibration-data", "{demos}", "--calibration-samples", "0"],
     "--calibration-samples 0: expected an integer >= 1"),
    (["--quantize", "int8", "--calibration-data", "{demos}", "--seed", "-1"], "--seed -1: expected an integer >= 0"),
    (["--quantize", "int8", "--calibration-data", "{tmp}/nothing"], "nothing"),
])
def test_bad_quantization_arguments_are_refused_with_exit_2(demos, tmp_path, capsys, arguments, named):
    arguments = [a.replace("{demos}", demos).replace("{tmp}", str(tmp_path)) for a in arguments]
    assert main(["export-policy", CHECKPOINT, *arguments, "--out", str(tmp_path / "P.onnx")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("ditch-drake: error: ") and named.replace("{tmp}", str(tmp_path)) in err
    assert "Traceback" not in err and not (tmp_path / "P.onnx").exists()


def test_the_report_names_what_an_onnx_policy_was_exported_from(int8_file, tmp_path):
    from ditch_drake.evaluation.report import write_report
    from ditch_drake.evaluation.results import RolloutRecord
    from ditch_drake.learning.checkpoint import checkpoint_digest

    digest = checkpoint_digest(int8_file)
    source = checkpoint_digest(CHECKPOINT)
    record = RolloutRecord(
        key="learned|int8|wide|0", controller="learned", checkpoint=int8_file, environment="wide", task=0, seed=0,
        time_limit_s=120.0, goal_radius_m=1.5, checkpoint_sha256=digest, status="reached_goal", success=True,
        time_s=40.0, path_length_m=30.0, peak_abs_roll_deg=5.0, peak_abs_pitch_deg=30.0, peak_tilt_deg=31.0,
        min_stability_margin_deg=10.0, final_x_m=0.0, final_y_m=0.0, failure_region="", wall_s=1.0)
    results = tmp_path / "results" / "int8.jsonl"
    results.parent.mkdir()
    results.write_text(record.to_json() + "\n")
    page = write_report([results], tmp_path / "page.md", tmp_path / "img").read_text()
    row = next(line for line in page.split("## Models")[1].splitlines() if int8_file in line)
    assert row.endswith(f"| {digest} | ONNX of {CHECKPOINT} ({source}) | - | int8, 16 calibration samples | - |")
