"""`rename`: give features new names (e.g. to match another dataset or a policy's inputs)."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import override

import numpy as np

from shiftkit.pipelines.episode import Episode
from shiftkit.pipelines.errors import ConfigError
from shiftkit.pipelines.features import Features
from shiftkit.pipelines.stage import Stage, register_stage


@dataclass
class RenameConfig:
    """Parameters of `rename`."""

    mapping: dict[str, str] = field(default_factory=dict)
    """Old feature name -> new feature name."""


@register_stage
class Rename(Stage):
    """Renames features in the schema and every frame."""

    name = "rename"
    version = 1
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
        return out

    @override
    def process(self, episode: Episode, rng: np.random.Generator) -> Iterable[Episode]:
        mapping = self.config.mapping
        yield Episode({mapping.get(k, k): v for k, v in episode.frames.items()}, dict(episode.meta))
