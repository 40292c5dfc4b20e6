"""An int8 ONNX policy: the exported network with its convolutions in 8-bit integers.

The two convolutions are about nine tenths of the network's multiply-adds
(docs/results/performance.md). `quantize_int8` rewrites an `export_onnx` model with ONNX
Runtime's static quantization in the QDQ format (QuantizeLinear / DequantizeLinear pairs
around each convolution, which ONNX Runtime fuses into integer kernels and TensorRT reads as
int8 layers):

- weights: int8, symmetric, one scale per output channel;
- activations: uint8, one scale and zero point per tensor, from the smallest and largest value
  each convolution's input took on the calibration samples (MinMax);
- everything else (ELU, pooling, the scalar branches, the head) stays float32, so the inputs
  and the output are those of the float model.

Calibration samples are real observations: drawn with a seed from the demonstrations a
checkpoint trained on (never its validation demonstrations), each also reflected for a
canonical-side model, which is fed reflections where the crossing turns left.

The labels of an int8 model differ from the float model's on a small share of samples (an
approximation chosen on purpose: docs/concepts/learning.md has the measured agreement,
docs/results/performance.md the rollouts and the step time). The result depends on the CPU's integer kernels: on x86 without VNNI, ONNX
Runtime's uint8 x int8 products can saturate.
"""

import importlib.metadata
import json
import tempfile
from pathlib import Path

import numpy as np

import ditch_drake
from ditch_drake.common.errors import ConfigError
from ditch_drake.learning.data import ArraySet
from ditch_drake.learning.onnx_policy import METADATA_KEY, network_feeds, require_module

QUANTIZATIONS = ("none", "int8")
QUANTIZED_OPERATORS = ("Conv",)
# Samples per calibration forward pass: ONNX Runtime's MinMax calibration keeps every
# intermediate output of every pass until the end, so the memory is the total, not the batch.
CALIBRATION_BATCH = 16


def check_quantization(quantize: str = "none", calibration_data: list[str] | tuple[str, ...] = ()) -> None:
    """`export-policy --quantize` and `--calibration-data` together.

    Raises:
        ConfigError: an unknown quantization, int8 without calibration data, or calibration
            data without int8.
    """
    if quantize not in QUANTIZATIONS:
        raise ConfigError(f"--quantize {quantize!r}: expected one of {list(QUANTIZATIONS)}")
    if quantize == "int8" and not calibration_data:
        raise ConfigError("--quantize int8 without --calibration-data: expected one or more dataset folders holding "
                          "demonstrations the checkpoint trained on (e.g. --calibration-data data/demos/wide)")
    if quantize == "none" and calibration_data:
        raise ConfigError(f"--calibration-data {list(calibration_data)} without --quantize int8: expected no "
                          "calibration data for a float32 export")


def int8_quantizer(arrays: ArraySet, calibration_data: list[str], calibration_samples: int = 128, seed: int = 0):
    """The `export_policy` quantizer of `--quantize int8`: `calibration_samples` samples of
    `arrays` (the folders `calibration_data`, numbered as `train` numbers them) drawn with `seed`
    from the checkpoint's training demonstrations (`calibration_rows`), reflected too for a
    canonical-side model, calibrate `quantize_int8`.

    Raises:
        ConfigError: `calibration_samples` < 1 or a negative `seed` (here); when it runs, no
            sample outside the checkpoint's validation demonstrations.
    """
    _check_draw(calibration_samples, seed)

    def quantize(policy, model: bytes) -> tuple[bytes, dict]:
        rows = calibration_rows(arrays, policy.training.get("val_demo_ids", []), calibration_samples, seed)
        reflect = bool(policy.model_config.canonical_side)
        calibration = {"calibration_data": list(calibration_data), "calibration_samples": len(rows),
                       "calibration_seed": seed, "calibration_reflected": reflect}
        batches = calibration_batches(arrays, rows, reflect)
        return quantize_int8(model, batches, calibration), {"quantize": "int8", **calibration}

    return quantize


def _check_draw(samples: int, seed: int) -> None:
    if not (isinstance(samples, int) and not isinstance(samples, bool) and samples >= 1):
        raise ConfigError(f"--calibration-samples {samples!r}: expected an integer >= 1")
    if not (isinstance(seed, int) and not isinstance(seed, bool) and seed >= 0):
        raise ConfigError(f"--seed {seed!r}: expected an integer >= 0 for the calibration samples' draw")


def calibration_rows(arrays: ArraySet, val_demo_ids, samples: int, seed: int) -> np.ndarray:
    """`samples` rows of `arrays` drawn without replacement (seeded) from the demonstrations
    not in `val_demo_ids`, sorted.

    Raises:
        ConfigError: `samples` < 1, a negative `seed`, or no sample outside the validation
            demonstrations.
    """
    _check_draw(samples, seed)
    candidates = np.flatnonzero(~np.isin(arrays.demo_id, list(val_demo_ids)))
    if not len(candidates):
        raise ConfigError(f"the calibration data's {len(np.unique(arrays.demo_id))} demonstrations are all among the "
                          "checkpoint's validation demonstrations (val_demo_ids); expected folders holding some of "
                          "the demonstrations it trained on")
    chosen = np.random.default_rng(seed).choice(candidates, min(samples, len(candidates)), replace=False)
    return np.sort(chosen)


def calibration_batches(arrays: ArraySet, rows: np.ndarray, reflect: bool) -> list[dict]:
    """The network's float32 inputs of `rows` (and of their reflections with `reflect`), in
    batches of `CALIBRATION_BATCH`."""
    return [feed for start in range(0, len(rows), CALIBRATION_BATCH)
            for feed in network_feeds(arrays, rows[start:start + CALIBRATION_BATCH], reflect)]


def quantize_int8(model: bytes, batches: list[dict], calibration: dict) -> bytes:
    """`model` (an `export_onnx` model) with its convolutions quantized to int8 (module docstring).

    Args:
        model: the float model's bytes.
        batches: the calibration inputs ({input name: float32 array}), at least one.
        calibration: what the batches are (data, samples, seed), recorded in the metadata's
            "quantization" object beside the scheme.

    Raises:
        ConfigError: onnxruntime or onnx is not installed, or no calibration batch.
    """
    onnx = require_module("onnx", "quantizing a policy to int8")
    require_module("onnxruntime", "quantizing a policy to int8")
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    if not batches:
        raise ConfigError("no calibration samples: expected at least one to quantize to int8")

    class Reader(CalibrationDataReader):
        def __init__(self):
            self._batches = iter(batches)

        def get_next(self):
            return next(self._batches, None)

    with tempfile.TemporaryDirectory(prefix="ditch_drake_int8_") as folder:
        source, inferred, quantized = (Path(folder) / name for name in ("float.onnx", "inferred.onnx", "int8.onnx"))
        source.write_bytes(model)
        # Shape inference only: ONNX Runtime's graph optimizations would write its own operator
        # domains into the file, which other runtimes do not know.
        quant_pre_process(str(source), str(inferred), skip_optimization=True)
        quantize_static(str(inferred), str(quantized), Reader(), quant_format=QuantFormat.QDQ,
                        op_types_to_quantize=list(QUANTIZED_OPERATORS), per_channel=True, reduce_range=False,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8)
        proto = onnx.load(str(quantized))
    entries = {entry.key: entry for entry in proto.metadata_props}
    metadata = json.loads(entries[METADATA_KEY].value)
    metadata["quantization"] = {
        "scheme": "int8",
        "format": "QDQ",
        "operators": list(QUANTIZED_OPERATORS),
        "weights": "int8, symmetric, per output channel",
        "activations": "uint8, per tensor, MinMax over the calibration samples",
        "tool": f"onnxruntime.quantization {importlib.metadata.version('onnxruntime')}",
        **calibration,
    }
    entries[METADATA_KEY].value = json.dumps(metadata)
    # Only the policy's metadata: the quantizer's own notes name temporary files.
    for key in [key for key in entries if key != METADATA_KEY]:
        proto.metadata_props.remove(entries[key])
    proto.producer_name = "ditch_drake"
    proto.producer_version = ditch_drake.__version__
    return proto.SerializeToString()
