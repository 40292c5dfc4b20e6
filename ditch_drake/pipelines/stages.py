"""The stages the training pipelines share (the paper's protocol, the generalist's recipe)."""

from ditch_drake.common.errors import ConfigError


def training_device(requested: str) -> str:
    """The torch device a training run asks for: `auto` (CUDA when torch sees a GPU, else the
    CPU), `cpu` or `cuda`.

    Raises:
        ConfigError: `cuda` asked for where torch sees no CUDA device.
    """
    import torch

    from ditch_drake.learning.train import available_device

    if requested == "auto":
        return available_device()
    if requested == "cuda" and not torch.cuda.is_available():
        raise ConfigError("--device cuda: torch sees no CUDA device; use --device cpu or auto")
    return requested
