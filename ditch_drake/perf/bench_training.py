"""Memory of the training pipeline and time of one learned-policy step.

Run: `python -m ditch_drake.perf.bench_training.py [samples]`. Prints
{"policy_step_ms": ..., "train_peak_rss_mib": ..., ...} (keys end with their unit).

- `measure_policy_step_ms`: median wall time of one `LearnedPolicy` update (read the four
  stacked inputs, one forward pass, softmax, write the state) on one CPU thread, with
  random weights (the time does not depend on them).
- `measure_training_memory_mib`: peak resident memory of a fresh process that builds a
  synthetic set the size of one environment's 40 demonstrations (16 k samples, uint8
  images, label 8 dominant) and runs the whole `train` pipeline on it: split, input
  statistics, SMOTE with the default `SmoteConfig`, and a few training batches plus a
  full validation pass (the memory of an epoch does not grow with its length).
"""

import json
import os
import resource
import subprocess
import sys
import time

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


def synthetic_arrays(samples: int, demos: int = DEMOS, seed: int = 0):
    """A random `ArraySet` with a driving-like label distribution.

    Label 8 takes 55 % of the samples; the rest fall off as exp(-|l - 8| / 3) around it.
    Samples are split evenly over `demos` consecutive demonstrations.
    """
    from ditch_drake.learning.data import ArraySet

    rng = np.random.default_rng(seed)
    weights = np.exp(-np.abs(np.arange(NUM_LABELS) - STRAIGHT_LABEL) / 3.0)
    weights[STRAIGHT_LABEL] = 0.0
    weights = 0.45 * weights / weights.sum()
    weights[STRAIGHT_LABEL] = 0.55
    image = np.empty((samples, *IMAGE_STACK_SHAPE), dtype=np.uint8)
    for start in range(0, samples, 1024):  # Bounded temporaries.
        chunk = image[start : start + 1024]
        chunk[:] = rng.integers(0, 256, chunk.shape, dtype=np.uint8)
    return ArraySet(
        image=image,
        imu=rng.normal(0.0, 0.2, (samples, IMU_STACK_SIZE)).astype(np.float32),
        distance=rng.uniform(0.0, 20.0, (samples, DISTANCE_STACK_SIZE)).astype(np.float32),
        bearing=rng.uniform(-np.pi, np.pi, (samples, BEARING_STACK_SIZE)).astype(np.float32),
        label=rng.choice(NUM_LABELS, samples, p=weights),
        demo_id=np.arange(samples) * demos // samples,
    )


def _training_memory_worker(samples: int) -> dict:
    """Runs in a fresh process: the pipeline on `samples` synthetic samples."""
    from ditch_drake.learning.train import TrainConfig, train

    arrays = synthetic_arrays(samples)
    data_mib = sum(getattr(arrays, name).nbytes for name in arrays.__dataclass_fields__) / 2**20
    start = time.perf_counter()
    result = train(arrays, TrainConfig(epochs=1, max_batches_per_epoch=4, num_threads=1), progress=False)
    return {
        "train_peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "train_data_mib": data_mib,
        "train_pipeline_s": time.perf_counter() - start,
        "train_synthetic_samples": int(result.checkpoint.training["num_synthetic_samples"]),
        "train_real_samples": int(result.checkpoint.training["num_train_samples"]),
    }


def measure_training_memory_mib(samples: int = TRAINING_SAMPLES) -> dict:
    """Peak RSS (MiB) of the training pipeline on a synthetic set, in a fresh process.

    Returns:
        {"train_peak_rss_mib", "train_data_mib" (the input set), "train_pipeline_s",
        "train_synthetic_samples", "train_real_samples"}.
    """
    completed = subprocess.run(
        [sys.executable, "-m", "ditch_drake.perf.bench_training", "--memory-worker", str(samples)],
        check=True,
        capture_output=True,
        text=True,
    )
    return json.loads(completed.stdout.strip().splitlines()[-1])


def measure_policy_step_ms(repeats: int = 50) -> dict:
    """Median time (ms) of one `LearnedPolicy` discrete update on one thread.

    Returns:
        {"policy_step_ms": median, "policy_step_max_ms": slowest}.
    """
    from pydrake.systems.analysis import Simulator  # noqa: F401 (loads Drake's analysis module)

    from ditch_drake.learning.checkpoint import make_checkpoint
    from ditch_drake.learning.model import FourInputClassifier
    from ditch_drake.systems.policy import LearnedPolicy

    policy = LearnedPolicy(make_checkpoint(FourInputClassifier()), num_threads=1)
    context = policy.CreateDefaultContext()
    rng = np.random.default_rng(0)
    policy.GetInputPort("image_stack").FixValue(context, rng.random(int(np.prod(IMAGE_STACK_SHAPE))))
    policy.GetInputPort("imu_stack").FixValue(context, rng.normal(0.0, 0.2, IMU_STACK_SIZE))
    policy.GetInputPort("distance_stack").FixValue(context, rng.uniform(0.0, 20.0, DISTANCE_STACK_SIZE))
    policy.GetInputPort("bearing_stack").FixValue(context, rng.uniform(-3.0, 3.0, BEARING_STACK_SIZE))
    state = policy.AllocateDiscreteVariables()
    times = []
    for _ in range(repeats + 3):
        start = time.perf_counter()
        policy.CalcForcedDiscreteVariableUpdate(context, state)
        times.append(time.perf_counter() - start)
    times = times[3:]  # Warm-up: oneDNN picks its kernels on the first calls.
    return {"policy_step_ms": 1e3 * float(np.median(times)), "policy_step_max_ms": 1e3 * float(np.max(times))}


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
    if len(sys.argv) == 3 and sys.argv[1] == "--memory-worker":
        print(json.dumps(_training_memory_worker(int(sys.argv[2]))))
    else:
        figures = measure_policy_step_ms()
        figures.update(measure_training_memory_mib(*[int(a) for a in sys.argv[1:2]]))
        print(json.dumps(figures, indent=1))
