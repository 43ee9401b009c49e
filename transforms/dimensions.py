"""`select` and `pad`: the dimensions of a vector feature by name, so that sources that record
other dimensions can be merged (keep `x, y, z, gripper` of a 9-dim state; add a dimension one
source lacks as a constant, which the provenance lists under `padded`)."""

from __future__ import annotations

import copy
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any, override

import numpy as np

from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import ConfigError
from shiftkit.datasets.features import NUMERIC_DTYPES, Features
from shiftkit.pipelines.stage import FrameStage, register_stage


def _names(stage: str, features: Features, key: str) -> list[str]:
    """The dimension names of vector feature `key` (a ConfigError names what is wrong)."""
    if key not in features:
        raise ConfigError(f"{stage}: no feature {key!r} (features: {', '.join(features)})")
    ft = features[key]
    names = ft.get("names")
    if ft["dtype"] not in NUMERIC_DTYPES or len(tuple(ft["shape"])) != 1 or not isinstance(names, list):
        raise ConfigError(f"{stage}: feature {key!r} is not a vector with dimension names")
    return [str(n) for n in names]


def _first_vector(features: Features) -> tuple[str, list[str]] | None:
    """The first vector feature with dimension names, and its names (for identity parameters)."""
    for key, ft in features.items():
        names = ft.get("names")
        if ft["dtype"] in NUMERIC_DTYPES and len(tuple(ft["shape"])) == 1 and isinstance(names, list) and names:
            return key, [str(n) for n in names]
    return None


def _with_names(features: Features, key: str, names: list[str]) -> Features:
    out = copy.deepcopy(features)
    out[key]["shape"] = (len(names),)
    out[key]["names"] = list(names)
    return out


@dataclass
class SelectConfig:
    """Parameters of `select`."""

    feature: str
    """The vector feature (e.g. `observation.state`)."""
    names: list[str]
    """Its dimensions to keep, by name, in the output order."""
    rename: dict[str, str] = field(default_factory=dict)
    """New names for kept dimensions (old name -> new name)."""

    def __post_init__(self) -> None:
        if not self.names:
            raise ValueError("names must name at least one dimension")
        if len(set(self.names)) != len(self.names):
            raise ValueError(f"names lists a dimension twice: {self.names}")


@register_stage
class Select(FrameStage):
    """Keeps the named dimensions of one vector feature, in the given order, optionally renamed."""

    name = "select"
    version = 1
    example_params = {"feature": "observation.state", "names": ["gripper", "ee_x"], "rename": {"ee_x": "x"}}
    Config = SelectConfig

    @override
    def transform_features(self, features: Features) -> Features:
        names = _names("select", features, self.config.feature)
        missing = [n for n in self.config.names if n not in names]
        if missing:
            raise ConfigError(
                f"select: feature {self.config.feature!r} has no dimension(s) {missing} (it has {names}); "
                "use 'pad' to add a dimension"
            )
        stray = [n for n in self.config.rename if n not in self.config.names]
        if stray:
            raise ConfigError(f"select: rename names dimension(s) {stray} that are not selected")
        out_names = [self.config.rename.get(n, n) for n in self.config.names]
        if len(set(out_names)) != len(out_names):
            raise ConfigError(f"select: two dimensions would get the same name ({out_names})")
        self._index = np.array([names.index(n) for n in self.config.names], dtype=np.int64)
        return _with_names(features, self.config.feature, out_names)

    @override
    def process(self, episode: Episode, rng: np.random.Generator) -> Iterable[Episode]:
        arr = episode.frames[self.config.feature]
        yield episode.with_frames(**{self.config.feature: np.ascontiguousarray(arr[:, self._index])})

    @classmethod
    @override
    def identity_params(cls, features: Features, fps: int) -> dict[str, Any] | None:
        vector = _first_vector(features)
        return {"feature": vector[0], "names": vector[1]} if vector else None


@dataclass
class PadConfig:
    """Parameters of `pad`."""

    feature: str
    """The vector feature (e.g. `observation.state`)."""
    names: list[str]
    """Its dimensions in the output order: every dimension it has, plus the ones to add."""
    value: float = 0.0
    """The constant every added dimension holds in every frame."""

    def __post_init__(self) -> None:
        if len(set(self.names)) != len(self.names):
            raise ValueError(f"names lists a dimension twice: {self.names}")


@register_stage
class Pad(FrameStage):
    """Puts one vector feature's dimensions in the given order, adding the missing ones as the constant `value`."""

    name = "pad"
    version = 1
    example_params = {
        "feature": "observation.state",
        "names": ["ee_x", "ee_y", "ee_z", "ee_yaw", "gripper"],
        "value": 0.5,
    }
    Config = PadConfig

    @override
    def transform_features(self, features: Features) -> Features:
        names = _names("pad", features, self.config.feature)
        dropped = [n for n in names if n not in self.config.names]
        if dropped:
            raise ConfigError(
                f"pad: names leaves out dimension(s) {dropped} of {self.config.feature!r}; use 'select' to drop dimensions"
            )
        self._padded = [n for n in self.config.names if n not in names]
        self._index = np.array([names.index(n) if n in names else -1 for n in self.config.names], dtype=np.int64)
        return _with_names(features, self.config.feature, self.config.names)

    @override
    def process(self, episode: Episode, rng: np.random.Generator) -> Iterable[Episode]:
        arr = episode.frames[self.config.feature]
        out = np.full((len(arr), len(self._index)), self.config.value, dtype=arr.dtype)
        have = self._index >= 0
        out[:, have] = arr[:, self._index[have]]
        yield episode.with_frames(**{self.config.feature: out})

    @classmethod
    @override
    def identity_params(cls, features: Features, fps: int) -> dict[str, Any] | None:
        vector = _first_vector(features)
        return {"feature": vector[0], "names": vector[1]} if vector else None

    @override
    def describe(self) -> dict[str, Any]:
        # The provenance says which dimensions hold no recorded data.
        padded = getattr(self, "_padded", None)
        return {**super().describe(), **({"padded": padded} if padded is not None else {})}
