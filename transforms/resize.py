"""`resize`: camera images to one size, so that sources recorded with other cameras can be merged.

RGB is resized as lerobot 0.6.1 resizes camera images (`ImageCropResizeProcessorStep`:
torchvision's `resize`, bilinear with antialiasing, on float images in [0, 1]), then rounded back
to uint8. Depth maps take the nearest pixel (pixel centres mapped like OpenCV's `INTER_NEAREST_EXACT`):
averaging depth across an object's edge would invent surfaces that are not there. The intrinsics
in the episode metadata (`meta/cameras.json`) are scaled with the feature they describe: where a
camera's RGB and depth share them and only one is resized, the resized one gets intrinsics of its
own (`camera_meta.cameras_for_features`). A frame of the requested size passes through untouched.
"""

from __future__ import annotations

import copy
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any, override

import numpy as np

from shiftkit.datasets.camera_meta import cameras_for_features, feature_entries
from shiftkit.datasets.dataclass_config import check_fields, option
from shiftkit.datasets.depth import is_depth
from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import ConfigError
from shiftkit.datasets.features import CAMERA_DTYPES, Features
from shiftkit.pipelines.stage import FrameStage, register_stage


@dataclass
class ResizeConfig:
    """Parameters of `resize`."""

    width: int = option(rule="positive_int")
    """Output image width in pixels."""
    height: int = option(rule="positive_int")
    """Output image height in pixels."""
    features: list[str] = field(default_factory=list)
    """Camera features to resize (empty: every camera feature)."""

    def __post_init__(self) -> None:
        check_fields(self)


@register_stage
class Resize(FrameStage):
    """Resizes camera features (all, or the named ones) to `width` x `height` pixels."""

    name = "resize"
    # v2: intrinsics scaled per feature (a camera's RGB and depth apart); v3: video keeps its codec settings
    version = 3
    example_params = {"width": 32, "height": 24}
    Config = ResizeConfig

    @override
    def transform_features(self, features: Features) -> Features:
        cameras = [k for k, ft in features.items() if ft["dtype"] in CAMERA_DTYPES]
        for key in self.config.features:
            if key not in cameras:
                raise ConfigError(f"resize: no camera feature {key!r} (cameras: {', '.join(cameras) or 'none'})")
        self._keys = list(self.config.features) or cameras
        self._cameras = cameras
        self._depth = {k for k in self._keys if is_depth(features[k])}
        out = copy.deepcopy(features)
        for key in self._keys:
            ft = out[key]
            ft["shape"] = (self.config.height, self.config.width, tuple(ft["shape"])[-1])
            if "video.height" in (ft.get("info") or {}):
                # only the size changes: the source's codec settings (`video.codec`, `video.pix_fmt`,
                # `video.g`, `video.crf`, ...) stay, and the writer encodes the resized frames with them
                ft["info"] = {**ft["info"], "video.height": self.config.height, "video.width": self.config.width}
        return out

    @override
    def process(self, episode: Episode, rng: np.random.Generator) -> Iterable[Episode]:
        size = (self.config.height, self.config.width)
        updates, scaled = {}, {}
        for key in self._keys:
            frames = episode.frames[key]
            if frames.shape[1:3] == size:
                continue
            updates[key] = nearest(frames, size) if key in self._depth else bilinear(frames, size)
            scaled[key] = frames.shape[1:3]
        out = episode.with_frames(**updates)
        if scaled and out.meta.get("cameras"):
            cameras = [k for k in self._cameras if k in episode.frames]
            entries = {k: feature_entries(out.meta["cameras"], k) for k in cameras}
            for key, old in scaled.items():
                if entries[key].get("intrinsics"):
                    entries[key] = {
                        **entries[key],
                        "intrinsics": scale_intrinsics(entries[key]["intrinsics"], old, size),
                    }
            out.meta["cameras"] = cameras_for_features(out.meta["cameras"], cameras, entries)
        yield out

    @classmethod
    @override
    def identity_params(cls, features: Features, fps: int) -> dict[str, Any] | None:
        sizes = {tuple(ft["shape"])[:2] for ft in features.values() if ft["dtype"] in CAMERA_DTYPES}
        if len(sizes) != 1:
            return None  # no one size leaves every camera as it is
        ((h, w),) = sizes
        return {"width": w, "height": h}


def bilinear(frames: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(T, H, W, C) uint8 -> (T, h, w, C) uint8, as lerobot's image resize step computes it."""
    import torch
    from torchvision.transforms import InterpolationMode
    from torchvision.transforms.functional import resize

    x = torch.from_numpy(np.ascontiguousarray(frames)).permute(0, 3, 1, 2).to(torch.float32) / 255.0
    y = resize(x, list(size), interpolation=InterpolationMode.BILINEAR, antialias=True).clamp(0.0, 1.0)
    return torch.round(y * 255.0).to(torch.uint8).permute(0, 2, 3, 1).contiguous().numpy()


def nearest(frames: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(T, H, W, C) -> (T, h, w, C): each output pixel takes the input pixel under its centre."""
    h, w = size
    rows = np.minimum(((np.arange(h) + 0.5) * frames.shape[1] / h).astype(np.int64), frames.shape[1] - 1)
    cols = np.minimum(((np.arange(w) + 0.5) * frames.shape[2] / w).astype(np.int64), frames.shape[2] - 1)
    return np.ascontiguousarray(frames[:, rows][:, :, cols])


def scale_intrinsics(intrinsics: dict[str, Any], old: tuple[int, int], size: tuple[int, int]) -> dict[str, Any]:
    """Intrinsics of an image of (h, w) `old` scaled to `size` (pixel centres at integer coordinates,
    so cx = (width - 1) / 2 stays the centre). Intrinsics that describe another size than `old`
    are returned as they are: they do not describe this image."""
    if (intrinsics.get("width"), intrinsics.get("height")) != (old[1], old[0]):
        return intrinsics
    h, w = size
    sx, sy = w / old[1], h / old[0]
    return {
        **intrinsics,
        "fx": intrinsics["fx"] * sx,
        "fy": intrinsics["fy"] * sy,
        "cx": (intrinsics["cx"] + 0.5) * sx - 0.5,
        "cy": (intrinsics["cy"] + 0.5) * sy - 0.5,
        "width": w,
        "height": h,
    }
