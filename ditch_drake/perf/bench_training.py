"""Memory of the training pipeline and time of one learned-policy step.

Run: `python -m ditch_drake.perf.bench_training [samples]`. Prints
{"policy_step_ms": ..., "train_peak_rss_mib": ..., ...} (keys end with their unit).

- `measure_policy_step_ms`: median wall time of one `LearnedPolicy` update (read the four
  stacked inputs, one forward pass, softmax, its uncertainty signal, write the state) on one
  CPU thread, with random weights (the time does not depend on them).
- `measure_ensemble_policy_step_ms`: the same for a 5-member ensemble (`EnsembleNetwork`: all
  members in one forward pass, their mean probabilities and uncertainty), in float32 and, on a
  CPU that runs bfloat16 natively, with its image branch in bfloat16 (`precision:
  bfloat16_image`), the two taking turns update by update.
- `measure_streaming_memory`: peak resident memory of the training pipeline streaming from a
  dataset folder, each in a fresh process that writes a synthetic store (random frames, label
  8 dominant) into a temporary folder and trains on it as `ditch-drake train --data` does
  (`load_training_set`, then `train`: split, input statistics, class balancing, a few
  training batches and a whole validation pass, whose memory does not grow with its length),
  on one thread. `train_peak_rss_mib` is for one environment's 40 demonstrations (40 episodes
  of 400 steps, 16 k samples), `train_peak_rss_8x_mib` for 8 times as many episodes (128 k
  samples; the target is at most 1.2 times the 16 k figure, `train_rss_8x_ratio`). Both
  balance by "oversample" (`MEMORY_BALANCING`), which draws rows again by index, so the
  figures are the pipeline's own. The 8x run holds out 1/8 of the 16 k run's share of the
  demonstrations for validation, the same 3,200 samples, so that its validation pass takes
  as long (a full one over 25 k samples would take minutes more, for logits of 68 bytes a
  sample). The 16 k run also times every balancing method but SMOTE on its training split
  (`balancing_<method>_s`: milliseconds, labels only).
- `measure_smote_memory` (`ditch-drake bench --training`): the same 16 k run balanced by
  SMOTE, the paper's and the default (`train_peak_rss_smote_mib`, `balancing_smote_s`:
  minutes).
"""

import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ditch_drake.spec.actions import NUM_LABELS, STRAIGHT_LABEL
from ditch_drake.spec.observation_layout import (
    BEARING_STACK_SIZE,
    DISTANCE_STACK_SIZE,
    IMAGE_STACK_SHAPE,
    IMU_STACK_SIZE,
)

TRAINING_SAMPLES = 16_000
DEMOS = 40
# How many times more episodes the second streaming run has (`train_peak_rss_8x_mib`).
SCALE = 8
# The balancing of the streaming memory runs: rows drawn again by index, no copies.
MEMORY_BALANCING = "oversample"
VAL_FRACTION = 0.2


def _driving_labels(rng: np.random.Generator, samples: int) -> np.ndarray:
    """Label 8 for 55 % of the samples; the rest fall off as exp(-|l - 8| / 3) around it."""
    weights = np.exp(-np.abs(np.arange(NUM_LABELS) - STRAIGHT_LABEL) / 3.0)
    weights[STRAIGHT_LABEL] = 0.0
    weights = 0.45 * weights / weights.sum()
    weights[STRAIGHT_LABEL] = 0.55
    return rng.choice(NUM_LABELS, samples, p=weights)


def write_synthetic_store(folder: str | os.PathLike, samples: int, demos: int = DEMOS, seed: int = 0) -> Path:
    """A dataset store of `demos` episodes of samples // demos steps each (`DatasetStore.append`):
    random frames and scalars, driving-like labels (`_driving_labels`)."""
    from ditch_drake.demos.dataset import Demonstration, standard_metadata
    from ditch_drake.demos.store import DatasetStore

    store = DatasetStore.create(folder)
    steps = samples // demos
    for index in range(demos):
        rng = np.random.default_rng([seed, index])
        arrays = {
            "image": rng.integers(0, 256, (steps, *IMAGE_STACK_SHAPE[1:]), dtype=np.uint8),
            "imu_stack": rng.normal(0.0, 0.2, (steps, IMU_STACK_SIZE)).astype(np.float32),
            "distance_stack": rng.uniform(0.0, 20.0, (steps, DISTANCE_STACK_SIZE)).astype(np.float32),
            "bearing_stack": rng.uniform(-np.pi, np.pi, (steps, BEARING_STACK_SIZE)).astype(np.float32),
            "label": _driving_labels(rng, steps).astype(np.int16),
            "time_s": np.arange(steps) * 0.1,
            "pose": np.zeros((steps, 6), np.float32),
            "raw_command": np.zeros((steps, 2), np.float32),
        }
        metadata = standard_metadata(environment="wide", task={"index": index % 3, "name": "synthetic"}, seed=index,
                                     outcome={"status": "reached_goal"}, control_period_s=0.1)
        store.append(Demonstration(arrays, metadata), index)
    return Path(folder)


def _streaming_memory_worker(samples: int, demos: int, val_fraction: float, balancing: str) -> dict:
    """Runs in a fresh process: writes a synthetic store and trains on it, streaming."""
    from ditch_drake.demos.training_set import load_training_set
    from ditch_drake.learning.balance import balance_training_split
    from ditch_drake.learning.config import BALANCING_METHODS
    from ditch_drake.learning.data import InputStats, split_indices_by_demo
    from ditch_drake.learning.train import TrainConfig, train

    with tempfile.TemporaryDirectory(prefix="ditch_drake_bench_") as folder:
        start = time.perf_counter()
        write_synthetic_store(Path(folder) / "store", samples, demos)
        written = time.perf_counter()
        arrays = load_training_set([Path(folder) / "store"])
        config = TrainConfig(epochs=1, max_batches_per_epoch=4, num_threads=1, balancing=balancing,
                             val_fraction=val_fraction)
        result = train(arrays, config, progress=False)
        figures = {
            "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "store_write_s": written - start,
            "pipeline_s": time.perf_counter() - written,
            "val_samples": int(result.checkpoint.training["num_val_samples"]),
            "balancing_s": float(result.checkpoint.training["balancing_seconds"]),
        }
        if balancing == MEMORY_BALANCING:  # The other quick methods' time on the same split.
            train_rows, _ = split_indices_by_demo(arrays.demo_id, val_fraction, config.seed)
            stats = InputStats.fit(arrays, train_rows)
            for method in BALANCING_METHODS:
                if method != "smote":
                    made = balance_training_split(arrays, train_rows, stats, TrainConfig(balancing=method))
                    figures[f"balancing_{method}_s"] = made.seconds
        return figures


def _run_worker(samples: int, demos: int, val_fraction: float, balancing: str) -> dict:
    completed = subprocess.run(
        [sys.executable, "-m", "ditch_drake.perf.bench_training", "--memory-worker", str(samples), str(demos),
         repr(val_fraction), balancing],
        check=True,
        capture_output=True,
        text=True,
    )
    return json.loads(completed.stdout.strip().splitlines()[-1])


def measure_streaming_memory(samples: int = TRAINING_SAMPLES, scale: int = SCALE) -> dict:
    """Peak RSS (MiB) of the training pipeline streaming from a synthetic store of `samples`
    samples, and of `scale` times as many episodes, each in a fresh process (module docstring).

    Returns:
        {"train_peak_rss_mib", "train_peak_rss_8x_mib", "train_rss_8x_ratio",
        "train_pipeline_s", "train_pipeline_8x_s" (loading the set's index, balancing, the
        batches and the validation pass; writing the store is not in it), and
        "balancing_<method>_s" for every method but SMOTE, on the 16 k training split}.
    """
    small = _run_worker(samples, DEMOS, VAL_FRACTION, MEMORY_BALANCING)
    large = _run_worker(samples * scale, DEMOS * scale, VAL_FRACTION / scale, MEMORY_BALANCING)
    return {
        "train_peak_rss_mib": small["peak_rss_mib"],
        "train_peak_rss_8x_mib": large["peak_rss_mib"],
        "train_rss_8x_ratio": large["peak_rss_mib"] / small["peak_rss_mib"],
        "train_pipeline_s": small["pipeline_s"],
        "train_pipeline_8x_s": large["pipeline_s"],
        **{key: value for key, value in small.items() if key.startswith("balancing_") and key != "balancing_s"},
    }


def measure_smote_memory(samples: int = TRAINING_SAMPLES) -> dict:
    """The 16 k streaming run balanced by SMOTE (the default, the paper's), in a fresh process.

    Returns:
        {"train_peak_rss_smote_mib", "balancing_smote_s", "train_pipeline_smote_s"}.
    """
    run = _run_worker(samples, DEMOS, VAL_FRACTION, "smote")
    return {"train_peak_rss_smote_mib": run["peak_rss_mib"], "balancing_smote_s": run["balancing_s"],
            "train_pipeline_smote_s": run["pipeline_s"]}


def measure_policy_step_ms(repeats: int = 50) -> dict:
    """Median time (ms) of one `LearnedPolicy` discrete update on one thread.

    Returns:
        {"policy_step_ms": median, "policy_step_max_ms": slowest}.
    """
    from pydrake.systems.analysis import Simulator  # noqa: F401 (loads Drake's analysis module)

    from ditch_drake.learning.checkpoint import make_checkpoint
    from ditch_drake.learning.model import FourInputClassifier
    from ditch_drake.systems.policy import LearnedPolicy

    times = _policy_update_times(LearnedPolicy(make_checkpoint(FourInputClassifier()), num_threads=1), repeats)
    return {"policy_step_ms": 1e3 * float(np.median(times)), "policy_step_max_ms": 1e3 * float(np.max(times))}


def measure_onnxruntime_policy_step_ms(repeats: int = 50) -> dict:
    """`measure_policy_step_ms` with the network run by ONNX Runtime (`runtime: onnxruntime`, one
    thread), as exported and quantized to int8 (`export-policy --quantize int8`); none without
    the `onnx` extra, which says so on stderr.

    Returns:
        {"policy_step_onnxruntime_ms": median, "policy_step_onnxruntime_max_ms": slowest, and the
        same with "_int8" before "_ms"}, or {}.
    """
    import importlib.util

    if importlib.util.find_spec("onnxruntime") is None:
        print("bench: onnxruntime is not installed (pip install -e '.[onnx]'): no policy_step_onnxruntime_ms",
              file=sys.stderr)
        return {}
    from pydrake.systems.analysis import Simulator  # noqa: F401 (loads Drake's analysis module)

    from ditch_drake.learning.checkpoint import make_checkpoint
    from ditch_drake.learning.inference import OnnxRuntimeInference
    from ditch_drake.learning.model import FourInputClassifier
    from ditch_drake.learning.onnx_policy import INPUT_NAMES, example_inputs, export_onnx
    from ditch_drake.learning.onnx_quantize import quantize_int8
    from ditch_drake.systems.policy import LearnedPolicy

    checkpoint = make_checkpoint(FourInputClassifier())
    model = export_onnx(checkpoint, "an untrained network", "0" * 64)
    # The int8 model is calibrated on seeded synthetic inputs: its speed does not depend on them.
    calibration = [dict(zip(INPUT_NAMES, (tensor.numpy() for tensor in example_inputs(checkpoint.model_config, 16,
                                                                                        seed))))
                   for seed in range(2)]
    models = {"": model, "_int8": quantize_int8(model, calibration, {"calibration_data": "synthetic"})}
    # One update of each in turn, so that a busy spell of a shared host slows both alike.
    policies = [LearnedPolicy(OnnxRuntimeInference(each, checkpoint.model_config, checkpoint.action_commands,
                                                   num_threads=1)) for each in models.values()]
    figures = {}
    for suffix, times in zip(models, _alternating_update_times(policies, repeats), strict=True):
        figures[f"policy_step_onnxruntime{suffix}_ms"] = 1e3 * float(np.median(times))
        figures[f"policy_step_onnxruntime{suffix}_max_ms"] = 1e3 * float(np.max(times))
    return figures


def measure_ensemble_policy_step_ms(members: int = 5, repeats: int = 50, noise: float = 0.01) -> dict:
    """Median time (ms) of one `LearnedPolicy` discrete update of a `members`-clone ensemble on
    one thread, timed as `measure_policy_step_ms` times one clone: all members in one forward
    pass (`EnsembleNetwork`), their mean probabilities and the default uncertainty signal; in
    float32 and with the image branch in bfloat16 ("bfloat16_image"). Beside them, in the same
    rounds, each member as a clone of its own (a float32 `LearnedPolicy`): one member's update,
    and the members' updates one after another, what the ensemble would cost unbatched. Every
    round updates each policy once, in turn, so that the host's changing load falls on all alike
    and their ratios hold. On a CPU without native bfloat16 (`native_bfloat16_flags`) the
    bfloat16 figures are None and stderr says why.

    The ensemble is the shipped `wide` model's weights copied `members` times, each copy's
    floating-point tensors perturbed by seeded Gaussian noise of `noise` times the tensor's
    own standard deviation: the trained network's shapes and value ranges for timing, not a
    trained ensemble (the members' values do not change the time).

    Returns:
        {"ensemble_policy_step_ms": median, "ensemble_policy_step_max_ms": slowest,
        "ensemble_policy_step_bfloat16_ms": median or None, "ensemble_policy_step_bfloat16_max_ms":
        slowest or None, "ensemble_member_policy_step_ms": member 0's median,
        "ensemble_members_in_turn_ms": the median over rounds of the members' summed updates}.
    """
    import dataclasses

    import torch
    from pydrake.systems.analysis import Simulator  # noqa: F401 (loads Drake's analysis module)

    from ditch_drake.common.errors import ConfigError
    from ditch_drake.learning.checkpoint import load_checkpoint, resolve_checkpoint_path
    from ditch_drake.learning.ensemble import EnsembleCheckpoint, EnsembleInference
    from ditch_drake.systems.policy import LearnedPolicy

    wide = load_checkpoint(resolve_checkpoint_path("wide"))
    generator = torch.Generator().manual_seed(0)

    def perturbed(tensor: torch.Tensor) -> torch.Tensor:
        if not tensor.is_floating_point() or tensor.numel() < 2:
            return tensor.clone()
        return tensor + noise * tensor.std() * torch.randn(tensor.shape, generator=generator, dtype=tensor.dtype)

    copies = [dataclasses.replace(wide, state_dict={name: perturbed(value) for name, value in wide.state_dict.items()})
              for _ in range(members)]
    ensemble = EnsembleCheckpoint(copies)
    policies = {"ensemble_policy_step": LearnedPolicy(EnsembleInference(ensemble, num_threads=1))}
    try:
        policies["ensemble_policy_step_bfloat16"] = LearnedPolicy(
            EnsembleInference(ensemble, num_threads=1, precision="bfloat16_image"))
    except ConfigError as error:
        print(f"bench: no ensemble_policy_step_bfloat16_ms: {error}", file=sys.stderr)
    clones = [LearnedPolicy(copy, num_threads=1) for copy in copies]
    figures = dict.fromkeys(f"ensemble_policy_step{kind}_ms" for kind in ("", "_max", "_bfloat16", "_bfloat16_max"))
    times = _alternating_update_times([*policies.values(), *clones], repeats)
    for name, each in zip(policies, times, strict=False):
        figures.update({f"{name}_ms": 1e3 * float(np.median(each)), f"{name}_max_ms": 1e3 * float(np.max(each))})
    clone_times = np.asarray(times[len(policies):])
    figures["ensemble_member_policy_step_ms"] = 1e3 * float(np.median(clone_times[0]))
    figures["ensemble_members_in_turn_ms"] = 1e3 * float(np.median(clone_times.sum(axis=0)))
    return figures


def _policy_update_times(policy, repeats: int) -> list[float]:
    """Wall times (s) of `repeats` forced discrete updates of `policy` on fixed random inputs,
    after 3 warm-up updates (oneDNN picks its kernels on the first calls)."""
    return _alternating_update_times([policy], repeats)[0]


def _alternating_update_times(policies: list, repeats: int) -> list[list[float]]:
    """`_policy_update_times` of each of `policies` (the same inputs for each), one update of
    each in turn: per policy, its `repeats` wall times (s)."""
    updates = []
    for policy in policies:
        context = policy.CreateDefaultContext()
        rng = np.random.default_rng(0)
        policy.GetInputPort("image_stack").FixValue(context, rng.random(int(np.prod(IMAGE_STACK_SHAPE))))
        policy.GetInputPort("imu_stack").FixValue(context, rng.normal(0.0, 0.2, IMU_STACK_SIZE))
        policy.GetInputPort("distance_stack").FixValue(context, rng.uniform(0.0, 20.0, DISTANCE_STACK_SIZE))
        policy.GetInputPort("bearing_stack").FixValue(context, rng.uniform(-3.0, 3.0, BEARING_STACK_SIZE))
        updates.append((policy, context, policy.AllocateDiscreteVariables()))
    times = [[] for _ in policies]
    for _ in range(repeats + 3):
        for (policy, context, state), record in zip(updates, times, strict=True):
            start = time.perf_counter()
            policy.CalcForcedDiscreteVariableUpdate(context, state)
            record.append(time.perf_counter() - start)
    return [record[3:] for record in times]


def measure_training_throughput(batches: int = 6, warmup: int = 2) -> dict:
    """Training samples per second of the paper's network with the default `TrainConfig`
    (batch 64, Adam, layer-specific rates; forward, backward and step) on random inputs."""
    import torch
    from torch import nn

    from ditch_drake.learning.model import FourInputClassifier, parameter_groups
    from ditch_drake.learning.train import TrainConfig

    config = TrainConfig()
    # `ditch-drake train` runs on all cores; an earlier benchmark (the policy step) may have
    # set torch's process-wide thread count to 1.
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(os.cpu_count() or 1)
    generator = torch.Generator().manual_seed(0)
    model = FourInputClassifier(config.model)
    optimizer = torch.optim.Adam(parameter_groups(model, config.lr, config.scalar_lr_factor))
    b = config.batch_size
    inputs = [torch.rand(b, *IMAGE_STACK_SHAPE, generator=generator), torch.rand(b, IMU_STACK_SIZE, generator=generator),
              torch.rand(b, DISTANCE_STACK_SIZE, generator=generator), torch.rand(b, BEARING_STACK_SIZE, generator=generator)]
    labels = torch.randint(0, NUM_LABELS, (b,), generator=generator)
    model.train()
    for step in range(warmup + batches):
        if step == warmup:
            start = time.perf_counter()
        loss = nn.functional.cross_entropy(model(*inputs), labels)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    figures = {"train_samples_per_s": batches * b / (time.perf_counter() - start)}
    torch.set_num_threads(previous_threads)
    return figures


def shipped_model_figures() -> dict:
    """What the shipped 40-demonstration checkpoints (`<env>_bc40`, trained on this machine's
    CPU) recorded when `ditch-drake train` made them: wall time of training (SMOTE and every
    epoch, s)."""
    from ditch_drake.learning.checkpoint import ENVIRONMENT_MODELS, SHIPPED_MODELS_DIR, load_checkpoint

    figures = {}
    for env in ENVIRONMENT_MODELS:
        path = SHIPPED_MODELS_DIR / f"{env}_bc40.pt"
        if path.exists():
            metrics = load_checkpoint(path).metrics
            figures[f"train_{env}_40_demos_s"] = float(metrics.get("training_seconds", float("nan")))
    return figures


if __name__ == "__main__":
    if len(sys.argv) == 6 and sys.argv[1] == "--memory-worker":
        print(json.dumps(_streaming_memory_worker(int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4]),
                                                  sys.argv[5])))
    else:
        figures = measure_policy_step_ms()
        figures.update(measure_streaming_memory(*[int(a) for a in sys.argv[1:2]]))
        print(json.dumps(figures, indent=1))
