"""`rename`: give features new names (e.g. to match another dataset or a policy's inputs).

A camera feature's metadata (`meta/cameras.json`: intrinsics, extrinsics, ...) moves with it to its
new camera name; where the camera's other feature keeps the old name, both cameras keep the
entries that describe them (`camera_meta.cameras_for_features`)."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any, override

import numpy as np

from shiftkit.datasets.camera_meta import cameras_for_features, feature_entries
from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import ConfigError
from shiftkit.datasets.features import CAMERA_DTYPES, Features
from shiftkit.pipelines.stage import FrameStage, register_stage


@dataclass
class RenameConfig:
    """Parameters of `rename`."""

    mapping: dict[str, str] = field(default_factory=dict)
    """Old feature name -> new feature name."""


@register_stage
class Rename(FrameStage):
    """Renames features in the schema and every frame."""

    name = "rename"
    version = 2  # v2: camera metadata moves with a renamed camera feature
    example_params = {"mapping": {"observation.environment_state": "observation.goal"}}
    Config = RenameConfig

    @override
    def transform_features(self, features: Features) -> Features:
        mapping = self.config.mapping
        for old, new in mapping.items():
            if old not in features:
                raise ConfigError(f"rename: no feature {old!r} to rename (features: {', '.join(features)})")
            if "/" in new or not new:
                raise ConfigError(f"rename: invalid new name {new!r}")
        out = {mapping.get(k, k): v for k, v in features.items()}
        if len(out) != len(features):
            raise ConfigError("rename: two features would get the same name")
        self._cameras = [k for k, ft in features.items() if ft["dtype"] in CAMERA_DTYPES]
        return out

    @override
    def carried_features(self, features: Features) -> dict[str, str]:
        return {**super().carried_features(features), **{new: old for old, new in self.config.mapping.items()}}

    @override
    def process(self, episode: Episode, rng: np.random.Generator) -> Iterable[Episode]:
        mapping = self.config.mapping
        meta = dict(episode.meta)
        if meta.get("cameras") and any(k in mapping for k in self._cameras):
            moved = {mapping.get(k, k): feature_entries(meta["cameras"], k) for k in self._cameras}
            meta["cameras"] = cameras_for_features(meta["cameras"], self._cameras, moved)
        yield Episode({mapping.get(k, k): v for k, v in episode.frames.items()}, meta)

    @classmethod
    @override
    def identity_params(cls, features: Features, fps: int) -> dict[str, Any] | None:
        return {"mapping": {}}
