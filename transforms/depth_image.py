"""`depth_image`: depth features as lerobot 0.6's native depth (`datasets/depth.py`) in one unit.

The depth features older shiftkit versions wrote, 8-bit grey RGB images (decoded to metres through
the range recorded in the camera metadata, `meta/cameras.json`) and (H, W, 1) float arrays, become
(H, W, 1) depth features with `is_depth_map` and `depth_unit`, stored as lossless images (or
video, with `[destination] video = true`). With `unit` set, native depth features are converted to
it too (float32 metres <-> uint16 millimetres); unset, they keep their own unit, so the stage can
run on any dataset."""

from __future__ import annotations

import copy
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, Literal, override

import numpy as np

from shiftkit.datasets.depth import DEFAULT_UNIT, DEPTH_PREFIX, as_metres, depth_feature, is_depth, is_legacy_depth
from shiftkit.datasets.episode import Episode
from shiftkit.datasets.features import Features
from shiftkit.pipelines.stage import FrameStage, register_stage


@dataclass
class DepthImageConfig:
    """Parameters of `depth_image`."""

    unit: Literal["m", "mm"] | None = None
    """Unit every depth feature is stored in: "m" (float32 metres, exact) or "mm" (uint16
    millimetres, half the size, 0.5 mm steps). Unset: migrated depth in metres, native depth in its
    own unit."""


@register_stage
class DepthImage(FrameStage):
    """Rewrites legacy depth features (grey RGB images, float arrays) as native (H, W, 1) depth, and every depth feature in `unit` when set."""

    name = "depth_image"
    version = 3  # v3: `unit` converts native depth too; unset keeps each native feature's unit
    example_params = {"unit": "mm"}
    Config = DepthImageConfig

    @override
    def transform_features(self, features: Features) -> Features:
        out = dict(features)
        for key, ft in features.items():
            if is_legacy_depth(key, ft):
                h, w = ft["shape"][:2]
                dtype = "video" if ft["dtype"] == "video" else "image"
                out[key] = depth_feature(h, w, dtype, self.config.unit or DEFAULT_UNIT)
            elif is_depth(ft) and self.config.unit is not None:
                # depth is float32 metres inside shiftkit: the unit is how the writer stores it
                out[key] = copy.deepcopy(ft)
                out[key]["info"] = {**(ft.get("info") or {}), "depth_unit": self.config.unit}
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

    @classmethod
    @override
    def identity_params(cls, features: Features, fps: int) -> dict[str, Any] | None:
        return None if any(is_legacy_depth(k, ft) for k, ft in features.items()) else {}
