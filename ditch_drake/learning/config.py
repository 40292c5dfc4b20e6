"""The learning settings as plain dataclasses, importable without torch (the command line
shows their defaults in `--help` without loading it)."""

import math
import re
from dataclasses import asdict, dataclass, field, fields
from numbers import Integral, Real

from ditch_drake.common.errors import ConfigError
from ditch_drake.spec.actions import NUM_LABELS
from ditch_drake.spec.observation_layout import (
    BEARING_STACK_SIZE,
    DISTANCE_STACK_SIZE,
    IMAGE_SIZE,
    IMU_STACK_SIZE,
    STACK_DEPTH,
)


@dataclass
class ModelConfig:
    """Everything that fixes the network's shape; stored in every checkpoint.

    Attributes:
        image_channels: stacked images (channel 0 newest).
        image_size: rows = cols of each image.
        imu_size: length of the IMU stack (roll, pitch per step).
        distance_size: length of the distance stack.
        bearing_size: length of the bearing stack.
        num_labels: output classes (the action table's labels).
        conv1_channels: filters of the first convolution (paper: 64).
        conv2_channels: filters of the second convolution (paper: 32).
        kernel_size: convolution kernel (paper: 3).
        padding: convolution padding (project: 1, "same").
        pool_size: max-pooling window and stride (project: 4).
        pool_after_each_conv: pool after both convolutions (project) or only after the
            second.
        dropout: dropout probability of the image and scalar branches (paper: 0.4).
        scalar_hidden: units of each scalar branch (paper: 32).
        fusion_hidden: units of the layer after the concatenation (paper: 64).
        canonical_side: trained with every sample reflected left to right where its crossing
            turns left along the edge (`ditch_drake.pipelines.generalist`,
            `GeneralistConfig.canonical_side`), so the network only ever crosses turned right;
            the policy is told the side (`LearnedPolicy`'s `crossing_side` input) and
            reflects its view and its answer when it is left.
    """

    image_channels: int = STACK_DEPTH
    image_size: int = IMAGE_SIZE
    imu_size: int = IMU_STACK_SIZE
    distance_size: int = DISTANCE_STACK_SIZE
    bearing_size: int = BEARING_STACK_SIZE
    num_labels: int = NUM_LABELS
    conv1_channels: int = 64
    conv2_channels: int = 32
    kernel_size: int = 3
    padding: int = 1
    pool_size: int = 4
    pool_after_each_conv: bool = True
    dropout: float = 0.4
    scalar_hidden: int = 32
    fusion_hidden: int = 64
    canonical_side: bool = False

    def image_feature_size(self) -> int:
        """Length of the flattened image branch output.

        Raises:
            ValueError: a configuration whose maps shrink to nothing.
        """
        side = self.image_size
        for conv in range(2):
            side = side + 2 * self.padding - self.kernel_size + 1
            if self.pool_after_each_conv or conv == 1:
                side //= self.pool_size
        if side < 1:
            raise ValueError(f"{self} leaves no image features (map side {side})")
        return self.conv2_channels * side * side

    def to_dict(self) -> dict:
        """Plain types, for a checkpoint."""
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> "ModelConfig":
        """The config of `to_dict`'s output.

        Raises:
            ValueError: unknown keys.
        """
        known = {f.name for f in fields(cls)}
        unknown = set(values) - known
        if unknown:
            raise ValueError(f"unknown ModelConfig fields {sorted(unknown)}; expected some of {sorted(known)}")
        return cls(**values)


@dataclass
class SmoteConfig:
    """How far, and within what memory, SMOTE balances the training split.

    Attributes:
        target_fraction: each minority class is raised to this fraction of the majority
            class's count; 0 turns SMOTE off, 1 asks for full balance (subject to the cap).
        max_synthetic_fraction: at most this many synthetic samples per real training
            sample (a memory and epoch-time budget).
        k_neighbors: SMOTE's neighbours (imbalanced-learn's default 5), fewer for classes
            with fewer samples.
        chunk_size: new samples per imbalanced-learn call (bounds its temporaries).
        max_base_samples: a class with more training samples than this is interpolated
            from a random subset of this size (bounds imbalanced-learn's copies).
    """

    target_fraction: float = 0.5
    max_synthetic_fraction: float = 1.0
    k_neighbors: int = 5
    chunk_size: int = 512
    max_base_samples: int = 2048

    def __post_init__(self):
        if not 0.0 <= self.target_fraction <= 1.0:
            raise ConfigError(f"SmoteConfig.target_fraction={self.target_fraction} must be in [0, 1]")
        if not self.max_synthetic_fraction >= 0.0:  # NaN too.
            raise ConfigError(f"max_synthetic_fraction={self.max_synthetic_fraction}: expected >= 0 synthetic samples "
                              "per real one (--synthetic-fraction)")
        if self.k_neighbors < 1 or self.chunk_size < 1 or self.max_base_samples < 2:
            raise ConfigError(f"{self}: k_neighbors and chunk_size must be >= 1, max_base_samples >= 2")


PRECISIONS = ("fp32", "bf16")
SHARED_STEPS = ("all", "interventions")
"""Which steps of a shared episode training uses (`TrainConfig.shared_steps`)."""
# The class balancing methods (`TrainConfig.balancing`); `ditch_drake.learning.balance.BALANCING`
# implements them (a test keeps the two in step).
BALANCING_METHODS = ("smote", "oversample", "weighted_sampler", "class_weights", "ordinal_soft_labels", "none")
# The `ditch-drake train` option of each TrainConfig field it sets, named in config errors.
_OPTIONS = {
    "epochs": "--epochs",
    "patience": "--patience",
    "batch_size": "--batch-size",
    "max_batches_per_epoch": "--batches-per-epoch",
    "smote.max_synthetic_fraction": "--synthetic-fraction",
    "num_threads": "--threads",
    "seed": "--seed",
    "device": "--device",
    "precision": "--precision",
    "balancing": "--balancing",
    "num_workers": "--loader-workers",
    "intervention_weight": "--intervention-weight",
    "shared_steps": "--shared-steps",
}
# Torch device strings a training run can use ("cuda:1" picks a GPU).
_DEVICE_PATTERN = re.compile(r"(cpu|cuda|mps|xpu)(:\d+)?")


def _bad_field(name: str, value, expected: str) -> ConfigError:
    """A `ConfigError` "name=value: expected ... (--option)"."""
    option = f" ({_OPTIONS[name]})" if name in _OPTIONS else ""
    return ConfigError(f"{name}={value!r}: expected {expected}{option}")


def _is_integer(value) -> bool:
    return isinstance(value, Integral) and not isinstance(value, bool)


def _is_number(value) -> bool:
    return isinstance(value, Real) and not isinstance(value, bool) and math.isfinite(value)


@dataclass
class TrainConfig:
    """Training settings (paper 3.5, 3.6; values the paper does not give are the project's).

    Attributes:
        epochs: most epochs to run.
        batch_size: samples per optimizer step.
        lr: Adam learning rate of the image branch and the head.
        scalar_lr_factor: the scalar branches' rate relative to `lr` (paper: 1/10).
        patience: epochs without a better validation ordinal accuracy before stopping.
        val_fraction: share of the demonstrations held out for validation (0: none; then
            the last epoch's weights are kept and there is no early stopping).
        seed: seeds the split, SMOTE, initialization, shuffling and dropout.
        smote: SMOTE's targets, budget and memory bounds (`SmoteConfig`); "oversample" reaches
            the same targets by repeating rows.
        balancing: how the training split's classes are balanced, one of `BALANCING_METHODS`
            (`ditch_drake.learning.balance`): "smote" (the paper's: synthetic samples
            interpolated within each minority class, up to `smote`'s targets), "oversample"
            (the default: rows of the minority classes drawn again, to the same targets: no
            copies; chosen by rollout success on the paper's 40-demonstration sets and the
            generalist's data, where it crossed as many as SMOTE in milliseconds instead of
            minutes: docs/results/class_balancing.md),
            "weighted_sampler" (each epoch draws its samples with replacement, a sample's
            chance inverse to its class's count), "class_weights" (cross-entropy weighted
            inverse to the class counts), "ordinal_soft_labels" (cross-entropy against targets
            spread over the neighbouring turn rates, `soft_label_sigma`) or "none".
        soft_label_sigma: with "ordinal_soft_labels", the width (in labels) of the discretized
            Gaussian over the 17 ordered labels that a sample's target is.
        num_workers: processes reading the batches (torch `DataLoader` workers; 0 reads in the
            training process); None: 0 (`loader_workers`: workers start afresh for every
            epoch and validation, which on a GPU cost more than the reads they share out). The
            result does not depend on it.
        max_demos: train on the demonstrations with the `max_demos` smallest ids (None: all).
        ordinal_tolerance: labels of slack of the ordinal accuracy (paper: 1).
        device: torch device ("cpu"; "cuda" works but is not bitwise reproducible).
        precision: "fp32", or "bf16" to run the training steps' forward and backward passes
            under bfloat16 autocast (weights, optimizer and validation stay fp32). On a CPU
            with native bf16 (AVX512-BF16 or AMX) the steps ran 2.4x faster; on one without
            it, 5x slower: `available_precision` picks.
        num_threads: torch intra-op threads during training (None: leave torch's setting).
            Results are reproducible for a given thread count.
        eval_batch_size: samples per forward pass when evaluating.
        max_batches_per_epoch: stop each epoch after this many batches (None: all). Each
            epoch draws its batches from a fresh shuffle of the whole training set, so a
            capped epoch is a random 96 x 64 = 6,144-sample subset; the defaults (8 such
            epochs, SMOTE up to half the real samples) fit one environment's 40
            demonstrations into the 15-minute training budget on 2 CPU cores (docs/concepts/learning.md).
        intervention_weight: the weight of a sample whose step a supervisor took over (the
            dataset's `intervention` flag: the fallback of a shared rollout, a person at
            `teleop --shared`) in the training loss, relative to 1 for every other sample
            (Sirius, Liu et al. RSS 2023, weighs the interventions up). Each batch's loss is
            the weighted mean, sum(w_i l_i) / sum(w_i) (with class weights, w_i times the
            class's weight, as torch's weighted cross-entropy). 1 (the default) is uniform
            aggregation: training is exactly as without the field, and a checkpoint's
            `train_config` does not list it. Validation loss stays unweighted.
        shared_steps: which steps of a shared episode (one the gated policy drove, recorded
            by `collect --shared` or `teleop --shared`) are trained on, one of `SHARED_STEPS`:
            "all" (the policy's own and the supervisor's: Sirius's data) or "interventions"
            (the supervisor's only: HG-DAgger's and ThriftyDAgger's). Other episodes are used
            whole. "all" (the default) is recorded in no checkpoint, as before the field.
        model: the network's shape.
    """

    epochs: int = 8
    batch_size: int = 64
    lr: float = 1e-3
    scalar_lr_factor: float = 0.1
    patience: int = 4
    val_fraction: float = 0.2
    seed: int = 0
    smote: SmoteConfig = field(default_factory=lambda: SmoteConfig(max_synthetic_fraction=0.5))
    balancing: str = "oversample"
    soft_label_sigma: float = 1.0
    num_workers: int | None = None
    max_demos: int | None = None
    ordinal_tolerance: int = 1
    device: str = "cpu"
    precision: str = "fp32"
    num_threads: int | None = None
    eval_batch_size: int = 256
    max_batches_per_epoch: int | None = 96
    model: ModelConfig = field(default_factory=ModelConfig)
    intervention_weight: float = 1.0
    shared_steps: str = "all"

    def __post_init__(self):
        """Checks every field, so a bad setting fails when the config is made, before any data loads.

        Raises:
            ConfigError: the first bad field, as "name=value: expected ... (--option)".
        """
        minimums = {"epochs": 1, "patience": 1, "eval_batch_size": 1, "seed": 0, "ordinal_tolerance": 0}
        for name, minimum in minimums.items():
            value = getattr(self, name)
            if not (_is_integer(value) and value >= minimum):
                raise _bad_field(name, value, f"an integer >= {minimum}")
        if not (_is_integer(self.batch_size) and self.batch_size >= 2):
            raise _bad_field("batch_size", self.batch_size, "an integer >= 2 (BatchNorm needs two samples a batch)")
        none_means = {
            "num_threads": "torch's default (all cores)",
            "num_workers": "0 (read in the training process)",
            "max_batches_per_epoch": "all batches",
            "max_demos": "all demonstrations",
        }
        for name, meaning in none_means.items():
            value = getattr(self, name)
            lowest = 0 if name == "num_workers" else 1
            if value is not None and not (_is_integer(value) and value >= lowest):
                raise _bad_field(name, value, f"an integer >= {lowest}, or None for {meaning}")
        for name in ("lr", "scalar_lr_factor"):
            value = getattr(self, name)
            if not (_is_number(value) and value > 0):
                raise _bad_field(name, value, "a finite number > 0")
        if not (_is_number(self.val_fraction) and 0.0 <= self.val_fraction < 1.0):
            raise _bad_field("val_fraction", self.val_fraction, "a number in [0, 1)")
        if not isinstance(self.smote, SmoteConfig):
            raise _bad_field("smote", self.smote, "a SmoteConfig")
        # SmoteConfig refuses negative fractions itself, but lets NaN and inf through.
        if not (_is_number(self.smote.max_synthetic_fraction) and self.smote.max_synthetic_fraction >= 0):
            raise _bad_field("smote.max_synthetic_fraction", self.smote.max_synthetic_fraction, "a finite number >= 0")
        if self.balancing not in BALANCING_METHODS:
            raise _bad_field("balancing", self.balancing, f"one of {BALANCING_METHODS}")
        if not (_is_number(self.soft_label_sigma) and self.soft_label_sigma > 0):
            raise _bad_field("soft_label_sigma", self.soft_label_sigma, "a finite number > 0 (labels)")
        if self.precision not in PRECISIONS:
            raise _bad_field("precision", self.precision, f"one of {PRECISIONS}")
        if not (isinstance(self.device, str) and _DEVICE_PATTERN.fullmatch(self.device)):
            raise _bad_field("device", self.device, "a torch device: 'cpu', 'cuda' or 'cuda:N'")
        if not isinstance(self.model, ModelConfig):
            raise _bad_field("model", self.model, "a ModelConfig")
        if not (_is_number(self.intervention_weight) and self.intervention_weight > 0):
            raise _bad_field("intervention_weight", self.intervention_weight,
                             "a finite number > 0 (the loss weight of an intervention sample; 1: uniform)")
        if self.shared_steps not in SHARED_STEPS:
            raise _bad_field("shared_steps", self.shared_steps, f"one of {SHARED_STEPS}")

    @classmethod
    def from_options(cls, synthetic_fraction: float | None = None, **fields) -> "TrainConfig":
        """A config from `ditch-drake train`'s options: `fields` as they are, and
        `synthetic_fraction` (--synthetic-fraction) as `smote.max_synthetic_fraction` of
        the default SMOTE settings (None: the default).

        Raises:
            ConfigError: a bad value, named by its option, before anything else is done.
        """
        if synthetic_fraction is not None:
            if not (_is_number(synthetic_fraction) and synthetic_fraction >= 0):
                # Checked before SmoteConfig is built: it lets NaN and inf through.
                raise _bad_field("smote.max_synthetic_fraction", synthetic_fraction, "a finite number >= 0")
            smote = cls.__dataclass_fields__["smote"].default_factory()
            fields["smote"] = SmoteConfig(**{**vars(smote), "max_synthetic_fraction": synthetic_fraction})
        return cls(**fields)
