"""Image backbones in plain torch: ResNet-18 and VGG-16 with torchvision's parameter names, the
GPS-Gaussian residual U-Net encoder, and loading of local weight files.

torchvision cannot be imported beside the CPU torch (MODELS.md §0), so the two ImageNet backbones
are written here with exactly torchvision's module and parameter names: a torchvision state dict
(``resnet18-*.pth``, ``vgg16-*.pth``) loads into them without renaming through
:func:`load_backbone_weights`. Nothing is downloaded; with no file the backbones keep their random
initialisation and the message says so.

Input normalisation is the caller's job: ImageNet weights expect ``(x - mean) / std`` with
torchvision's ImageNet statistics, monodepth2-style encoders use ``(x - 0.45) / 0.225``.
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Optional, Sequence

import torch
from torch import Tensor, nn

__all__ = [
    "BasicBlock",
    "ResNet18",
    "VGG16",
    "VGG16_LPIPS_SLICES",
    "load_backbone_weights",
    "ResidualBlock",
    "ResidualUNetEncoder",
    "make_norm",
]


# --------------------------------------------------------------------------------------------
# ResNet-18 (He et al. 2016), torchvision's layout
# --------------------------------------------------------------------------------------------
def _conv3x3(in_ch: int, out_ch: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(in_ch, out_ch, kernel_size=3, stride=stride, padding=1, bias=False)


class BasicBlock(nn.Module):
    """torchvision's ResNet BasicBlock: conv3x3-BN-ReLU-conv3x3-BN, plus identity or a 1x1
    conv+BN ``downsample`` shortcut, then ReLU.  [B, in_ch, H, W] -> [B, out_ch, H/stride, W/stride]."""

    def __init__(self, in_ch: int, out_ch: int, stride: int = 1) -> None:
        super().__init__()
        self.conv1 = _conv3x3(in_ch, out_ch, stride)
        self.bn1 = nn.BatchNorm2d(out_ch)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = _conv3x3(out_ch, out_ch)
        self.bn2 = nn.BatchNorm2d(out_ch)
        self.downsample: Optional[nn.Sequential] = None
        if stride != 1 or in_ch != out_ch:
            self.downsample = nn.Sequential(
                nn.Conv2d(in_ch, out_ch, kernel_size=1, stride=stride, bias=False), nn.BatchNorm2d(out_ch)
            )

    def forward(self, x: Tensor) -> Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


class ResNet18(nn.Module):
    """ResNet-18 with torchvision's names: ``conv1, bn1, relu, maxpool, layer1..layer4`` (two
    :class:`BasicBlock` each, 64/128/256/512 channels), ``avgpool`` and ``fc`` only when
    ``num_classes`` is given.

    ``in_channels`` other than 3 widens ``conv1`` (6 for the pose network's two stacked images);
    :func:`load_backbone_weights` adapts a 3-channel ``conv1`` file to it. The input is expected
    already normalised (see the module docstring).

    ``forward_features(x [B, in_channels, H, W])`` returns the five levels of monodepth2's encoder:
    ``[64 @ H/2, 64 @ H/4, 128 @ H/8, 256 @ H/16, 512 @ H/32]`` (level 0 is after ``relu``, before
    ``maxpool``; sizes round up for odd inputs, as the strided convs do).
    ``forward(x)`` returns logits [B, num_classes] with ``fc``, else the feature list.
    """

    num_ch_enc = (64, 64, 128, 256, 512)

    def __init__(self, in_channels: int = 3, num_classes: Optional[int] = None) -> None:
        super().__init__()
        if not isinstance(in_channels, int) or in_channels < 1:
            raise ValueError(f"in_channels: expected a positive int, got {in_channels!r}")
        if num_classes is not None and (not isinstance(num_classes, int) or num_classes < 1):
            raise ValueError(f"num_classes: expected None or a positive int, got {num_classes!r}")
        self.in_channels = in_channels
        self.conv1 = nn.Conv2d(in_channels, 64, kernel_size=7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(kernel_size=3, stride=2, padding=1)
        self.layer1 = nn.Sequential(BasicBlock(64, 64), BasicBlock(64, 64))
        self.layer2 = nn.Sequential(BasicBlock(64, 128, 2), BasicBlock(128, 128))
        self.layer3 = nn.Sequential(BasicBlock(128, 256, 2), BasicBlock(256, 256))
        self.layer4 = nn.Sequential(BasicBlock(256, 512, 2), BasicBlock(512, 512))
        self.fc: Optional[nn.Linear] = None
        if num_classes is not None:
            self.avgpool = nn.AdaptiveAvgPool2d((1, 1))
            self.fc = nn.Linear(512, num_classes)
        # torchvision's initialisation: He (fan_out) for convs, BN as identity.
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def forward_features(self, x: Tensor) -> list[Tensor]:
        if x.dim() != 4 or x.shape[1] != self.in_channels:
            raise ValueError(f"x: expected [B, {self.in_channels}, H, W], got {list(x.shape)}")
        f0 = self.relu(self.bn1(self.conv1(x)))
        f1 = self.layer1(self.maxpool(f0))
        f2 = self.layer2(f1)
        f3 = self.layer3(f2)
        f4 = self.layer4(f3)
        return [f0, f1, f2, f3, f4]

    def forward(self, x: Tensor) -> Tensor | list[Tensor]:
        feats = self.forward_features(x)
        if self.fc is None:
            return feats
        return self.fc(torch.flatten(self.avgpool(feats[-1]), 1))


# --------------------------------------------------------------------------------------------
# VGG-16 (Simonyan & Zisserman 2015, configuration D), torchvision's ``features``
# --------------------------------------------------------------------------------------------
_VGG16_CFG = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M")

#: LPIPS's five taps: (name, start, stop) slices of ``VGG16.features`` ending after that ReLU.
VGG16_LPIPS_SLICES = (
    ("relu1_2", 0, 4),
    ("relu2_2", 4, 9),
    ("relu3_3", 9, 16),
    ("relu4_3", 16, 23),
    ("relu5_3", 23, 30),
)


class VGG16(nn.Module):
    """The convolutional part of torchvision's ``vgg16()``: ``features.0 .. features.30`` (13 3x3
    convs with bias, ReLU, 5 max-pools). There is no classifier; a full torchvision ``vgg16`` state
    dict still loads (its ``classifier.*`` entries are ignored by :func:`load_backbone_weights`).

    ``forward(x [B, 3, H, W])`` -> [B, 512, H/32, W/32].
    ``lpips_features(x)`` -> the five LPIPS taps ``relu1_2 .. relu5_3``:
    [64 @ H, 128 @ H/2, 256 @ H/4, 512 @ H/8, 512 @ H/16].
    """

    def __init__(self) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        in_ch = 3
        for v in _VGG16_CFG:
            if v == "M":
                layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
            else:
                layers += [nn.Conv2d(in_ch, int(v), kernel_size=3, padding=1), nn.ReLU(inplace=True)]
                in_ch = int(v)
        self.features = nn.Sequential(*layers)
        # torchvision's initialisation of the convolutions.
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
                nn.init.zeros_(m.bias)

    @staticmethod
    def _check(x: Tensor) -> None:
        if not isinstance(x, Tensor) or x.dim() != 4 or x.shape[1] != 3:
            raise ValueError(f"x: expected [B, 3, H, W], got {list(getattr(x, 'shape', []))}")

    def forward(self, x: Tensor) -> Tensor:
        self._check(x)
        return self.features(x)

    def lpips_features(self, x: Tensor) -> list[Tensor]:
        self._check(x)
        out = []
        for _, start, stop in VGG16_LPIPS_SLICES:
            for i in range(start, stop):
                layer = self.features[i]
                # Non-inplace ReLU: the tapped tensors must survive the next layer.
                x = torch.relu(x) if isinstance(layer, nn.ReLU) else layer(x)
            out.append(x)
        return out


# --------------------------------------------------------------------------------------------
# Local weight files
# --------------------------------------------------------------------------------------------
#: Head parameters a backbone file may carry that a headless module ignores.
_OPTIONAL_HEADS = ("fc.", "classifier.")


def _list(keys: Sequence[str], n: int = 5) -> str:
    keys = sorted(keys)
    more = f", ... ({len(keys)} in all)" if len(keys) > n else ""
    return ", ".join(keys[:n]) + more


def load_backbone_weights(module: nn.Module, path: Optional[str | os.PathLike], in_channels: Optional[int] = None) -> str:
    """Load a local torchvision-format state dict into ``module`` (a :class:`ResNet18`,
    :class:`VGG16` or any module with the file's names) and return a one-line message saying what
    was done, to be printed by the run.

    - ``path=None``: nothing is loaded; the message says the initialisation is random.
    - Keys must match ``module.state_dict()`` exactly, except head entries (``fc.*``,
      ``classifier.*``) when the module has no head, and BatchNorm ``num_batches_tracked`` that
      old files lack.
    - ``in_channels`` (default: the module's own ``conv1`` input width, or 3): a ``conv1.weight``
      of shape [64, 3, 7, 7] in the file is repeated ``in_channels / 3`` times along its input
      channels and divided by that factor (monodepth2's multi-image encoder: 6 channels =
      two stacked images, duplicated and halved), so a stack of identical images gives the
      ImageNet response.

    The file is read with ``torch.load(weights_only=True)``. Raises ``ValueError`` naming the file
    when it is missing, not a state dict, has missing/unexpected keys or a shape mismatch.
    """
    name = type(module).__name__
    if path is None:
        return f"{name}: random initialisation (no weights file given)"
    path = os.fspath(path)
    own = module.state_dict()
    conv1 = getattr(module, "conv1", None)
    own_in = conv1.in_channels if isinstance(conv1, nn.Conv2d) else 3
    if in_channels is None:
        in_channels = own_in
    if in_channels != own_in:
        raise ValueError(f"in_channels: {in_channels} requested but {name}'s first conv takes {own_in} channels")
    if not os.path.isfile(path):
        raise ValueError(f"{name} weights: file {path!r} does not exist")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # pickle errors, truncated files, non-tensor objects
        raise ValueError(f"{name} weights: cannot read {path!r} as a torch state dict ({exc})") from exc
    if not isinstance(state, Mapping) or not all(isinstance(v, Tensor) for v in state.values()):
        raise ValueError(
            f"{name} weights: {path!r} is not a state dict (a mapping of names to tensors), got {type(state).__name__}"
        )
    state = dict(state)
    heads = tuple(h for h in _OPTIONAL_HEADS if not any(k.startswith(h) for k in own))
    ignored = [k for k in state if k.startswith(heads)] if heads else []
    unexpected = [k for k in state if k not in own and k not in ignored]
    missing = [k for k in own if k not in state and not k.endswith("num_batches_tracked")]
    if missing or unexpected:
        parts = []
        if missing:
            parts.append(f"missing keys: {_list(missing)}")
        if unexpected:
            parts.append(f"unexpected keys: {_list(unexpected)}")
        raise ValueError(f"{name} weights: {path!r} does not match {name} ({'; '.join(parts)})")
    note = ""
    w = state.get("conv1.weight")
    if w is not None and w.dim() == 4 and w.shape[1] != in_channels:
        if w.shape[1] != 3 or in_channels % 3 != 0:
            raise ValueError(
                f"{name} weights: {path!r} has conv1.weight with {w.shape[1]} input channels, "
                f"cannot adapt it to in_channels={in_channels} (needs a multiple of 3)"
            )
        n = in_channels // 3
        state["conv1.weight"] = torch.cat([w] * n, dim=1) / n
        note = f" (conv1 repeated {n}x for {in_channels} input channels and divided by {n})"
    for k, v in state.items():
        if k in own and own[k].shape != v.shape:
            raise ValueError(
                f"{name} weights: {path!r} has {k} of shape {list(v.shape)}, {name} expects {list(own[k].shape)}"
            )
    module.load_state_dict({k: v for k, v in state.items() if k in own}, strict=False)  # keys checked above
    if ignored:
        note += f" (head not used: {_list(ignored, 2)})"
    return f"{name}: loaded weights from {path}{note}"


# --------------------------------------------------------------------------------------------
# GPS-Gaussian residual U-Net encoder (RAFT-style residual blocks)
# --------------------------------------------------------------------------------------------
def _groups(channels: int, groups: Optional[int] = None) -> int:
    """GroupNorm group count: ``groups`` if given, else ``channels // 8`` (8 channels per group,
    RAFT's rule), lowered until it divides ``channels``."""
    g = max(1, min(channels, groups if groups is not None else channels // 8))
    while channels % g:
        g -= 1
    return g


def make_norm(norm: Optional[str], channels: int, groups: Optional[int] = None) -> nn.Module:
    """``"group"`` (GroupNorm; ``groups`` groups, default 8 channels per group), ``"batch"``,
    ``"instance"`` (no affine) or ``None`` (identity)."""
    if norm == "group":
        return nn.GroupNorm(_groups(channels, groups), channels)
    if norm == "batch":
        return nn.BatchNorm2d(channels)
    if norm == "instance":
        return nn.InstanceNorm2d(channels)
    if norm is None:
        return nn.Identity()
    raise ValueError(f"norm: expected 'group', 'batch', 'instance' or None, got {norm!r}")


def _norm_params(norm: Optional[str], channels: int) -> int:
    return 2 * channels if norm in ("group", "batch") else 0


class ResidualBlock(nn.Module):
    """Residual block of GPS-Gaussian's encoder: ``relu(norm1(conv1(x)))``, ``relu(norm2(conv2(.)))``
    (3x3 convs with bias, the first with ``stride``), added to the input — through a 1x1 conv
    (``stride``) + norm ``downsample`` when the shape changes — then ReLU.

    [B, in_ch, H, W] -> [B, out_ch, ceil(H/stride), ceil(W/stride)].
    Parameters: ``9*in*out + out + 9*out*out + out + 2*n(out)`` plus ``in*out + out + n(out)`` with
    the shortcut, where ``n(c) = 2c`` for group/batch norm and 0 for instance/None.
    """

    def __init__(self, in_ch: int, out_ch: int, stride: int = 1, norm: Optional[str] = "group") -> None:
        super().__init__()
        if stride not in (1, 2):
            raise ValueError(f"stride: expected 1 or 2, got {stride!r}")
        self.conv1 = nn.Conv2d(in_ch, out_ch, kernel_size=3, stride=stride, padding=1)
        self.norm1 = make_norm(norm, out_ch)
        self.conv2 = nn.Conv2d(out_ch, out_ch, kernel_size=3, padding=1)
        self.norm2 = make_norm(norm, out_ch)
        self.relu = nn.ReLU(inplace=True)
        self.downsample: Optional[nn.Sequential] = None
        if stride != 1 or in_ch != out_ch:
            self.downsample = nn.Sequential(
                nn.Conv2d(in_ch, out_ch, kernel_size=1, stride=stride), make_norm(norm, out_ch)
            )

    @staticmethod
    def num_params(in_ch: int, out_ch: int, stride: int = 1, norm: Optional[str] = "group") -> int:
        """The parameter count from the formula in the class docstring."""
        n = 9 * in_ch * out_ch + out_ch + 9 * out_ch * out_ch + out_ch + 2 * _norm_params(norm, out_ch)
        if stride != 1 or in_ch != out_ch:
            n += in_ch * out_ch + out_ch + _norm_params(norm, out_ch)
        return n

    def forward(self, x: Tensor) -> Tensor:
        y = self.relu(self.norm1(self.conv1(x)))
        y = self.relu(self.norm2(self.conv2(y)))
        if self.downsample is not None:
            x = self.downsample(x)
        return self.relu(x + y)


class ResidualUNetEncoder(nn.Module):
    """The encoder half of GPS-Gaussian's residual U-Net (DrivingForward's depth encoder, PGT's
    image encoder): a 5x5 stride-2 stem conv to ``channels[0]`` + norm (8 groups) + ReLU, then three stages
    of two :class:`ResidualBlock` each (the first of stages 2 and 3 with stride 2).

    ``forward(x [B, in_ch, H, W])`` -> ``[c0 @ H/2, c1 @ H/4, c2 @ H/8]`` (sizes round up).

    Parameter count, with ``c = channels`` and ``R(i, o, s)`` = :meth:`ResidualBlock.num_params`:
    ``25*in_ch*c0 + c0 + n(c0)  +  R(c0,c0,1) + R(c0,c0,1)  +  R(c0,c1,2) + R(c1,c1,1)
    +  R(c1,c2,2) + R(c2,c2,1)`` (:meth:`num_params`); for ``in_ch=1, channels=(32, 48, 96)`` and
    GroupNorm (DrivingForward's depth encoder) that is 412,784.
    """

    def __init__(self, in_ch: int, channels: Sequence[int] = (32, 48, 96), norm: Optional[str] = "group") -> None:
        super().__init__()
        channels = tuple(int(c) for c in channels)
        if len(channels) != 3 or min(channels) < 1:
            raise ValueError(f"channels: expected three positive ints, got {channels!r}")
        if not isinstance(in_ch, int) or in_ch < 1:
            raise ValueError(f"in_ch: expected a positive int, got {in_ch!r}")
        c0, c1, c2 = channels
        self.in_ch, self.channels, self.norm = in_ch, channels, norm
        self.stem = nn.Sequential(
            nn.Conv2d(in_ch, c0, kernel_size=5, stride=2, padding=2), make_norm(norm, c0, groups=8), nn.ReLU(inplace=True)
        )
        self.stage1 = nn.Sequential(ResidualBlock(c0, c0, 1, norm), ResidualBlock(c0, c0, 1, norm))
        self.stage2 = nn.Sequential(ResidualBlock(c0, c1, 2, norm), ResidualBlock(c1, c1, 1, norm))
        self.stage3 = nn.Sequential(ResidualBlock(c1, c2, 2, norm), ResidualBlock(c2, c2, 1, norm))

    @staticmethod
    def num_params(in_ch: int, channels: Sequence[int] = (32, 48, 96), norm: Optional[str] = "group") -> int:
        """The parameter count from the formula in the class docstring."""
        c0, c1, c2 = channels
        R = ResidualBlock.num_params
        return (
            25 * in_ch * c0 + c0 + _norm_params(norm, c0)
            + R(c0, c0, 1, norm) + R(c0, c0, 1, norm)
            + R(c0, c1, 2, norm) + R(c1, c1, 1, norm)
            + R(c1, c2, 2, norm) + R(c2, c2, 1, norm)
        )

    def forward(self, x: Tensor) -> list[Tensor]:
        if x.dim() != 4 or x.shape[1] != self.in_ch:
            raise ValueError(f"x: expected [B, {self.in_ch}, H, W], got {list(x.shape)}")
        f1 = self.stage1(self.stem(x))
        f2 = self.stage2(f1)
        f3 = self.stage3(f2)
        return [f1, f2, f3]
