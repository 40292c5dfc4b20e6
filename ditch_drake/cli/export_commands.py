"""Commands that take a policy out of the package: export-policy."""

import json

import numpy as np

from ditch_drake.cli.options import Commands, ConfigDefault, add_out

EXPORT = "ditch_drake.learning.onnx_policy:export_policy"
QUANTIZE = "ditch_drake.learning.onnx_quantize:check_quantization"
INT8 = "ditch_drake.learning.onnx_quantize:int8_quantizer"


def add_export_policy(commands: Commands) -> None:
    export = commands.add("export-policy", "write a checkpoint's network as an ONNX model for ONNX Runtime or "
                                           "TensorRT (pip install -e '.[onnx]')")
    export.add_argument("checkpoint", metavar="CHECKPOINT", help="a shipped model name or a .pt file")
    export.add_argument("--format", default=ConfigDefault(EXPORT, "format"),
                        help="the model format; one of: onnx (opset 17; inputs image, imu, distance, bearing raw, "
                             "output logits, the action table and model config in its metadata)")
    add_out(export, "the file to write (atomically), e.g. policy.onnx")
    export.add_argument("--quantize", default=ConfigDefault(QUANTIZE, "quantize"),
                        help="none (float32) or int8 (the convolutions in 8-bit integers, QDQ format, calibrated "
                             "on --calibration-data; its labels differ from the float model's on a few samples)")
    export.add_argument("--calibration-data", action="append", default=[], metavar="DIR",
                        help="with --quantize int8: a dataset folder (repeatable) holding demonstrations the "
                             "checkpoint trained on; its validation demonstrations are never drawn")
    export.add_argument("--calibration-samples", type=int, default=ConfigDefault(INT8, "calibration_samples"),
                        help="with --quantize int8: how many samples, drawn with --seed, set the activations' ranges")
    export.add_argument("--seed", type=int, default=ConfigDefault(INT8, "seed"),
                        help="with --quantize int8: the seed of the calibration samples' draw")
    export.add_argument("--check-data", action="append", default=[], metavar="DIR",
                        help="after writing, run the written model and the checkpoint on the samples of this "
                             "dataset folder (repeatable) and print how often their labels agree (default: none)")
    export.add_argument("--check-split", choices=["all", "val"], default="all",
                        help="with --check-data: every sample, or those of the demonstrations the checkpoint "
                             "validated on (its val_demo_ids: the folders' demonstrations numbered in the order "
                             "given, as train numbers them)")
    export.set_defaults(run=cmd_export_policy)


def cmd_export_policy(args) -> int:
    from ditch_drake.learning.onnx_policy import export_policy
    from ditch_drake.learning.onnx_quantize import check_quantization, int8_quantizer

    check_quantization(args.quantize, args.calibration_data)
    quantizer = None
    if args.quantize == "int8":
        from ditch_drake.demos.training_set import load_training_set

        quantizer = int8_quantizer(load_training_set(args.calibration_data), args.calibration_data,
                                   args.calibration_samples, args.seed)
    report = export_policy(args.checkpoint, args.out, args.format, quantizer)
    if args.check_data:
        report["check"] = check_export(args.checkpoint, args.out, args.check_data, args.check_split)
    print(json.dumps(report, indent=2))
    return 0


def check_export(checkpoint: str, model_path: str, folders: list[str], split: str = "all") -> dict:
    """How often the ONNX model at `model_path` and the checkpoint choose the same label on the
    samples of `folders` (and their reflections, for a canonical-side checkpoint).

    With `split` "val", only the demonstrations whose numbers are the checkpoint's
    `val_demo_ids`; the result gives the number of validation samples the checkpoint recorded
    beside the number found, which differ where the folders are not its training data.

    Raises:
        DatasetError: a folder that is not a dataset.
    """
    from pathlib import Path

    from ditch_drake.demos.training_set import load_training_set
    from ditch_drake.learning.checkpoint import load_checkpoint, resolve_checkpoint_path
    from ditch_drake.learning.onnx_policy import label_agreement, read_onnx_policy

    policy = load_checkpoint(resolve_checkpoint_path(checkpoint))
    arrays = load_training_set(folders)
    rows = None
    if split == "val":
        rows = np.flatnonzero(np.isin(arrays.demo_id, policy.training.get("val_demo_ids", [])))
    result = label_agreement(policy, read_onnx_policy(Path(model_path)).model, arrays, rows,
                             reflect=policy.model_config.canonical_side)
    flipped = result.pop("flipped_margins")
    return {**result, "data": folders, "split": split, "reflected": policy.model_config.canonical_side,
            "largest_flipped_margin": max(flipped, default=0.0),
            "checkpoint_val_samples": policy.training.get("num_val_samples")}
