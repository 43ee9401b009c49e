"""Depth maps as lerobot 0.6 defines them: a camera feature `observation.depth.CAM` of shape
(H, W, 1) whose `info` carries `is_depth_map: true` and `depth_unit` ("m" or "mm"), so that
lerobot's `meta.depth_keys` lists it, its loader returns it as depth and its tools keep it.

* Stored as `image`: one lossless TIFF per frame (float32 metres for unit "m", uint16 millimetres
  for "mm"), the bytes lerobot's own writer produces.
* Stored as `video`: lerobot's depth encoder (12-bit log-quantised HEVC, `DepthEncoderConfig`;
  its parameters are recorded as `video.depth_min/max/shift/use_log` in the feature's `info`).

Inside shiftkit (episodes, stages, trainers) depth is always float32 metres, (T, H, W, 1): the
reader converts from the stored unit and the writer back to it, so a uint16-millimetre dataset
recorded by lerobot keeps its unit when shiftkit rewrites it (the round trip is exact).

Older shiftkit datasets stored depth as 8-bit grey RGB images (`gray8`, 1 cm steps, saturating at
2.55 m) with the range in `meta/cameras.json`; the `depth_image` stage migrates them
(`legacy_depth_to_metres`). docs/video_depth.md has the measured errors of each representation.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from shiftkit.datasets.errors import DatasetError

DEPTH_PREFIX = "observation.depth."
UNITS = ("m", "mm")  # lerobot's depth units: float32 metres, uint16 millimetres
DEFAULT_UNIT = "m"  # float32 metres: exact for MuJoCo's float depth
_IMAGE_NAMES = ["height", "width", "channels"]
# The encoding older shiftkit versions wrote (grey level = round((d - near) / (far - near) * 255)).
LEGACY_ENCODING = "gray8"
LEGACY_DEFAULT = {"encoding": LEGACY_ENCODING, "near": 0.0, "far": 2.55, "unit": "m"}


def depth_feature(height: int, width: int, dtype: str = "image", unit: str = DEFAULT_UNIT) -> dict[str, Any]:
    """A depth camera feature as lerobot 0.6 declares one (its writer adds `video.*` for videos)."""
    if unit not in UNITS:
        raise DatasetError(f"depth unit must be one of {sorted(UNITS)}, got {unit!r}")
    return {
        "dtype": dtype,
        "shape": (int(height), int(width), 1),
        "names": list(_IMAGE_NAMES),
        "info": {"is_depth_map": True, "depth_unit": unit},
    }


def is_depth(feature: Mapping[str, Any]) -> bool:
    """Whether `feature` is a lerobot depth map (`is_depth_map`, or the legacy `video.is_depth_map`)."""
    info = feature.get("info") or {}
    return bool(info.get("is_depth_map") or info.get("video.is_depth_map"))


def depth_unit(feature: Mapping[str, Any]) -> str:
    """The unit a depth feature is stored in ("m" when lerobot recorded none: float frames)."""
    unit = (feature.get("info") or {}).get("depth_unit") or DEFAULT_UNIT
    if unit not in UNITS:
        raise DatasetError(f"depth feature has unknown depth_unit {unit!r} (lerobot knows 'm' and 'mm')")
    return unit


def to_stored(metres: np.ndarray, unit: str) -> np.ndarray:
    """Float metres -> the stored representation (float32 m, or uint16 mm rounded and clipped)."""
    d = np.asarray(metres, dtype=np.float32)
    if unit == "mm":
        return np.rint(np.clip(d, 0.0, 65.535) * np.float32(1000.0)).astype(np.uint16)
    return d


def to_metres(stored: np.ndarray, unit: str | None = None) -> np.ndarray:
    """A stored depth array -> float32 metres (unit from the dtype when not given, as lerobot infers)."""
    arr = np.asarray(stored)
    if unit is None:
        unit = "m" if arr.dtype.kind == "f" else "mm"
    if unit == "mm":
        return arr.astype(np.float32) / np.float32(1000.0)
    return arr.astype(np.float32, copy=False)


def clean_metres(depth: np.ndarray) -> np.ndarray:
    """(..., H, W) or (..., H, W, 1) rendered depth -> (..., H, W, 1) float32, no return (inf, NaN)
    as 0 m (lerobot's convention for invalid depth, which its quantiser clips to depth_min)."""
    d = np.asarray(depth, dtype=np.float32)
    if d.shape[-1] != 1:
        d = d[..., None]
    return np.where(np.isfinite(d), d, np.float32(0.0)).astype(np.float32, copy=False)


def is_legacy_depth(key: str, feature: Mapping[str, Any]) -> bool:
    """A depth camera in a form older shiftkit wrote: 8-bit grey RGB images, or (H, W, 1) float arrays."""
    if not key.startswith(DEPTH_PREFIX) or is_depth(feature):
        return False
    shape = tuple(feature.get("shape", ()))
    grey = feature.get("dtype") in ("image", "video") and len(shape) == 3 and shape[-1] == 3
    floats = feature.get("dtype") in ("float32", "float64") and len(shape) == 3
    return grey or floats


def legacy_encoding(cameras: Mapping[str, Any] | None, camera: str) -> dict[str, Any]:
    """The gray8 range of `camera` from an older dataset's camera metadata (the default if absent)."""
    entry = ((cameras or {}).get(camera) or {}).get("depth") or LEGACY_DEFAULT
    near, far = entry.get("near"), entry.get("far")
    if (
        entry.get("encoding") != LEGACY_ENCODING
        or not isinstance(near, int | float)
        or not isinstance(far, int | float)
        or not 0 <= near < far
    ):
        raise DatasetError(f"camera {camera!r}: legacy depth encoding must be {{'encoding': 'gray8', 0 <= near < far}}")
    return {"encoding": LEGACY_ENCODING, "near": float(near), "far": float(far), "unit": "m"}


def legacy_grey(metres: np.ndarray, encoding: Mapping[str, Any] = LEGACY_DEFAULT) -> np.ndarray:
    """Metres -> older shiftkit's grey levels (H, W, 3) uint8, for policies trained on such data."""
    d = np.asarray(metres, dtype=np.float32)
    d = d[..., 0] if d.shape[-1] == 1 else d
    near, far = float(encoding["near"]), float(encoding["far"])
    d = np.where(np.isfinite(d), d, far)
    grey = np.rint((np.clip(d, near, far) - near) * (255.0 / (far - near))).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=-1)


def as_metres(frames: np.ndarray, cameras: Mapping[str, Any] | None, camera: str) -> np.ndarray:
    """A depth feature's frames as shiftkit holds depth: native (T, H, W, 1) float32 metres pass
    unchanged (their source bytes kept); older shiftkit arrays (grey levels, other float dtypes)
    are converted through the camera's legacy range."""
    if frames.dtype == np.float32 and frames.shape[-1] == 1:
        return frames
    return legacy_depth_to_metres(frames, legacy_encoding(cameras, camera))


def legacy_depth_to_metres(frames: np.ndarray, encoding: Mapping[str, Any] = LEGACY_DEFAULT) -> np.ndarray:
    """Older shiftkit depth -> (T, H, W, 1) float32 metres: grey levels (uint8 (T, H, W, 3); channel
    mean, since lossy video coding lets the channels differ) through the gray8 range, or float
    (T, H, W, 1) metres as they are."""
    arr = np.asarray(frames)
    if arr.dtype.kind == "f":
        return clean_metres(arr)
    grey = arr.astype(np.float32).mean(axis=-1, keepdims=True)
    near, far = float(encoding["near"]), float(encoding["far"])
    return (near + grey * ((far - near) / 255.0)).astype(np.float32)


# lerobot's depth video quantiser defaults (configs/video.py; metres), for videos whose `info`
# lacks a key. A test checks them against lerobot's constants.
VIDEO_DEFAULTS = {"depth_min": 0.01, "depth_max": 10.0, "shift": 3.5, "use_log": True}
