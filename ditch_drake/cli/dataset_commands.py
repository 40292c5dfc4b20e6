"""`ditch-drake dataset`: what a dataset folder holds, converting older folders, exports."""

import json

from ditch_drake.cli.options import Commands, add_json, print_table

EXPORT_FORMATS = ("lerobot", "robomimic")


def add_dataset(commands: Commands) -> None:
    dataset = commands.add("dataset", "dataset folders: info, convert (from .npz folders), export (LeRobot, robomimic)")
    actions = dataset.add_subparsers(dest="dataset_command", required=True, metavar="ACTION",
                                     help="info, convert or export (each has its own --help)")
    info = actions.add_parser("info", help="episodes, steps, counts per label, task, split and driver",
                              description="episodes, steps, counts per label, task, split and driver")
    info.add_argument("path", help="a dataset folder (or an older folder of demo_NNN.npz files)")
    add_json(info)
    info.set_defaults(run=cmd_dataset_info)
    convert = actions.add_parser("convert", help="copy a folder of demo_NNN.npz files into a dataset folder, "
                                 "losslessly (resumable)",
                                 description="copy a folder of demo_NNN.npz files into a dataset folder, "
                                 "losslessly; run again, it converts only what is missing")
    convert.add_argument("source", help="folder of demo_NNN.npz files")
    convert.add_argument("destination", help="dataset folder to write (made if missing)")
    convert.set_defaults(run=cmd_dataset_convert)
    export = actions.add_parser("export", help="write a dataset in LeRobotDataset v3 or robomimic HDF5 layout",
                                description="write a dataset in LeRobotDataset v3 layout (a folder) or robomimic's "
                                "HDF5 layout (a file); needs the export extra: pip install -e '.[export]'")
    export.add_argument("path", help="a dataset folder")
    export.add_argument("--format", required=True, choices=EXPORT_FORMATS, help="the layout to write")
    export.add_argument("--out", required=True,
                        help="what to write: a folder for lerobot, a .hdf5 file for robomimic (must not exist)")
    export.set_defaults(run=cmd_dataset_export)


def cmd_dataset_info(args) -> int:
    from ditch_drake.demos.dataset import dataset_summary, load_dataset
    from ditch_drake.demos.store import DatasetStore, is_store, store_summary
    from ditch_drake.spec.actions import ANGULAR_RATES_RADPS

    if is_store(args.path):
        summary = store_summary(DatasetStore.open(args.path))
    else:
        summary = dataset_summary(load_dataset(args.path))
    if args.json:
        print(json.dumps(summary))
        return 0
    print(f"{args.path}: {summary['demonstrations']} demonstrations, {summary['steps']} steps"
          + (f", {summary['disk_mib']:.0f} MiB on disk" if "disk_mib" in summary else ""))
    print("per task: " + ", ".join(f"{name} {count}" for name, count in summary["per_task"].items()))
    print("outcomes: " + ", ".join(f"{name} {count}" for name, count in sorted(summary["per_outcome"].items())))
    print("driven by: " + ", ".join(f"{name} {count}" for name, count in summary["per_driver"].items()))
    if "per_split" in summary:
        print("splits: " + ", ".join(f"{name} {count}" for name, count in sorted(summary["per_split"].items())))
        print(f"environments: {len(summary['per_environment'])}; steps a supervisor took over: "
              f"{summary['intervened_steps']}")
    rows = [{"label": label, "w_radps": f"{rate:+.2f}", "steps": count,
             "share": f"{count / max(1, summary['steps']):.1%}"}
            for label, (rate, count) in enumerate(zip(ANGULAR_RATES_RADPS, summary["per_label"]))]
    print_table(rows, ["label", "w_radps", "steps", "share"])
    print(f"straight (label 8) share {summary['straight_fraction']:.1%}; "
          f"majority/minority ratio {summary['majority_to_minority_ratio']:.1f}")
    return 0


def cmd_dataset_convert(args) -> int:
    from ditch_drake.demos.store import convert_npz_folder

    print(json.dumps(convert_npz_folder(args.source, args.destination), indent=2))
    return 0


def cmd_dataset_export(args) -> int:
    from ditch_drake.demos.exports import export_dataset

    print(json.dumps(export_dataset(args.path, args.format, args.out), indent=2))
    return 0
