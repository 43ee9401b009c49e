"""Depth maps as LeRobot camera features that lerobot's dataset tools and trainers accept.

A depth map in metres becomes an `image` feature `observation.depth.CAM` of shape (H, W, 3), uint8:
the grey level `round((clip(d, near, far) - near) / (far - near) * 255)` in all three channels.
lerobot's tools (`delete_episodes`, `split_dataset`, `merge_datasets`, `aggregate_datasets`,
`convert_image_to_video_dataset`, `modify_tasks`) all handle it, and lerobot's policies see it as
one more camera. The default range 0-2.55 m is 1 cm per grey level (worst-case error 5 mm inside
the range; farther points read as `far`). Measured choices and error bounds: docs/video_depth.md.

The encoding of a camera's depth is recorded in its camera metadata (`meta["cameras"][CAM]["depth"]`,
kept in `meta/cameras.json`), so it can be decoded back to metres; without it the default applies.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from shiftkit.pipelines.errors import DatasetError

DEPTH_PREFIX = "observation.depth."
ENCODING = "gray8"
DEFAULT_ENCODING = {"encoding": ENCODING, "near": 0.0, "far": 2.55, "unit": "m"}


def depth_encoding(cameras: Mapping[str, Any] | None, camera: str) -> dict[str, Any]:
    """The depth encoding of `camera` from an episode's camera metadata (the default if absent)."""
    entry = ((cameras or {}).get(camera) or {}).get("depth") or DEFAULT_ENCODING
    near, far = entry.get("near"), entry.get("far")
    if (
        entry.get("encoding") != ENCODING
        or not isinstance(near, int | float)
        or not isinstance(far, int | float)
        or not 0 <= near < far
    ):
        raise DatasetError(f"camera {camera!r}: depth encoding must be {{'encoding': 'gray8', 0 <= near < far}}")
    return {"encoding": ENCODING, "near": float(near), "far": float(far), "unit": "m"}


def encode_depth(metres: np.ndarray, encoding: Mapping[str, Any] = DEFAULT_ENCODING) -> np.ndarray:
    """(..., H, W) or (..., H, W, 1) float metres -> (..., H, W, 3) uint8 grey levels."""
    d = np.asarray(metres, dtype=np.float32)
    if d.ndim >= 3 and d.shape[-1] == 1:
        d = d[..., 0]
    if not np.isfinite(d).all():
        d = np.where(np.isfinite(d), d, encoding["far"])  # no return (inf/NaN) reads as far away
    near, far = float(encoding["near"]), float(encoding["far"])
    grey = np.rint((np.clip(d, near, far) - near) * (255.0 / (far - near))).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=-1)


def decode_depth(image: np.ndarray, encoding: Mapping[str, Any] = DEFAULT_ENCODING) -> np.ndarray:
    """(..., H, W, 3) uint8 grey levels -> (..., H, W) float32 metres (channel mean: after lossy
    video coding the three channels can differ slightly)."""
    grey = np.asarray(image, dtype=np.float32).mean(axis=-1)
    near, far = float(encoding["near"]), float(encoding["far"])
    return (near + grey * ((far - near) / 255.0)).astype(np.float32)


def is_float_depth(key: str, feature: Mapping[str, Any]) -> bool:
    """A depth feature in the float (H, W, 1) form shiftkit wrote before the image encoding (which
    lerobot's `delete_episodes`/`aggregate_datasets`/... cannot process)."""
    shape = tuple(feature.get("shape", ()))
    return key.startswith(DEPTH_PREFIX) and feature.get("dtype") in ("float32", "float64") and len(shape) == 3
