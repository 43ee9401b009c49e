"""`subsample`: keep every k-th frame; the dataset's fps becomes fps / k.

A kept frame stands for the frames up to the next kept one (`pipelines/frame_map.py`): events
(`next.success` / `next.done`, language events) of that window land on it, so an episode that ends
in success still does; the frames before the first kept one belong to it."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, override

import numpy as np

from shiftkit.datasets.dataclass_config import check_fields, option
from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import ConfigError
from shiftkit.datasets.features import Features
from shiftkit.pipelines.stage import Reindex, ReindexStage, register_stage


@dataclass
class SubsampleConfig:
    """Parameters of `subsample`."""

    every: int = option(2, rule="positive_int")
    """Keep one frame out of `every`; it must divide the input fps (LeRobot fps are integers)."""
    offset: int = 0
    """Index of the first kept frame (0 <= offset < every)."""

    def __post_init__(self) -> None:
        check_fields(self)
        if not 0 <= self.offset < self.every:
            raise ValueError(f"need 0 <= offset < every, got offset {self.offset} with every {self.every}")


@register_stage
class Subsample(ReindexStage):
    """Keeps every `every`-th frame from `offset`; the output fps is the input fps / `every`."""

    name = "subsample"
    version = 3  # v3: events moved by the frame map (a repeated frame fires none), language rows' times follow
    example_params = {"every": 2, "offset": 1}
    resampling_params = {"every": [2, 3, 4, 5], "offset": [0, 1, 2]}
    Config = SubsampleConfig

    @override
    def transform_fps(self, fps: int) -> int:
        if fps % self.config.every:
            raise ConfigError(f"subsample: every={self.config.every} does not divide the input fps {fps}")
        return fps // self.config.every

    @override
    def transform_features(self, features: Features) -> Features:
        return features

    @override
    def kept_frames(self, features: Features) -> dict[str, str]:
        return self.carried_cameras(features)  # every k-th frame: keyframes copied, the others encoded

    @override
    def reindex(self, episode: Episode, rng: np.random.Generator) -> Iterable[Reindex]:
        index = np.arange(self.config.offset, len(episode), self.config.every)
        if len(index):
            yield Reindex(index, np.arange(len(index)) / self.transform_fps(self.context.fps))

    @classmethod
    @override
    def identity_params(cls, features: Features, fps: int) -> dict[str, Any] | None:
        return {"every": 1, "offset": 0}
