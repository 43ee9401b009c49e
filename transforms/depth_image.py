"""`depth_image`: migrate float depth maps (H, W, 1) metres, the form shiftkit wrote before, to the
grey-level `image` encoding that lerobot's dataset tools accept (`pipelines/depth.py`). Features
already in that form pass unchanged, so the stage can run on any dataset."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from shiftkit.pipelines.depth import DEFAULT_ENCODING, DEPTH_PREFIX, encode_depth, is_float_depth
from shiftkit.pipelines.episode import Episode
from shiftkit.pipelines.features import Features, image_feature
from shiftkit.pipelines.stage import Stage, register_stage


@dataclass
class DepthImageConfig:
    near: float = DEFAULT_ENCODING["near"]
    """Depth (m) that maps to grey level 0; nearer points are clipped."""
    far: float = DEFAULT_ENCODING["far"]
    """Depth (m) that maps to grey level 255; farther points (and no return) read as `far`."""

    def __post_init__(self) -> None:
        if not 0 <= self.near < self.far:
            raise ValueError(f"need 0 <= near < far, got near={self.near}, far={self.far}")


@register_stage
class DepthImage(Stage):
    name = "depth_image"
    version = 1
    Config = DepthImageConfig

    def transform_features(self, features: Features) -> Features:
        out = dict(features)  # idempotent: a dataset without float depth passes unchanged
        for key in [k for k, ft in features.items() if is_float_depth(k, ft)]:
            h, w = features[key]["shape"][:2]
            out[key] = image_feature((h, w, 3))
        return out

    def process(self, episode: Episode, rng: np.random.Generator) -> Iterable[Episode]:
        encoding = {**DEFAULT_ENCODING, "near": float(self.config.near), "far": float(self.config.far)}
        frames, cameras = dict(episode.frames), dict(episode.meta.get("cameras") or {})
        for key, arr in episode.frames.items():
            if key.startswith(DEPTH_PREFIX) and arr.dtype.kind == "f":
                frames[key] = encode_depth(arr, encoding)
                cam = key.removeprefix(DEPTH_PREFIX)
                cameras[cam] = {**cameras.get(cam, {}), "depth": encoding}
        yield Episode(frames, {**episode.meta, "cameras": cameras})
