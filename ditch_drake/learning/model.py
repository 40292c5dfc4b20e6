"""The paper's four-input behavioural-cloning classifier (paper 3.4; docs/design.md, "The network and training").

Layers, as we read the paper (docs/design.md, "Reading the paper"):

- image (4 x 128 x 128, values in [0, 1]): Conv2d 4 -> 64 (3 x 3, ELU), Conv2d 64 -> 32
  (3 x 3, ELU), max pooling, dropout 0.4, flatten;
- IMU (8), distance (4), bearing (4): each its own Linear 32 + ELU + BatchNorm1d + dropout 0.4;
- concatenation -> Linear 64 + ELU + BatchNorm1d -> Linear 17: logits (softmax at inference,
  cross-entropy in training; the softmax is not a layer, `nn.CrossEntropyLoss` takes logits).

Choices where the paper is silent (all in `ModelConfig`):

- Padding 1 ("same"), so the maps are 128, 32 and 8 wide.
- Max pooling 4 x 4 after *each* convolution ("each of the resulting feature maps are passed
  through a max pooling operation"). The first convolution must run at full resolution
  (4 -> 64 channels on 128 x 128: 38 M multiply-adds); pooling right after it makes the
  second convolution run on 32 x 32 (19 M) instead of 128 x 128 (302 M), and the flattened
  image feature is 32 x 8 x 8 = 2,048 values, so the fusion layer has 137 k weights instead of
  the 2.1 M (2 x 2 pools) or 31 M (one 2 x 2 pool at the end) of the alternatives. The whole
  network has 160,145 parameters (see `parameter_count`); one forward pass of a single
  sample takes a few ms on one CPU core (`ditch_drake/perf/bench_training.py`).
- Each pooling comes before its ELU rather than after: ELU is increasing, so
  pool(ELU(x)) = ELU(pool(x)) exactly, and the ELU then touches 16 x fewer values.
- The convolutions run in channels-last memory layout (oneDNN's fast path on CPU); the
  numbers are the same as in the default layout.
- The scalar inputs are standardized inside the network (`set_input_stats`, mean and std
  from the training split), so every caller feeds raw values: radians and metres as the
  FrameStacker outputs them. The image is used as it is ([0, 1]).
"""


import torch
from torch import nn

from ditch_drake.learning.config import ModelConfig

SCALAR_INPUTS = ("imu", "distance", "bearing")


def _scalar_branch(size: int, config: ModelConfig) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(size, config.scalar_hidden),
        nn.ELU(),
        nn.BatchNorm1d(config.scalar_hidden),
        nn.Dropout(config.dropout),
    )


class FourInputClassifier(nn.Module):
    """The paper's classifier: image, IMU, distance and bearing stacks -> 17 logits.

    Attributes:
        config: the shape.
        image_branch, imu_branch, distance_branch, bearing_branch: the four input branches.
        head: the fusion layer and the output layer.
    """

    def __init__(self, config: ModelConfig | None = None):
        """Builds the layers (PyTorch's default initialization) with identity input stats."""
        super().__init__()
        self.config = config = config or ModelConfig()
        # ELU is increasing, so max-pooling before it equals pooling after it (values and
        # gradients) at 1/pool_size**2 of the ELU work.
        image_layers: list[nn.Module] = [
            nn.Conv2d(config.image_channels, config.conv1_channels, config.kernel_size, padding=config.padding),
        ]
        if config.pool_after_each_conv:
            image_layers.append(nn.MaxPool2d(config.pool_size))
        image_layers += [
            nn.ELU(),
            nn.Conv2d(config.conv1_channels, config.conv2_channels, config.kernel_size, padding=config.padding),
            nn.MaxPool2d(config.pool_size),
            nn.ELU(),
            nn.Dropout(config.dropout),
            nn.Flatten(),
        ]
        self.image_branch = nn.Sequential(*image_layers)
        self.imu_branch = _scalar_branch(config.imu_size, config)
        self.distance_branch = _scalar_branch(config.distance_size, config)
        self.bearing_branch = _scalar_branch(config.bearing_size, config)
        fused = config.image_feature_size() + 3 * config.scalar_hidden
        self.head = nn.Sequential(
            nn.Linear(fused, config.fusion_hidden),
            nn.ELU(),
            nn.BatchNorm1d(config.fusion_hidden),
            nn.Linear(config.fusion_hidden, config.num_labels),
        )
        # Standardization of the scalar inputs; not in the state dict: the checkpoint keeps
        # them as plain lists (`input_stats`) and `set_input_stats` puts them here.
        for name in SCALAR_INPUTS:
            size = getattr(config, f"{name}_size")
            self.register_buffer(f"{name}_mean", torch.zeros(size), persistent=False)
            self.register_buffer(f"{name}_std", torch.ones(size), persistent=False)
        # oneDNN's convolutions run several times faster on channels-last (NHWC) tensors.
        self.to(memory_format=torch.channels_last)

    def set_input_stats(self, stats: dict) -> None:
        """Sets the standardization of the scalar inputs.

        Args:
            stats: {"imu_mean": [...], "imu_std": [...], "distance_mean": ..., ...}, the
                output of `ditch_drake.learning.data.InputStats.to_dict`.

        Raises:
            ValueError: a missing key, a wrong length, or a std that is not positive.
        """
        for name in SCALAR_INPUTS:
            for kind in ("mean", "std"):
                key = f"{name}_{kind}"
                if key not in stats:
                    raise ValueError(f"input stats lack {key!r}")
                value = torch.as_tensor(stats[key], dtype=torch.float32)
                buffer = getattr(self, key)
                if value.shape != buffer.shape:
                    raise ValueError(
                        f"input stats {key!r} has shape {tuple(value.shape)}, expected {tuple(buffer.shape)}"
                    )
                if kind == "std" and not bool(torch.all(value > 0)):
                    raise ValueError(f"input stats {key!r} must be positive, got {value.tolist()}")
                buffer.copy_(value)

    def forward(
        self, image: torch.Tensor, imu: torch.Tensor, distance: torch.Tensor, bearing: torch.Tensor
    ) -> torch.Tensor:
        """Logits (B, num_labels).

        Args:
            image: (B, channels, rows, cols) float, values in [0, 1], channel 0 newest.
            imu: (B, imu_size) raw radians.
            distance: (B, distance_size) raw metres.
            bearing: (B, bearing_size) raw radians.
        """
        features = [self.image_branch(image.contiguous(memory_format=torch.channels_last))]
        for name, value in zip(SCALAR_INPUTS, (imu, distance, bearing)):
            standardized = (value - getattr(self, f"{name}_mean")) / getattr(self, f"{name}_std")
            features.append(getattr(self, f"{name}_branch")(standardized))
        return self.head(torch.cat(features, dim=1))


def set_torch_threads(num_threads: int | None) -> None:
    """Sets torch's intra-op threads for the whole process (`torch.set_num_threads` is
    process-wide) before a network runs; None leaves torch's setting.

    Raises:
        ValueError: a thread count < 1.
    """
    if num_threads is not None:
        if num_threads < 1:
            raise ValueError(f"num_threads={num_threads} must be >= 1 or None")
        torch.set_num_threads(num_threads)


def parameter_count(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def parameter_groups(model: FourInputClassifier, lr: float, scalar_lr_factor: float = 0.1) -> list[dict]:
    """Optimizer parameter groups with layer-specific learning rates (paper 3.6).

    The image branch and the fusion head (the concatenation layer and the output layer)
    learn at `lr`; the three scalar branches (IMU, distance, bearing: their Linear and
    BatchNorm parameters) at `lr * scalar_lr_factor`. The paper slows only "the dense layers
    processing the lower dimensional inputs"; the head sees the image features too, so it
    keeps the image rate.

    Args:
        model: the classifier.
        lr: the image branch's learning rate.
        scalar_lr_factor: the scalar branches' rate relative to `lr` (paper: 1/10).

    Returns:
        Two groups, [{"name": "image_and_head", "params": [...], "lr": lr},
        {"name": "scalar_branches", "params": [...], "lr": lr * scalar_lr_factor}], for any
        `torch.optim` optimizer.

    Raises:
        ValueError: a non-positive `lr` or `scalar_lr_factor`.
    """
    if not (lr > 0 and scalar_lr_factor > 0):
        raise ValueError(f"lr={lr} and scalar_lr_factor={scalar_lr_factor} must be positive")
    scalar = [p for name in SCALAR_INPUTS for p in getattr(model, f"{name}_branch").parameters()]
    fast = list(model.image_branch.parameters()) + list(model.head.parameters())
    return [
        {"name": "image_and_head", "params": fast, "lr": lr},
        {"name": "scalar_branches", "params": scalar, "lr": lr * scalar_lr_factor},
    ]
