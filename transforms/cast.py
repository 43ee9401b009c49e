"""`cast`: change the dtype of numeric features (e.g. float64 simulator state to float32)."""

from __future__ import annotations

import copy
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any, Literal, override

import numpy as np

from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import ConfigError, DatasetError
from shiftkit.datasets.features import NUMERIC_DTYPES, Features
from shiftkit.pipelines.stage import FrameStage, register_stage

NumericDtype = Literal["float32", "float64", "int64", "int32", "bool"]


@dataclass
class CastConfig:
    """Parameters of `cast`."""

    dtypes: dict[str, NumericDtype] = field(default_factory=dict)
    """Feature name -> new dtype."""


@register_stage
class Cast(FrameStage):
    """Changes the dtype of the named numeric features, in the schema and in every frame."""

    name = "cast"
    version = 1
    example_params = {"dtypes": {"action": "float64"}}
    Config = CastConfig

    @override
    def transform_features(self, features: Features) -> Features:
        out = copy.deepcopy(features)
        for key, dtype in self.config.dtypes.items():
            if key not in features:
                raise ConfigError(f"cast: no feature {key!r} (features: {', '.join(features)})")
            if features[key]["dtype"] not in NUMERIC_DTYPES:
                raise ConfigError(f"cast: feature {key!r} has dtype {features[key]['dtype']!r}, not numeric")
            out[key]["dtype"] = dtype
        return out

    @override
    def process(self, episode: Episode, rng: np.random.Generator) -> Iterable[Episode]:
        frames = dict(episode.frames)
        for key, dtype in self.config.dtypes.items():
            arr = frames[key]
            if np.dtype(dtype).kind in "iub" and arr.dtype.kind == "f" and not np.isfinite(arr).all():
                raise DatasetError(f"cast: feature {key!r} has NaN/inf values that cannot become {dtype}")
            frames[key] = arr.astype(dtype)
        yield Episode(frames, dict(episode.meta))

    @classmethod
    @override
    def identity_params(cls, features: Features, fps: int) -> dict[str, Any] | None:
        return {"dtypes": {}}
