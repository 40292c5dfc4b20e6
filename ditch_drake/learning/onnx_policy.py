"""A policy as an ONNX model: what a robot's computer runs without this package.

`export_onnx` turns a checkpoint into an ONNX model (bytes) of the network alone:

| name | shape | dtype | values |
| --- | --- | --- | --- |
| input `image` | (batch, 4, 128, 128) | float32 | the stacked surface-normal images in [0, 1], channel 0 newest |
| input `imu` | (batch, 8) | float32 | [roll_t, pitch_t, roll_t-1, pitch_t-1, ...] (rad), newest first |
| input `distance` | (batch, 4) | float32 | planar distance to the goal (m), newest first |
| input `bearing` | (batch, 4) | float32 | goal direction minus yaw (rad, positive: goal to the left), newest first |
| output `logits` | (batch, 17) | float32 | one per action label; the label is the argmax |

The inputs are raw, as the `FrameStacker` gives them: the training split's standardization
of the scalar inputs is inside the graph (the network's forward pass applies it, so the export
folds it in). The batch axis is dynamic. The operator set is `OPSET` (17), written by
PyTorch's TorchScript-based exporter (`torch.onnx.export(..., dynamo=False)`), which needs
no `onnxscript` and exports in a fraction of a second; the `onnx` package adds the metadata.

Everything else a robot needs is one JSON object in the model's `metadata_props` under
`METADATA_KEY` (`policy_metadata`): the action table (label -> [v m/s, w rad/s]), the model
config (with `canonical_side`: such a model is fed the left-right reflection of its inputs,
and its logits read in reverse, where the crossing turns left along the edge; see `MIRROR`),
the control period, the source checkpoint's name and SHA-256, the schema and its version.

`read_onnx_policy` reads such a file back and checks it (inputs, output, opset, metadata), so
that a .onnx file serves wherever a checkpoint is taken (`ditch_drake.learning.inference`);
`label_agreement` measures how often the exported model's argmax equals torch's.
"""

import hashlib
import importlib
import io
import json
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

import ditch_drake
from ditch_drake.common.errors import CheckpointError, ConfigError
from ditch_drake.common.files import atomic_write_bytes, prepare_output
from ditch_drake.learning.checkpoint import PolicyCheckpoint, load_checkpoint, resolve_checkpoint_path
from ditch_drake.learning.config import ModelConfig
from ditch_drake.learning.data import ArraySet, images_to_float32
from ditch_drake.learning.mirror import mirror_left_right
from ditch_drake.spec import actions, robot

SCHEMA = "ditch_drake.onnx_policy"
SCHEMA_VERSION = 1
METADATA_KEY = "ditch_drake.policy"
# What the exporter writes; a file of a newer opset reads up to the newest the installed `onnx` knows.
OPSET = 17
INPUT_NAMES = ("image", "imu", "distance", "bearing")
OUTPUT_NAME = "logits"
ONNX_SUFFIX = ".onnx"
# The export formats of `export_policy` (`ditch-drake export-policy --format`), each with its file suffix.
POLICY_FORMATS = {"onnx": ONNX_SUFFIX}
INSTALL_HINT = "pip install -e '.[onnx]'"
EXPECTED_ONNX = (f"an ONNX policy written by `ditch-drake export-policy` (metadata {METADATA_KEY!r} of schema "
                 f"{SCHEMA!r}, inputs {list(INPUT_NAMES)} float32 with a batch axis, output {OUTPUT_NAME!r}, opset >= "
                 f"{OPSET})")
MIRROR = ("where the crossing turns left along the edge (crossing_side -1), feed the left-right reflection of the "
          "inputs (image columns reversed, roll of each IMU step negated, bearing negated, distance kept) and read "
          "the logits in reverse order (label k of the reflection is label num_labels - 1 - k); crossing_side +1 or 0 "
          "(not yet known): the inputs as they are")


def is_onnx_path(checkpoint: str | os.PathLike) -> bool:
    """Whether a checkpoint argument names an ONNX model (a path ending .onnx)."""
    return str(checkpoint).lower().endswith(ONNX_SUFFIX)


def require_module(name: str, what: str):
    """The module `name` (onnx or onnxruntime), imported.

    Raises:
        ConfigError: it is not installed, naming `what` needs it and the extra that installs it.
    """
    try:
        return importlib.import_module(name)
    except ImportError as error:
        raise ConfigError(f"{what} needs the {name!r} package, which is not installed; expected the onnx extra: "
                          f"{INSTALL_HINT}") from error


def file_sha256(path: str | os.PathLike) -> str:
    """The SHA-256 (hex) of a file's bytes (the metadata's `source_checkpoint_sha256`)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _input_descriptions(config: ModelConfig) -> dict:
    return {
        "image": {"shape": ["batch", config.image_channels, config.image_size, config.image_size], "dtype": "float32",
                  "values": "surface-normal images in [0, 1] (the normals' z component), channel 0 newest; column 0 "
                            "is the robot's left (+y)"},
        "imu": {"shape": ["batch", config.imu_size], "dtype": "float32",
                "values": "[roll_t, pitch_t, roll_t-1, pitch_t-1, ...] in rad, newest first, raw"},
        "distance": {"shape": ["batch", config.distance_size], "dtype": "float32",
                     "values": "planar distance to the goal in m, newest first, raw"},
        "bearing": {"shape": ["batch", config.bearing_size], "dtype": "float32",
                    "values": "goal direction minus yaw in rad (positive: goal to the left), newest first, raw"},
    }


def policy_metadata(checkpoint: PolicyCheckpoint, source: str = "", source_sha256: str = "") -> dict:
    """The JSON object stored under `METADATA_KEY`: everything a robot needs beside the graph."""
    config = checkpoint.model_config
    return {
        "schema": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "code_version": ditch_drake.__version__,
        "opset": OPSET,
        "inputs": _input_descriptions(config),
        "outputs": {OUTPUT_NAME: {"shape": ["batch", config.num_labels], "dtype": "float32",
                                  "values": "one logit per action label; the command is action_commands[argmax]"}},
        "standardization": "folded in: the scalar inputs are standardized inside the graph (input_stats); feed raw "
                           "values",
        "input_stats": checkpoint.input_stats.to_dict(),
        "action_commands": np.asarray(checkpoint.action_commands, dtype=float).tolist(),
        "action_units": "[v m/s, w rad/s] per label (row = label); positive w turns left",
        "control_period_s": robot.CONTROL_PERIOD_S,
        "model_config": config.to_dict(),
        "canonical_side": bool(config.canonical_side),
        "mirror": MIRROR if config.canonical_side else "none: the inputs are fed as they are",
        "source_checkpoint": source,
        "source_checkpoint_sha256": source_sha256,
    }


def example_inputs(config: ModelConfig, batch: int = 2, seed: int = 0) -> tuple[torch.Tensor, ...]:
    """Seeded inputs of the network's shapes (image in [0, 1], scalars of realistic size)."""
    generator = torch.Generator().manual_seed(seed)
    return (torch.rand(batch, config.image_channels, config.image_size, config.image_size, generator=generator),
            0.3 * torch.randn(batch, config.imu_size, generator=generator),
            20.0 * torch.rand(batch, config.distance_size, generator=generator),
            torch.randn(batch, config.bearing_size, generator=generator))


def export_onnx(checkpoint: PolicyCheckpoint, source: str = "", source_sha256: str = "") -> bytes:
    """The ONNX model of `checkpoint`'s network (module docstring), with its metadata.

    Args:
        checkpoint: the trained policy.
        source: the checkpoint's name or path, recorded in the metadata.
        source_sha256: the checkpoint file's SHA-256 (hex), recorded in the metadata.

    Raises:
        ConfigError: the `onnx` package is not installed.
    """
    onnx = require_module("onnx", "exporting a policy to ONNX")
    model = checkpoint.build_model()
    buffer = io.BytesIO()
    # The TorchScript-based exporter warns that it is deprecated; it is the one that runs on both
    # supported torch versions without onnxscript (the module docstring).
    with warnings.catch_warnings(), torch.inference_mode(False), torch.no_grad():
        warnings.simplefilter("ignore")
        torch.onnx.export(model, example_inputs(checkpoint.model_config), buffer, input_names=list(INPUT_NAMES),
                          output_names=[OUTPUT_NAME], opset_version=OPSET, dynamo=False,
                          dynamic_axes={name: {0: "batch"} for name in (*INPUT_NAMES, OUTPUT_NAME)})
    proto = onnx.load_from_string(buffer.getvalue())
    metadata = policy_metadata(checkpoint, source, source_sha256)
    for value in proto.graph.input:
        if value.name in metadata["inputs"]:
            value.doc_string = metadata["inputs"][value.name]["values"]
    proto.graph.output[0].doc_string = metadata["outputs"][OUTPUT_NAME]["values"]
    proto.producer_name = "ditch_drake"
    proto.producer_version = ditch_drake.__version__
    proto.doc_string = (f"ditch_drake behavioural-cloning policy from {source or 'a checkpoint'}: inputs "
                        f"{list(INPUT_NAMES)} (raw), output {OUTPUT_NAME!r}; see metadata {METADATA_KEY!r}")
    entry = proto.metadata_props.add()
    entry.key, entry.value = METADATA_KEY, json.dumps(metadata)
    return proto.SerializeToString()


def export_policy(checkpoint: str, out: str | os.PathLike, format: str = "onnx", quantizer=None) -> dict:
    """Writes the policy of `checkpoint` (a shipped name or a .pt file) to `out` in `format`,
    atomically; returns a summary (what the command line prints).

    Args:
        quantizer: None (float32), or a function (checkpoint, model bytes) -> (model bytes,
            summary) that rewrites the exported model (`onnx_quantize.int8_quantizer`).

    Raises:
        ConfigError: an unknown format, an unwritable `out`, a .onnx given as the checkpoint, or
            the onnx package missing.
        CheckpointError: no such checkpoint, or one that does not load.
    """
    if format not in POLICY_FORMATS:
        raise ConfigError(f"--format {format!r}: expected one of {list(POLICY_FORMATS)}")
    if is_onnx_path(checkpoint):
        raise ConfigError(f"checkpoint {str(checkpoint)!r} is already an ONNX model; expected a .pt checkpoint or "
                          "a shipped model name to export")
    path = resolve_checkpoint_path(checkpoint)
    out = prepare_output(out, "--out")
    require_module("onnx", "exporting a policy to ONNX")
    sha256 = file_sha256(path)
    policy = load_checkpoint(path)
    model = export_onnx(policy, str(checkpoint), sha256)
    summary = {"quantize": "none"}
    if quantizer is not None:
        model, summary = quantizer(policy, model)
    atomic_write_bytes(out, model)
    return {"out": str(out), "format": format, "opset": OPSET, "bytes": len(model), "inputs": list(INPUT_NAMES),
            "output": OUTPUT_NAME, "metadata_key": METADATA_KEY, "source_checkpoint": str(checkpoint),
            "source_checkpoint_sha256": sha256, **summary}


@dataclass
class OnnxPolicy:
    """An ONNX policy as read and checked by `read_onnx_policy`.

    Attributes:
        path: the file.
        model: its bytes (what an `onnxruntime.InferenceSession` takes).
        metadata: the JSON object under `METADATA_KEY`.
        model_config: the network's shape, from the metadata.
        action_commands: (num_labels, 2) [v m/s, w rad/s] per label, from the metadata.
        opset: the default domain's operator set.
    """

    path: Path
    model: bytes
    metadata: dict
    model_config: ModelConfig
    action_commands: np.ndarray
    opset: int


def _bad(path: Path, problem: str) -> CheckpointError:
    return CheckpointError(f"{path}: {problem}; expected {EXPECTED_ONNX}")


def _read_metadata(proto, path: Path) -> dict:
    entries = {entry.key: entry.value for entry in proto.metadata_props}
    if METADATA_KEY not in entries:
        raise _bad(path, f"no {METADATA_KEY!r} metadata (keys: {sorted(entries)})")
    try:
        metadata = json.loads(entries[METADATA_KEY])
    except json.JSONDecodeError as error:
        raise _bad(path, f"its {METADATA_KEY!r} metadata is not JSON ({error})") from error
    if not isinstance(metadata, dict) or metadata.get("schema") != SCHEMA:
        found = metadata.get("schema") if isinstance(metadata, dict) else type(metadata).__name__
        raise _bad(path, f"its {METADATA_KEY!r} metadata has schema {found!r}")
    version = metadata.get("schema_version")
    if not isinstance(version, int) or isinstance(version, bool) or not 1 <= version <= SCHEMA_VERSION:
        raise CheckpointError(f"{path}: metadata schema_version {version!r}, written by ditch_drake "
                              f"{metadata.get('code_version')!r}; this code ({ditch_drake.__version__}) reads "
                              f"1..{SCHEMA_VERSION}")
    return metadata


def _shape(value) -> list:
    """A graph value's dims: ints where fixed, names (or None) where symbolic."""
    return [dim.dim_value if dim.HasField("dim_value") else (dim.dim_param or None)
            for dim in value.type.tensor_type.shape.dim]


def _check_signature(proto, config: ModelConfig, path: Path, onnx) -> None:
    """The graph's inputs and output against the names, dtypes and shapes `config` gives."""
    initializers = {tensor.name for tensor in proto.graph.initializer}
    inputs = {value.name: value for value in proto.graph.input if value.name not in initializers}
    expected = {name: [None, *shape[1:]] for name, shape in
                ((name, spec["shape"]) for name, spec in _input_descriptions(config).items())}
    if sorted(inputs) != sorted(expected):
        raise _bad(path, f"inputs {sorted(inputs)}")
    float32 = onnx.TensorProto.FLOAT
    for name, want in expected.items():
        value = inputs[name]
        dtype = onnx.TensorProto.DataType.Name(value.type.tensor_type.elem_type)
        shape = _shape(value)
        if value.type.tensor_type.elem_type != float32 or len(shape) != len(want) or shape[1:] != want[1:]:
            raise _bad(path, f"input {name!r} is {dtype} of shape {shape}; this model config needs float32 of shape "
                             f"[batch, {', '.join(map(str, want[1:]))}]")
    outputs = {value.name: value for value in proto.graph.output}
    logits = outputs.get(OUTPUT_NAME)
    if len(outputs) != 1 or logits is None or logits.type.tensor_type.elem_type != float32 or (
            _shape(logits)[1:] != [config.num_labels]):
        found = {name: _shape(value) for name, value in outputs.items()}
        raise _bad(path, f"outputs {found}; this model config needs one float32 {OUTPUT_NAME!r} of shape "
                         f"[batch, {config.num_labels}]")


def read_onnx_policy(path: str | os.PathLike, allow_other_action_table: bool = False) -> OnnxPolicy:
    """Reads and checks an ONNX policy written by `export_onnx` (no session is made).

    The action table is refused when it is not `actions.COMMANDS`, as `load_checkpoint` refuses
    a checkpoint's, unless `allow_other_action_table`.

    Raises:
        CheckpointNotFoundError: no file at `path`, or a folder.
        CheckpointError: naming the file and what was expected, for a file that is not an ONNX
            model, an opset below `OPSET` or newer than the installed onnx knows, missing or
            foreign metadata, or inputs and output that do not match the metadata's model config.
        ConfigError: the onnx package is not installed.
    """
    onnx = require_module("onnx", f"reading the ONNX policy {path}")
    path = resolve_checkpoint_path(path)
    model = path.read_bytes()
    try:
        proto = onnx.load_from_string(model)
    except Exception as error:  # protobuf raises DecodeError, onnx its own, for bytes that are not a model.
        raise _bad(path, f"not a readable ONNX model ({type(error).__name__})") from error
    if not len(proto.graph.node):
        raise _bad(path, "not an ONNX model (no graph)")
    opsets = {entry.domain or "ai.onnx": entry.version for entry in proto.opset_import}
    opset = opsets.get("ai.onnx")
    newest = onnx.defs.onnx_opset_version()
    if opset is None or not OPSET <= opset <= newest:
        raise CheckpointError(f"{path}: ONNX opset {opset}; expected an opset in {OPSET}..{newest} (the exporter writes "
                              f"{OPSET}; the installed onnx {onnx.__version__} knows up to {newest})")
    metadata = _read_metadata(proto, path)
    try:
        config = ModelConfig.from_dict(metadata["model_config"])
        config.image_feature_size()
        commands = np.asarray(metadata["action_commands"], dtype=float)
    except (KeyError, TypeError, ValueError) as error:
        raise _bad(path, f"its metadata's model_config or action_commands is missing or malformed ({error})") from error
    if commands.shape != (config.num_labels, 2) or not np.all(np.isfinite(commands)):
        raise _bad(path, f"metadata action_commands of shape {commands.shape}; the model config needs "
                         f"({config.num_labels}, 2) finite [v m/s, w rad/s] rows")
    if not allow_other_action_table and (
            commands.shape != actions.COMMANDS.shape or not np.allclose(commands, actions.COMMANDS)):
        raise CheckpointError(f"{path} was exported with another action table {commands.tolist()}; expected "
                              f"ditch_drake.spec.actions.COMMANDS {actions.COMMANDS.tolist()}")
    _check_signature(proto, config, path, onnx)
    return OnnxPolicy(path=path, model=model, metadata=metadata, model_config=config, action_commands=commands,
                      opset=opset)


def onnxruntime_session(model: bytes, num_threads: int = 1, where: str = "the ONNX policy"):
    """An `onnxruntime.InferenceSession` of `model` on the CPU with `num_threads` intra-op
    threads (and one inter-op thread): one forward pass of one sample gains little from more,
    and rollouts run one process per core.

    Raises:
        ConfigError: onnxruntime is not installed, or `num_threads` < 1.
        CheckpointError: onnxruntime cannot load the model, naming `where`.
    """
    onnxruntime = require_module("onnxruntime", "runtime 'onnxruntime'")
    if not (isinstance(num_threads, int) and num_threads >= 1):
        raise ConfigError(f"num_threads={num_threads!r}: expected an integer >= 1 for onnxruntime")
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = num_threads
    options.inter_op_num_threads = 1
    options.log_severity_level = 3  # Errors only: its optimizer's notes are not the user's business.
    try:
        return onnxruntime.InferenceSession(model, sess_options=options, providers=["CPUExecutionProvider"])
    except Exception as error:  # onnxruntime raises its own Fail / InvalidGraph / NotImplemented.
        reason = " ".join(str(error).split())[:300]
        raise CheckpointError(f"{where}: onnxruntime {onnxruntime.__version__} cannot load it ({reason}); expected "
                              f"{EXPECTED_ONNX}") from error


def network_feeds(arrays: ArraySet, rows: np.ndarray, reflect: bool = False) -> list[dict[str, np.ndarray]]:
    """The network's inputs of `rows` of `arrays` as float32 arrays by input name: one feed,
    and with `reflect` a second of their left-right reflections (`mirror_left_right`)."""
    batch = {"image": images_to_float32(arrays.image[rows]),
             **{name: np.asarray(getattr(arrays, name)[rows], dtype=np.float32)
                for name in ("imu", "distance", "bearing")}}
    views = [batch]
    if reflect:
        mirrored = {name: value.copy() for name, value in batch.items()}
        mirror_left_right(mirrored)
        views.append(mirrored)
    return [{name: np.ascontiguousarray(view[name]) for name in INPUT_NAMES} for view in views]


def label_agreement(checkpoint: PolicyCheckpoint, model: bytes, arrays: ArraySet, rows: np.ndarray | None = None,
                    reflect: bool = False, batch_size: int = 256) -> dict:
    """How often the ONNX model's argmax equals torch's on samples of `arrays`.

    Args:
        checkpoint: the torch side.
        model: the ONNX side (`export_onnx`'s bytes, or a file's).
        arrays: the samples (images in memory or on disk, as `train` takes them).
        rows: which samples (None: all).
        reflect: also each sample's left-right reflection (what a canonical_side model is fed
            where the crossing turns left).
        batch_size: samples per forward pass.

    Returns:
        {"samples", "agreeing", "agreement", "max_abs_logit_diff", "flipped_margins"}: the
        flipped margins are torch's gap between its two best logits where the labels differ.
    """
    rows = np.arange(len(arrays.label)) if rows is None else np.asarray(rows)
    torch_model = checkpoint.build_model()
    session = onnxruntime_session(model)
    samples = agreeing = 0
    max_diff, flipped = 0.0, []
    for start in range(0, len(rows), batch_size):
        for feed in network_feeds(arrays, np.sort(rows[start:start + batch_size]), reflect):
            with torch.inference_mode():
                reference = torch_model(*(torch.from_numpy(feed[name]) for name in INPUT_NAMES)).numpy()
            exported = session.run([OUTPUT_NAME], feed)[0]
            same = reference.argmax(axis=1) == exported.argmax(axis=1)
            samples += len(same)
            agreeing += int(same.sum())
            max_diff = max(max_diff, float(np.abs(reference - exported).max()))
            top2 = np.sort(reference[~same], axis=1)[:, -2:]
            flipped += (top2[:, 1] - top2[:, 0]).tolist()
    return {"samples": samples, "agreeing": agreeing, "agreement": agreeing / samples if samples else math.nan,
            "max_abs_logit_diff": max_diff, "flipped_margins": flipped}
