"""`resize`: camera images to one size, so that sources recorded with other cameras can be merged.

RGB is resized as lerobot 0.6.1 resizes camera images (`ImageCropResizeProcessorStep`:
torchvision's `resize`, bilinear with antialiasing, on float images in [0, 1]), then rounded back
to uint8. Depth maps take the nearest pixel (pixel centres mapped like OpenCV's `INTER_NEAREST_EXACT`):
averaging depth across an object's edge would invent surfaces that are not there. The camera's
intrinsics in the episode metadata (`meta/cameras.json`) are scaled with its image; a frame of the
requested size passes through untouched.
"""

from __future__ import annotations

import copy
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any, override

import numpy as np

from shiftkit.pipelines.depth import is_depth
from shiftkit.pipelines.episode import Episode
from shiftkit.pipelines.errors import ConfigError
from shiftkit.pipelines.features import CAMERA_DTYPES, Features
from shiftkit.pipelines.stage import Stage, register_stage

CAMERA_PREFIXES = ("observation.images.", "observation.depth.")


@dataclass
class ResizeConfig:
    """Parameters of `resize`."""

    width: int
    """Output image width in pixels."""
    height: int
    """Output image height in pixels."""
    features: list[str] = field(default_factory=list)
    """Camera features to resize (empty: every camera feature)."""

    def __post_init__(self) -> None:
        if self.width < 1 or self.height < 1:
            raise ValueError(f"width and height must be >= 1, got {self.width}x{self.height}")


@register_stage
class Resize(Stage):
    """Resizes camera features (all, or the named ones) to `width` x `height` pixels."""

    name = "resize"
    version = 1
    example_params = {"width": 32, "height": 24}
    Config = ResizeConfig

    @override
    def transform_features(self, features: Features) -> Features:
        cameras = [k for k, ft in features.items() if ft["dtype"] in CAMERA_DTYPES]
        for key in self.config.features:
            if key not in cameras:
                raise ConfigError(f"resize: no camera feature {key!r} (cameras: {', '.join(cameras) or 'none'})")
        self._keys = list(self.config.features) or cameras
        self._depth = {k for k in self._keys if is_depth(features[k])}
        out = copy.deepcopy(features)
        for key in self._keys:
            ft = out[key]
            ft["shape"] = (self.config.height, self.config.width, tuple(ft["shape"])[-1])
            if ft.get("info"):
                # a video's recorded size and encoder settings no longer describe it; lerobot's
                # writer records them again
                ft["info"] = {k: v for k, v in ft["info"].items() if not k.startswith("video.")}
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
            scaled[camera_name(key)] = frames.shape[1:3]
        out = episode.with_frames(**updates)
        if scaled and out.meta.get("cameras"):
            out.meta["cameras"] = scale_intrinsics(out.meta["cameras"], scaled, size)
        yield out


def camera_name(key: str) -> str:
    """The camera a feature belongs to (`observation.images.front` and `observation.depth.front`
    are the camera `front` of `meta/cameras.json`)."""
    for prefix in CAMERA_PREFIXES:
        if key.startswith(prefix):
            return key.removeprefix(prefix)
    return key


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


def scale_intrinsics(
    cameras: dict[str, Any], scaled: dict[str, tuple[int, int]], size: tuple[int, int]
) -> dict[str, Any]:
    """The cameras with the intrinsics of each resized camera scaled from its old (h, w) to `size`
    (pixel centres at integer coordinates, so cx = (width - 1) / 2 stays the centre). Intrinsics
    that describe another size (e.g. of a depth map left as it is) are kept."""
    out = copy.deepcopy(cameras)
    h, w = size
    for name, (old_h, old_w) in scaled.items():
        intr = (out.get(name) or {}).get("intrinsics")
        if not intr or (intr.get("width"), intr.get("height")) != (old_w, old_h):
            continue
        sx, sy = w / old_w, h / old_h
        intr.update(
            fx=intr["fx"] * sx,
            fy=intr["fy"] * sy,
            cx=(intr["cx"] + 0.5) * sx - 0.5,
            cy=(intr["cy"] + 0.5) * sy - 0.5,
            width=w,
            height=h,
        )
    return out
