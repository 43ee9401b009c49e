"""`depth_image`: migrate the depth features older shiftkit versions wrote to lerobot 0.6's native
depth (`pipelines/depth.py`): 8-bit grey RGB images (decoded to metres through the range recorded
in the camera metadata, `meta/cameras.json`) and (H, W, 1) float arrays both become (H, W, 1)
depth features with `is_depth_map` and `depth_unit`, stored as lossless images (or video, with
`[destination] video = true`). Native depth features pass unchanged, so the stage can run on any
dataset."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal, override

import numpy as np

from shiftkit.pipelines.depth import (
    DEFAULT_UNIT,
    DEPTH_PREFIX,
    as_metres,
    depth_feature,
    is_legacy_depth,
)
from shiftkit.pipelines.episode import Episode
from shiftkit.pipelines.features import Features
from shiftkit.pipelines.stage import Stage, register_stage


@dataclass
class DepthImageConfig:
    """Parameters of `depth_image`."""

    unit: Literal["m", "mm"] = DEFAULT_UNIT
    """Unit the migrated depth is stored in: "m" (float32 metres, exact) or "mm" (uint16
    millimetres, half the size, 0.5 mm steps)."""


@register_stage
class DepthImage(Stage):
    """Rewrites legacy depth features (grey RGB images, float arrays) as native (H, W, 1) depth in `unit`."""

    name = "depth_image"
    version = 2
    example_params = {"unit": "mm"}
    Config = DepthImageConfig

    @override
    def transform_features(self, features: Features) -> Features:
        out = dict(features)  # idempotent: a dataset with native depth passes unchanged
        for key in [k for k, ft in features.items() if is_legacy_depth(k, ft)]:
            h, w = features[key]["shape"][:2]
            dtype = "video" if features[key]["dtype"] == "video" else "image"
            out[key] = depth_feature(h, w, dtype, self.config.unit)
        return out

    @override
    def process(self, episode: Episode, rng: np.random.Generator) -> Iterable[Episode]:
        frames, cameras = dict(episode.frames), dict(episode.meta.get("cameras") or {})
        for key in [k for k in frames if k.startswith(DEPTH_PREFIX)]:
            cam = key.removeprefix(DEPTH_PREFIX)
            frames[key] = as_metres(frames[key], cameras, cam)
            if "depth" in cameras.get(cam, {}):  # the grey-level range no longer applies
                cameras[cam] = {k: v for k, v in cameras[cam].items() if k != "depth"}
        meta = {**episode.meta, "cameras": cameras} if cameras else dict(episode.meta)
        yield Episode(frames, meta)
