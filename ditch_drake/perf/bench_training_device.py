"""The training path on an accelerator: samples per second, epoch time, and whether the loader
keeps the device busy.

    python -m ditch_drake.perf.bench_training_device [--device cuda] [--samples 16000]
        [--batches 96] [--workers 0 2 4 8] [--precision fp32 bf16]

A synthetic dataset folder (`bench_training.write_synthetic_store`: random frames, driving-like
labels) is streamed by the real path (`load_training_set`, `train`) with each loader worker count
and precision: two epochs of `--batches` batches (the paper recipe's 96), random oversampling,
no early stop; the second epoch's time is the steady state (the first pays cuDNN's autotuning and
the workers' start). An epoch's time includes its validation pass (`val_samples`, forward only), as
in training; the rate counts the training samples alone, so it is a little below the steps'
own. Beside it, the same network's training steps on one batch already on the
device, with no loader at all: the compute's own rate. `loader_busy_fraction` is the loader path's
rate over that rate: 1 when the device never waits for data.

Prints one JSON object. Runs on a CPU too (`--device cpu`), where the compute-only rate is the
one `ditch-drake bench --json` prints as `train_samples_per_s`.
"""

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path


def compute_only_samples_per_s(device: str, precision: str, batches: int = 30, warmup: int = 5) -> float:
    """Training samples per second of forward, backward and step on one batch held on `device`."""
    import torch
    from torch import nn

    from ditch_drake.learning.model import FourInputClassifier, parameter_groups
    from ditch_drake.learning.train import TrainConfig

    config = TrainConfig()
    generator = torch.Generator().manual_seed(0)
    model = FourInputClassifier(config.model).to(device)
    optimizer = torch.optim.Adam(parameter_groups(model, config.lr, config.scalar_lr_factor))
    size = config.batch_size
    model_config = config.model
    inputs = [torch.rand(size, model_config.image_channels, model_config.image_size, model_config.image_size,
                         generator=generator),
              torch.rand(size, model_config.imu_size, generator=generator),
              torch.rand(size, model_config.distance_size, generator=generator),
              torch.rand(size, model_config.bearing_size, generator=generator)]
    inputs = [value.to(device) for value in inputs]
    labels = torch.randint(0, model_config.num_labels, (size,), generator=generator).to(device)
    model.train()
    device_type = torch.device(device).type
    for step in range(warmup + batches):
        if step == warmup:
            if device_type == "cuda":
                torch.cuda.synchronize()
            start = time.perf_counter()
        with torch.autocast(device_type, torch.bfloat16, precision == "bf16"):
            loss = nn.functional.cross_entropy(model(*inputs), labels)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    if device_type == "cuda":
        torch.cuda.synchronize()
    return batches * size / (time.perf_counter() - start)


def loader_epochs(store: Path, device: str, precision: str, workers: int, batches: int) -> dict:
    """Two epochs of `train` streaming from `store`: each epoch's seconds and the second's rate."""
    from ditch_drake.demos.training_set import load_training_set
    from ditch_drake.learning.train import TrainConfig, train

    arrays = load_training_set([store])
    config = TrainConfig(epochs=2, patience=2, max_batches_per_epoch=batches, device=device, precision=precision,
                         num_workers=workers, balancing="oversample")
    result = train(arrays, config, progress=False)
    seconds = [record["seconds"] for record in result.history]
    return {"epoch_s": seconds, "samples_per_s": batches * config.batch_size / seconds[-1],
            "val_samples": int(result.checkpoint.training["num_val_samples"])}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m ditch_drake.perf.bench_training_device",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--samples", type=int, default=16_000, help="samples in the synthetic dataset")
    parser.add_argument("--batches", type=int, default=96, help="batches per epoch")
    parser.add_argument("--workers", type=int, nargs="+", default=[0, 2, 4, 8], help="loader worker counts")
    parser.add_argument("--precision", nargs="+", default=["fp32"], choices=["fp32", "bf16"])
    args = parser.parse_args(argv)
    import torch

    if torch.device(args.device).type == "cuda" and not torch.cuda.is_available():
        print(f"--device {args.device}: torch sees no CUDA device here", file=sys.stderr)
        raise SystemExit(2)
    from ditch_drake.perf.bench_training import write_synthetic_store

    figures = {"device": args.device, "torch": torch.__version__, "cpu_count": os.cpu_count(),
               "samples": args.samples, "batches_per_epoch": args.batches}
    if torch.device(args.device).type == "cuda":
        figures["device_name"] = torch.cuda.get_device_name()
    with tempfile.TemporaryDirectory(prefix="ditch_drake_device_") as folder:
        start = time.perf_counter()
        store = write_synthetic_store(Path(folder) / "store", args.samples)
        figures["store_write_s"] = time.perf_counter() - start
        for precision in args.precision:
            compute = compute_only_samples_per_s(args.device, precision)
            figures[f"compute_only_{precision}_samples_per_s"] = compute
            print(json.dumps({f"compute_only_{precision}_samples_per_s": compute}), file=sys.stderr, flush=True)
            for workers in args.workers:
                run = loader_epochs(store, args.device, precision, workers, args.batches)
                key = f"{precision}_workers{workers}"
                figures[f"{key}_epoch_s"] = run["epoch_s"][-1]
                figures[f"{key}_first_epoch_s"] = run["epoch_s"][0]
                figures[f"{key}_samples_per_s"] = run["samples_per_s"]
                figures[f"{key}_loader_busy_fraction"] = run["samples_per_s"] / compute
                figures["val_samples"] = run["val_samples"]
                print(json.dumps({key: run}), file=sys.stderr, flush=True)
    print(json.dumps(figures, indent=1))


if __name__ == "__main__":
    main()
