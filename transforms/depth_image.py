"""`depth_image`: migrate the depth features older shiftkit versions wrote to lerobot 0.6's native
depth (`pipelines/depth.py`): 8-bit grey RGB images (decoded to metres through the range recorded
in the camera metadata, `meta/cameras.json`) and (H, W, 1) float arrays both become (H, W, 1)
depth features with `is_depth_map` and `depth_unit`, stored as lossless images (or video, with
`[destination] video = true`). Native depth features pass unchanged, so the stage can run on any
dataset."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from shiftkit.pipelines.depth import (
    DEFAULT_UNIT,
    DEPTH_PREFIX,
    depth_feature,
    is_legacy_depth,
    legacy_depth_to_metres,
    legacy_encoding,
)
from shiftkit.pipelines.episode import Episode
from shiftkit.pipelines.features import Features
from shiftkit.pipelines.stage import Stage, register_stage


@dataclass
class DepthImageConfig:
    unit: Literal["m", "mm"] = DEFAULT_UNIT
    """Unit the migrated depth is stored in: "m" (float32 metres, exact) or "mm" (uint16
    millimetres, half the size, 0.5 mm steps)."""


@register_stage
class DepthImage(Stage):
    name = "depth_image"
    version = 2
    Config = DepthImageConfig

    def transform_features(self, features: Features) -> Features:
        out = dict(features)  # idempotent: a dataset with native depth passes unchanged
        for key in [k for k, ft in features.items() if is_legacy_depth(k, ft)]:
            h, w = features[key]["shape"][:2]
            dtype = "video" if features[key]["dtype"] == "video" else "image"
            out[key] = depth_feature(h, w, dtype, self.config.unit)
        return out

    def process(self, episode: Episode, rng: np.random.Generator) -> Iterable[Episode]:
        frames, cameras = dict(episode.frames), dict(episode.meta.get("cameras") or {})
        # Older depth by its arrays (grey uint8, or float (H, W, 1) of another dtype); native depth is
        # float32 (H, W, 1) metres already and passes unchanged.
        legacy = [
            k for k, a in frames.items() if k.startswith(DEPTH_PREFIX) and (a.dtype != np.float32 or a.shape[-1] != 1)
        ]
        for key in legacy:
            cam = key.removeprefix(DEPTH_PREFIX)
            frames[key] = legacy_depth_to_metres(episode.frames[key], legacy_encoding(cameras, cam))
            if "depth" in cameras.get(cam, {}):  # the grey-level range no longer applies
                cameras[cam] = {k: v for k, v in cameras[cam].items() if k != "depth"}
        meta = {**episode.meta, "cameras": cameras} if cameras else dict(episode.meta)
        yield Episode(frames, meta)
