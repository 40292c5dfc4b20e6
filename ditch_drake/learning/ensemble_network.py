"""K clones of the four-input classifier as one network: every member's logits in one forward pass.

The members' layers are stacked, not looped over: the first convolution reads the shared image
once with all K members' filters side by side (K x 64 output channels), each later convolution
is a grouped one (groups = K: member k's filters see only member k's channels), and each dense
layer is a batched matrix product over the members (`torch.baddbmm`). BatchNorm in eval mode is
the affine map of its running statistics, folded into a scale and a shift per member; dropout
is off in eval mode and left out. Each member standardizes its scalar inputs with its own
statistics.

Why not `torch.func` (`stack_module_state` + `functional_call` + `vmap`): it gives the same
numbers, but its batching rules ran the network about 30 times slower than one member
(batch 1, one thread, on the 2-core host, loaded), where the stacked layers run at about the
cost of looping over the members' convolutions and once the overhead of the small layers.

Precision (`PRECISIONS`): "float32" throughout, the default; or "bfloat16_image", the image
branch (convolutions, pools, ELUs: nearly all of the multiply-adds) in bfloat16 on the
image rounded to bfloat16, its features cast back to float32 for the scalar branches and the
head, which stay float32. It approximates the float32 network (bfloat16 keeps 8 significant
bits): the members' logits move slightly, and a label may change where two logits nearly tie
(`tests/test_ensemble_bfloat16.py` measures how often on a fixed batch). It is offered only on a CPU that runs bfloat16 natively (`native_bfloat16_flags`), where
it is the faster one; elsewhere torch would emulate it. Whole-network bfloat16 or autocast
agreed less with float32 and are not offered.
"""

import copy
import sys
from collections.abc import Sequence
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from ditch_drake.common.errors import ConfigError
from ditch_drake.learning.model import SCALAR_INPUTS, FourInputClassifier

# What `EnsembleNetwork` runs in (the module docstring); the first is the default.
PRECISIONS = ("float32", "bfloat16_image")
DEFAULT_PRECISION = PRECISIONS[0]
# The CPU flags (Linux /proc/cpuinfo) of instructions that compute in bfloat16 natively:
# AVX512-BF16's dot products and AMX's bfloat16 tiles.
NATIVE_BFLOAT16_FLAGS = ("avx512_bf16", "amx_bf16")


def native_bfloat16_flags(cpuinfo: str | Path | None = None) -> tuple[str, ...]:
    """The flags of `NATIVE_BFLOAT16_FLAGS` that the CPU has, read from `cpuinfo` (a file in the
    format of Linux's /proc/cpuinfo; None: that file, or () on another system); () where the
    file does not read (taken as no native bfloat16)."""
    if cpuinfo is None:
        if not sys.platform.startswith("linux"):
            return ()
        cpuinfo = "/proc/cpuinfo"
    try:
        text = Path(cpuinfo).read_text()
    except OSError:
        return ()
    flags = set()
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "flags":
            flags.update(value.split())
    return tuple(flag for flag in NATIVE_BFLOAT16_FLAGS if flag in flags)


def check_precision(precision: str) -> None:
    """That `precision` is one of `PRECISIONS` and runs natively on this CPU.

    Raises:
        ConfigError: an unknown precision, naming the choices; "bfloat16_image" on a CPU
            without `NATIVE_BFLOAT16_FLAGS`, naming what it lacks.
    """
    if precision not in PRECISIONS:
        raise ConfigError(f"ensemble precision={precision!r}: expected one of {list(PRECISIONS)}")
    if precision != DEFAULT_PRECISION and not native_bfloat16_flags():
        raise ConfigError(f"ensemble precision={precision!r} needs a CPU that runs bfloat16 natively; this one has "
                          f"none of the CPU flags {list(NATIVE_BFLOAT16_FLAGS)} (read from /proc/cpuinfo on Linux); "
                          f"expected precision {DEFAULT_PRECISION!r} here")


class _StackedConv2d(nn.Module):
    """K members' `Conv2d` as one: on a shared input (all filters side by side) or grouped."""

    def __init__(self, convs: Sequence[nn.Conv2d], shared_input: bool):
        super().__init__()
        first = convs[0]
        self.register_buffer("weight", torch.cat([conv.weight.detach() for conv in convs]).contiguous(
            memory_format=torch.channels_last))
        self.register_buffer("bias", None if first.bias is None else torch.cat([conv.bias.detach() for conv in convs]))
        self.stride, self.padding, self.dilation = first.stride, first.padding, first.dilation
        self.groups = first.groups if shared_input else first.groups * len(convs)
        if first.padding_mode != "zeros":
            raise ValueError(f"padding_mode {first.padding_mode!r}: the stacked convolution pads with zeros only")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.conv2d(x, self.weight, self.bias, self.stride, self.padding, self.dilation, self.groups)


class _MemberFlatten(nn.Module):
    """(B, K * C, H, W), member-major channels -> (K, B, C * H * W), each member's `nn.Flatten`."""

    def __init__(self, members: int):
        super().__init__()
        self.members = members

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x.reshape(x.shape[0], self.members, -1).transpose(0, 1)


class _StackedLinear(nn.Module):
    """K members' `Linear` on (K, B, in) -> (K, B, out)."""

    def __init__(self, linears: Sequence[nn.Linear]):
        super().__init__()
        self.register_buffer("weight_t", torch.stack([linear.weight.detach().T for linear in linears]).contiguous())
        biases = [torch.zeros(linear.out_features) if linear.bias is None else linear.bias.detach()
                  for linear in linears]
        self.register_buffer("bias", torch.stack(biases).unsqueeze(1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.baddbmm(self.bias, x, self.weight_t)


class _StackedBatchNorm(nn.Module):
    """K members' eval-mode `BatchNorm1d` on (K, B, F): x * scale + shift per member."""

    def __init__(self, norms: Sequence[nn.BatchNorm1d]):
        super().__init__()
        scales, shifts = [], []
        for norm in norms:
            if norm.running_mean is None:
                raise ValueError("a BatchNorm without running statistics has no eval-mode map to fold")
            scale = 1.0 / torch.sqrt(norm.running_var + norm.eps)
            shift = -norm.running_mean * scale
            if norm.affine:
                scale, shift = scale * norm.weight.detach(), shift * norm.weight.detach() + norm.bias.detach()
            scales.append(scale)
            shifts.append(shift)
        self.register_buffer("scale", torch.stack(scales).unsqueeze(1))
        self.register_buffer("shift", torch.stack(shifts).unsqueeze(1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.addcmul(self.shift, x, self.scale)


def _stack_sequential(branches: Sequence[nn.Sequential], image: bool) -> nn.Sequential:
    """The layers of K members' `branches` (same structure) stacked, in order.

    Image branches: (B, C, H, W) shared -> (K, B, F) after the flatten. Dense branches:
    (K, B, in) -> (K, B, out).
    """
    layers, shared = [], image
    for stage in zip(*branches, strict=True):
        first = stage[0]
        if any(type(layer) is not type(first) for layer in stage):
            raise ValueError(f"members differ in layer types {[type(layer).__name__ for layer in stage]}")
        if isinstance(first, nn.Dropout):
            continue  # Off in eval mode.
        if isinstance(first, nn.Conv2d):
            layers.append(_StackedConv2d(stage, shared))
            shared = False
        elif isinstance(first, nn.Flatten):
            layers.append(_MemberFlatten(len(stage)))
        elif isinstance(first, nn.Linear):
            layers.append(_StackedLinear(stage))
        elif isinstance(first, nn.BatchNorm1d):
            layers.append(_StackedBatchNorm(stage))
        elif isinstance(first, (nn.MaxPool2d, nn.ELU)):
            layers.append(copy.deepcopy(first))  # No parameters: the same for every member, and elementwise or per channel.
        else:
            raise TypeError(f"no stacked form of {type(first).__name__}")
    return nn.Sequential(*layers)


class EnsembleNetwork(nn.Module):
    """K `FourInputClassifier`s of one config as one inference network: logits (K, B, labels).

    Built from the members as they are (their eval-mode maps, copied); a change to a member
    afterwards is not seen. Inference only: no dropout, BatchNorm on its running statistics.

    Attributes:
        members: K.
        precision: what it runs in, a name of `PRECISIONS` (the module docstring).
    """

    def __init__(self, models: Sequence[FourInputClassifier], precision: str = DEFAULT_PRECISION):
        """Stacks the members' layers.

        Args:
            models: the members, of one model config.
            precision: a name of `PRECISIONS`; "bfloat16_image" casts the stacked image branch's
                weights to bfloat16.

        Raises:
            ValueError: fewer than two members, or members of different configs or layers.
            TypeError: a layer with no stacked form.
            ConfigError: an unknown precision, or "bfloat16_image" on a CPU without native
                bfloat16 (`check_precision`).
        """
        super().__init__()
        check_precision(precision)
        self.precision = precision
        models = list(models)
        if len(models) < 2:
            raise ValueError(f"{len(models)} member(s); an ensemble network needs at least 2")
        config = models[0].config
        if any(model.config != config for model in models):
            raise ValueError("the members' model configs differ")
        self.config = config
        self.members = len(models)
        self.image_branch = _stack_sequential([model.image_branch for model in models], image=True)
        self._image_dtype = torch.bfloat16 if precision == "bfloat16_image" else torch.float32
        self.image_branch.to(self._image_dtype)
        for name in SCALAR_INPUTS:
            setattr(self, f"{name}_branch", _stack_sequential([getattr(m, f"{name}_branch") for m in models], False))
            for kind in ("mean", "std"):
                stacked = torch.stack([getattr(model, f"{name}_{kind}").detach() for model in models]).unsqueeze(1)
                self.register_buffer(f"{name}_{kind}", stacked)
        self.head = _stack_sequential([model.head for model in models], image=False)
        self.eval()

    def forward(
        self, image: torch.Tensor, imu: torch.Tensor, distance: torch.Tensor, bearing: torch.Tensor
    ) -> torch.Tensor:
        """Logits (K, B, num_labels): member k's row equals `FourInputClassifier.forward` of member k
        (in float32; approximates it in "bfloat16_image").

        Args:
            image, imu, distance, bearing: as `FourInputClassifier.forward` takes them, shared by
                every member.
        """
        image = image.to(self._image_dtype, memory_format=torch.channels_last)
        features = [self.image_branch(image).float()]
        for name, value in zip(SCALAR_INPUTS, (imu, distance, bearing), strict=True):
            standardized = (value.unsqueeze(0) - getattr(self, f"{name}_mean")) / getattr(self, f"{name}_std")
            features.append(getattr(self, f"{name}_branch")(standardized))
        return self.head(torch.cat(features, dim=2))
