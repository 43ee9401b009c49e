"""Networks shared by the trainers: MLPs and image encoders ending in a spatial soft-argmax.

Image encoders take float images `(B, C, H, W)` and return flattened keypoints `(B, 2 * K)`, each
keypoint an expected (x, y) image position in [-1, 1] (Levine et al., 2016). Two trunks:

* `KeypointCNN`: the small CNN of the multiview chapter (thesis 3.6.3, after Zhang et al. 2018):
  a 7x7/2 conv with 64 filters (the layer that can take ResNet-18 `conv1` weights), then 1x1 and two
  3x3 convs with K filters, one keypoint per final filter.
* `ResNet18Keypoints`: a ResNet-18 trunk (torchvision's architecture, random init or a local weights
  file; nothing is downloaded) whose last feature map goes through a 1x1 conv to K channels and the
  spatial soft-argmax (the tactile chapter, thesis 4.4.2).
"""

from __future__ import annotations

from pathlib import Path
from typing import override

import torch
from torch import nn

from shiftkit.datasets.errors import ConfigError


def mlp(
    in_dim: int,
    out_dim: int,
    hidden: tuple[int, ...] = (256, 256),
    act: type[nn.Module] = nn.ReLU,
) -> nn.Sequential:
    """Fully connected layers `in_dim -> hidden... -> out_dim` with `act` between them (none at the end)."""
    layers: list[nn.Module] = []
    dims = (in_dim, *hidden)
    for a, b in zip(dims[:-1], dims[1:], strict=True):
        layers += [nn.Linear(a, b), act()]
    layers.append(nn.Linear(dims[-1], out_dim))
    return nn.Sequential(*layers)


class SpatialSoftArgmax(nn.Module):
    """Feature map `(B, K, H, W)` -> keypoints `(B, K, 2)`: the softmax-weighted mean (x, y) position per
    channel, coordinates in [-1, 1] (x along width, y along height), with a learned temperature."""

    def __init__(self, height: int, width: int) -> None:
        super().__init__()
        ys, xs = torch.meshgrid(torch.linspace(-1.0, 1.0, height), torch.linspace(-1.0, 1.0, width), indexing="ij")
        self.register_buffer("grid", torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=-1), persistent=False)
        self.log_temperature = nn.Parameter(torch.zeros(()))

    @override
    def forward(self, features: torch.Tensor) -> torch.Tensor:
        b, k, h, w = features.shape
        weights = torch.softmax(features.reshape(b, k, h * w) / self.log_temperature.exp(), dim=-1)
        return weights @ self.grid


def _load_state_dict(path: str | Path) -> dict[str, torch.Tensor]:
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"pretrained weights file not found: {path}")
    state = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(state, dict):
        raise ConfigError(f"pretrained weights file {path} does not hold a state dict")
    return state.get("state_dict", state)


def _adapt_conv1(weight: torch.Tensor, in_channels: int) -> torch.Tensor:
    """ResNet `conv1` weights (64, 3, 7, 7) for `in_channels` inputs: RGB as is; extra channels
    (e.g. depth) get the mean over the RGB filters."""
    if in_channels <= weight.shape[1]:
        return weight[:, :in_channels].clone()
    extra = weight.mean(dim=1, keepdim=True).expand(-1, in_channels - weight.shape[1], -1, -1)
    return torch.cat([weight, extra], dim=1)


class KeypointCNN(nn.Module):
    """Small CNN + spatial soft-argmax for low-resolution images (64x48 in the thesis)."""

    def __init__(
        self, in_channels: int, height: int, width: int, num_keypoints: int = 32, weights: str | Path | None = None
    ) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, 64, kernel_size=7, stride=2, padding=3)
        self.convs = nn.Sequential(
            nn.ReLU(),
            nn.Conv2d(64, num_keypoints, kernel_size=1),
            nn.ReLU(),
            nn.Conv2d(num_keypoints, num_keypoints, kernel_size=3, padding=1),
            nn.ReLU(),
            nn.Conv2d(num_keypoints, num_keypoints, kernel_size=3, padding=1),
        )
        # layers holding pretrained weights, left out of the ensemble's random init
        self.pretrained_layers: nn.Module | None = self.conv1 if weights is not None else None
        if weights is not None:
            state = _load_state_dict(weights)
            if "conv1.weight" not in state:
                raise ConfigError(f"pretrained weights file {weights} has no ResNet 'conv1.weight'")
            with torch.no_grad():
                self.conv1.weight.copy_(_adapt_conv1(state["conv1.weight"], in_channels))
                self.conv1.bias.zero_()
        self.ssam = SpatialSoftArgmax((height + 1) // 2, (width + 1) // 2)
        self.out_dim = 2 * num_keypoints

    def keypoints(self, images: torch.Tensor) -> torch.Tensor:
        """`(B, C, H, W)` -> `(B, K, 2)` keypoints in [-1, 1]."""
        return self.ssam(self.convs(self.conv1(images)))

    @override
    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.keypoints(images).flatten(1)


class ResNet18Keypoints(nn.Module):
    """ResNet-18 trunk (stride 32 at layer4, or 16 with `drop_layer4`) + 1x1 conv + spatial soft-argmax."""

    def __init__(
        self,
        in_channels: int,
        height: int,
        width: int,
        num_keypoints: int = 32,
        weights: str | Path | None = None,
    ) -> None:
        super().__init__()
        from torchvision.models import resnet18

        net = resnet18(weights=None)
        if weights is not None:
            state = _load_state_dict(weights)
            state = {k: v for k, v in state.items() if not k.startswith("fc.")}
            if "conv1.weight" in state:
                state["conv1.weight"] = _adapt_conv1(state["conv1.weight"], in_channels)
            net.conv1 = nn.Conv2d(in_channels, 64, kernel_size=7, stride=2, padding=3, bias=False)
            missing, unexpected = net.load_state_dict(state, strict=False)
            missing = [k for k in missing if not k.startswith("fc.")]
            if missing or unexpected:
                raise ConfigError(
                    f"pretrained weights file {weights} does not match ResNet-18 "
                    f"(missing {missing[:3]}, unexpected {list(unexpected)[:3]})"
                )
        elif in_channels != 3:
            net.conv1 = nn.Conv2d(in_channels, 64, kernel_size=7, stride=2, padding=3, bias=False)
        self.trunk = nn.Sequential(
            net.conv1, net.bn1, net.relu, net.maxpool, net.layer1, net.layer2, net.layer3, net.layer4
        )
        self.head = nn.Conv2d(512, num_keypoints, kernel_size=1)
        # layers holding pretrained weights, left out of the ensemble's random init
        self.pretrained_layers: nn.Module | None = self.trunk if weights is not None else None
        with torch.no_grad():
            h, w = self.trunk(torch.zeros(1, in_channels, height, width)).shape[-2:]
        self.ssam = SpatialSoftArgmax(h, w)
        self.out_dim = 2 * num_keypoints

    def keypoints(self, images: torch.Tensor) -> torch.Tensor:
        """`(B, C, H, W)` -> `(B, K, 2)` keypoints in [-1, 1]."""
        return self.ssam(self.head(self.trunk(images)))

    @override
    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.keypoints(images).flatten(1)


ENCODERS: dict[str, type[nn.Module]] = {"cnn": KeypointCNN, "resnet18": ResNet18Keypoints}


def image_encoder(
    kind: str, in_channels: int, height: int, width: int, num_keypoints: int = 32, weights: str | Path | None = None
) -> nn.Module:
    """An image encoder by name (`cnn` or `resnet18`), output `(B, 2 * num_keypoints)`."""
    if kind not in ENCODERS:
        raise ConfigError(f"unknown image encoder {kind!r} (choose from {', '.join(ENCODERS)})")
    return ENCODERS[kind](in_channels, height, width, num_keypoints=num_keypoints, weights=weights)


def orthogonal_init_(module: nn.Module, skip: nn.Module | None = None) -> None:
    """Orthogonal weights and zero biases for every Linear/Conv layer (thesis 3.6.3: ensemble members
    differ by init), leaving the layers inside `skip` (pretrained weights) untouched."""
    skipped = {id(m) for m in skip.modules()} if skip is not None else set()
    for m in module.modules():
        if isinstance(m, (nn.Linear, nn.Conv2d)) and id(m) not in skipped:
            nn.init.orthogonal_(m.weight)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
