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
"""

import copy
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from ditch_drake.learning.model import SCALAR_INPUTS, FourInputClassifier


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
    """

    def __init__(self, models: Sequence[FourInputClassifier]):
        """Stacks the members' layers.

        Raises:
            ValueError: fewer than two members, or members of different configs or layers.
            TypeError: a layer with no stacked form.
        """
        super().__init__()
        models = list(models)
        if len(models) < 2:
            raise ValueError(f"{len(models)} member(s); an ensemble network needs at least 2")
        config = models[0].config
        if any(model.config != config for model in models):
            raise ValueError("the members' model configs differ")
        self.config = config
        self.members = len(models)
        self.image_branch = _stack_sequential([model.image_branch for model in models], image=True)
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
        """Logits (K, B, num_labels): member k's row equals `FourInputClassifier.forward` of member k.

        Args:
            image, imu, distance, bearing: as `FourInputClassifier.forward` takes them, shared by
                every member.
        """
        features = [self.image_branch(image.contiguous(memory_format=torch.channels_last))]
        for name, value in zip(SCALAR_INPUTS, (imu, distance, bearing), strict=True):
            standardized = (value.unsqueeze(0) - getattr(self, f"{name}_mean")) / getattr(self, f"{name}_std")
            features.append(getattr(self, f"{name}_branch")(standardized))
        return self.head(torch.cat(features, dim=2))
