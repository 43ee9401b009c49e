"""The BC policy (thesis 3.6.3): an ensemble of members that each encode cameras with a CNN
(or ResNet-18 trunk) ending in a spatial soft-argmax and regress the action from those keypoints and
the normalised numeric state; the policy outputs the members' mean, their spread is FIRE's ensemble
doubt (thesis 5.4). `PolicySpec` rebuilds one without the data; `load_policy` reads a checkpoint.
The trainer is `policies/trainers/bc/`; FIRE and the discriminator build on these classes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from shiftkit.datasets.errors import ConfigError, DatasetError
from shiftkit.datasets.features import numpy_dtype
from shiftkit.policies.networks import image_encoder, mlp, orthogonal_init_
from shiftkit.policies.run_dir import RunDir, load_checkpoint
from shiftkit.policies.trainers.bc.args import OUTPUT_ACTIVATIONS


@dataclass(frozen=True)
class Normalization:
    """How a policy normalises: per dimension `std' = max(std, std_floor * sqrt(mean^2 + std^2),
    std_min)`, inputs `clip((x - mean) / std', -clip, clip)`; actions use the same floor, unclipped.

    Why these defaults: a dimension whose std is under 1% of its magnitude (coefficient of variation
    < 1%) barely moved in the demonstrations, and dividing by that std turns noise or a small
    deviation into hundreds of stds; the floor caps that gain at 100 / magnitude while leaving any
    dimension that varies by more than 1% of its size untouched. It cannot help a dimension that sits
    at ~0 (an untouched object's velocity), so inputs are also clipped: by Chebyshev's inequality at
    most 1/k^2 of any dimension's training frames lie beyond k stds, so clipping at 10 touches at
    most 1% of the frames of even a spiky feature (contact forces), where 5 could touch 4%, while a
    state outside the demonstrations reaches the network as at most 10 stds. Action targets are not
    clipped: a correction may need an action the demonstrations never took, and the output must be
    able to reach it."""

    std_floor: float = 0.01
    """Relative floor: share of the dimension's RMS value `sqrt(mean^2 + std^2)`."""
    std_min: float = 1e-6
    """Absolute floor (dataset units), so an exactly constant zero dimension divides by no zero."""
    clip: float | None = 10.0
    """Bound of the normalised inputs in floored stds; None: no clipping."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.std_floor) and 0 <= self.std_floor < 1):
            raise ConfigError(f"norm_std_floor must be in [0, 1), got {self.std_floor}")
        if not (math.isfinite(self.std_min) and self.std_min > 0):
            raise ConfigError(f"the absolute std floor must be positive, got {self.std_min}")
        if self.clip is not None and not self.clip > 0:
            raise ConfigError(f"norm_clip must be positive (or none for no clipping), got {self.clip}")

    def floored(self, mean: torch.Tensor, std: torch.Tensor) -> torch.Tensor:
        """The std used for normalisation."""
        floor = torch.clamp(self.std_floor * torch.sqrt(mean**2 + std**2), min=self.std_min)
        return torch.maximum(std, floor)


def legacy_std(std: torch.Tensor) -> torch.Tensor:
    """Normalisation of checkpoints written before `Normalization` was recorded (their policy spec has
    no `normalization`): a std below 1e-6 is replaced by 1 and nothing is clipped, so such policies act
    exactly as they were trained, near-constant dimensions included."""
    return torch.where(std < 1e-6, torch.ones_like(std), std)


@dataclass
class PolicySpec:
    """What a trained BC policy consumes and how it is built: enough to rebuild it without the data."""

    features: dict[str, dict]
    """Input feature -> {"dtype", "shape", "names"} as in the dataset's info.json."""
    action: dict
    """The `action` feature ({"dtype", "shape", "names"})."""
    stats: dict[str, dict[str, list]]
    """Feature (inputs and `action`) -> {"mean", "std"} used for normalisation."""
    encoder: str
    num_keypoints: int
    hidden: list[int]
    ensemble_size: int
    normalization: Normalization | None = field(default_factory=Normalization)
    """Std floor and input clipping; None for checkpoints that predate it (`legacy_std`, no clip)."""
    output_activation: str = "linear"
    """`linear`, or `tanh`: actions bounded to [-1, 1] in the dataset's units (thesis 5.4.2's policy)."""

    def __post_init__(self) -> None:
        if isinstance(self.normalization, dict):  # as stored in a checkpoint by dataclasses.asdict
            self.normalization = Normalization(**self.normalization)
        if self.output_activation not in OUTPUT_ACTIVATIONS:
            raise ConfigError(
                f"output activation must be one of {', '.join(OUTPUT_ACTIVATIONS)}, got {self.output_activation!r}"
            )

    def image_keys(self) -> list[str]:
        """Camera features: RGB (`image`/`video`, uint8) and float maps named (height, width, channels),
        e.g. depth; each gets its own image encoder."""
        return [k for k, ft in self.features.items() if is_image_feature(ft)]

    def numeric_keys(self) -> list[str]:
        """The non-image input features (vectors, normalised and concatenated)."""
        return [k for k, ft in self.features.items() if not is_image_feature(ft)]


def is_image_feature(ft: dict) -> bool:
    """Whether a LeRobot feature is a camera image (RGB or e.g. a depth map)."""
    names = ft.get("names")
    return ft["dtype"] in ("image", "video") or (
        len(ft["shape"]) == 3 and isinstance(names, list) and names[:2] == ["height", "width"]
    )


def _channel_stats(mean: np.ndarray, std: np.ndarray, channels: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel mean/std from stats that are per channel (lerobot's images: (C, 1, 1)) or per
    pixel (float maps: (H, W, C)), pooling the pixels' moments."""
    mean, std = mean.reshape(-1, channels), std.reshape(-1, channels)
    if mean.shape[0] == 1 and mean.size == channels and std.size == channels:
        return mean.reshape(-1), std.reshape(-1)
    pooled = mean.mean(axis=0)
    return pooled, np.sqrt(np.maximum((std**2 + mean**2).mean(axis=0) - pooled**2, 0.0))


class Normalizer(nn.Module):
    """Dataset-stats normalisation: numeric features `(x - mean) / std`; images `(B, H, W, C)` to float
    `(B, C, H, W)` (uint8 scaled to [0, 1], as lerobot's image stats are), then per-channel
    `(x - mean) / std`; std floored and inputs clipped as `spec.normalization` says."""

    def __init__(self, spec: PolicySpec) -> None:
        super().__init__()
        norm = spec.normalization
        self.clip = norm.clip if norm is not None else None
        self.keys = [*spec.numeric_keys(), *spec.image_keys(), "action"]
        self.images = set(spec.image_keys())
        # RGB cameras are uint8 (scaled to [0, 1] as lerobot's image stats are); depth is metres.
        self.uint8 = {k for k in self.images if numpy_dtype(spec.features[k]) == np.uint8}
        for i, key in enumerate(self.keys):
            mean = np.asarray(spec.stats[key]["mean"], dtype=np.float32)
            std = np.asarray(spec.stats[key]["std"], dtype=np.float32)
            if key in self.images:
                channels = spec.features[key]["shape"][-1]
                mean, std = (x.reshape(1, -1, 1, 1) for x in _channel_stats(mean, std, channels))
            mean, std = torch.as_tensor(mean), torch.as_tensor(std)
            std = norm.floored(mean, std) if norm is not None else legacy_std(std)
            self.register_buffer(f"mean{i}", mean)
            self.register_buffer(f"std{i}", std)

    def _ms(self, key: str) -> tuple[torch.Tensor, torch.Tensor]:
        i = self.keys.index(key)
        return getattr(self, f"mean{i}"), getattr(self, f"std{i}")

    def forward(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Every input but the action normalised by its statistics (images channel-first, uint8 scaled
        to [0, 1] first) and clipped to +-`clip` stds."""
        out = {}
        for key in self.keys[:-1]:
            mean, std = self._ms(key)
            x = batch[key]
            if key in self.images:
                x = x.permute(0, 3, 1, 2).float() / (255.0 if key in self.uint8 else 1.0)
            x = (x.float() - mean) / std
            out[key] = x if self.clip is None else x.clamp(-self.clip, self.clip)
        return out

    def floored_dims(self, spec: PolicySpec) -> int:
        """How many numeric dimensions normalise by a floored std (for the model card)."""
        return sum(
            int((getattr(self, f"std{i}") > torch.as_tensor(spec.stats[k]["std"], dtype=torch.float32)).sum())
            for i, k in enumerate(self.keys)
            if k not in self.images
        )

    def action(self, action: torch.Tensor) -> torch.Tensor:
        """An action in the units of the normalised policy output."""
        mean, std = self._ms("action")
        return (action - mean) / std

    def unaction(self, action: torch.Tensor) -> torch.Tensor:
        """A normalised policy output back in the dataset's action units."""
        mean, std = self._ms("action")
        return action * std + mean


class BCNet(nn.Module):
    """One ensemble member: image encoders -> keypoints, concatenated with the numeric state -> MLP."""

    def __init__(self, spec: PolicySpec, encoder_weights: str | None = None) -> None:
        super().__init__()
        self.numeric_keys, self.image_keys = spec.numeric_keys(), spec.image_keys()
        self.encoders = nn.ModuleList()
        for key in self.image_keys:
            h, w, c = spec.features[key]["shape"]
            self.encoders.append(image_encoder(spec.encoder, c, h, w, spec.num_keypoints, encoder_weights))
        in_dim = sum(int(np.prod(spec.features[k]["shape"])) for k in self.numeric_keys)
        in_dim += sum(enc.out_dim for enc in self.encoders)
        self.head = mlp(in_dim, int(np.prod(spec.action["shape"])), tuple(spec.hidden))
        self.tanh = spec.output_activation == "tanh"
        if self.tanh:  # tanh bounds the action in dataset units; the loss stays in normalised units
            mean, std = (torch.as_tensor(spec.stats["action"][k], dtype=torch.float32) for k in ("mean", "std"))
            norm = spec.normalization
            self.register_buffer("action_mean", mean)
            self.register_buffer("action_std", norm.floored(mean, std) if norm is not None else legacy_std(std))

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """The (B, A) normalised action of normalised observations `obs`."""
        parts = [obs[k].flatten(1) for k in self.numeric_keys]
        parts += [enc(obs[k]) for enc, k in zip(self.encoders, self.image_keys, strict=True)]
        out = self.head(torch.cat(parts, dim=-1))
        return (torch.tanh(out) - self.action_mean) / self.action_std if self.tanh else out


def ensemble_doubt(outs: torch.Tensor) -> torch.Tensor:
    """`||diag Cov||_2` over the members of `(M, B, A)` actions -> `(B,)`; 0 for a single member."""
    if outs.shape[0] < 2:
        return torch.zeros(outs.shape[1], device=outs.device)
    return outs.var(dim=0).norm(dim=-1)


class BCPolicy(nn.Module):
    """A BC ensemble with its normalisation; outputs actions in the dataset's units."""

    trainer = "bc"

    def __init__(self, spec: PolicySpec, encoder_weights: str | None = None, seed: int = 0) -> None:
        super().__init__()
        self.spec = spec
        self.features = spec.features
        self.normalizer = Normalizer(spec)
        members = []
        for m in range(spec.ensemble_size):
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(seed * 1009 + m)
                net = BCNet(spec, encoder_weights)
                pretrained = [enc.pretrained_layers for enc in net.encoders if enc.pretrained_layers is not None]
                orthogonal_init_(net, skip=nn.ModuleList(pretrained))
            members.append(net)
        self.members = nn.ModuleList(members)

    def member_outputs(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Every member's action `(M, B, A)` in dataset units."""
        obs = self.normalizer(batch)
        return self.normalizer.unaction(torch.stack([net(obs) for net in self.members]))

    def forward(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """The ensemble's mean action `(B, A)`."""
        return self.member_outputs(batch).mean(dim=0)

    def spread(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Ensemble doubt `(B,)`: the 2-norm of the members' per-dimension action variance
        (`||diag Cov||_2`, Menda et al. 2019; thesis 5.4); 0 for a single member."""
        return ensemble_doubt(self.member_outputs(batch))

    @property
    def action_names(self) -> list[str] | None:
        """Names of the action's dims (the training dataset's), for matching the env's action."""
        return self.spec.action.get("names")

    @torch.no_grad()
    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """One unbatched observation (feature -> array) -> one action (float32)."""
        device = next(self.parameters()).device
        batch = {k: torch.as_tensor(np.asarray(obs[k]))[None].to(device) for k in self.features}
        return self(batch)[0].cpu().numpy().astype(np.float32)


def load_policy(path: str | Path, device: str = "cpu") -> BCPolicy:
    """A trained BC policy from a checkpoint file or a run folder (its newest checkpoint)."""
    path = Path(path)
    if path.is_dir():
        ckpt_path = RunDir(path, resume=True).latest_checkpoint()
        if ckpt_path is None:
            raise DatasetError(f"run folder {path} has no checkpoint")
        path = ckpt_path
    if not path.is_file():
        raise DatasetError(f"policy checkpoint not found: {path}")
    state = load_checkpoint(path)
    if state.get("trainer") != "bc":
        raise DatasetError(f"{path} is not a BC checkpoint (trainer {state.get('trainer')!r})")
    # a spec without `normalization` predates it: None keeps that policy's own (legacy) normalisation
    policy = BCPolicy(PolicySpec(**{"normalization": None, **state["policy_spec"]}))
    policy.load_state_dict(state["model"])
    return policy.to(device).eval()
