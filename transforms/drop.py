"""`drop`: remove features (e.g. simulator state before publishing a dataset)."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any, override

import numpy as np

from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import ConfigError
from shiftkit.datasets.features import Features
from shiftkit.pipelines.stage import FrameStage, register_stage


@dataclass
class DropConfig:
    """Parameters of `drop`."""

    features: list[str] = field(default_factory=list)
    """Feature names to remove."""


@register_stage
class Drop(FrameStage):
    """Removes the named features from the schema and every frame."""

    name = "drop"
    version = 1
    example_params = {"features": ["observation.environment_state"]}
    Config = DropConfig

    @override
    def transform_features(self, features: Features) -> Features:
        for key in self.config.features:
            if key not in features:
                raise ConfigError(f"drop: no feature {key!r} (features: {', '.join(features)})")
        out = {k: v for k, v in features.items() if k not in self.config.features}
        if not out:
            raise ConfigError("drop: would remove every feature")
        return out

    @override
    def dropped_unread(self, features: Features) -> set[str]:
        return set(self.config.features)

    @override
    def process(self, episode: Episode, rng: np.random.Generator) -> Iterable[Episode]:
        drop = set(self.config.features)
        yield Episode({k: v for k, v in episode.frames.items() if k not in drop}, dict(episode.meta))

    @classmethod
    @override
    def identity_params(cls, features: Features, fps: int) -> dict[str, Any] | None:
        return {"features": []}
