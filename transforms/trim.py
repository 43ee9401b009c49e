"""`trim`: drop frames at the start and end of each episode (timestamps restart at 0).

A kept frame stands for itself only (`frame_map.reindexed` with the kept frames as its cover):
events of the dropped frames are dropped with them, task segments are clipped, and lerobot's
persistent language rows move with the time line."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, override

import numpy as np

from shiftkit.datasets.dataclass_config import check_fields, option
from shiftkit.datasets.episode import Episode
from shiftkit.datasets.features import Features
from shiftkit.pipelines.frame_map import rebased_times
from shiftkit.pipelines.stage import Reindex, ReindexStage, register_stage


@dataclass
class TrimConfig:
    """Parameters of `trim`."""

    head: int = option(0, rule="non_negative_int")
    """Frames removed from the start."""
    tail: int = option(0, rule="non_negative_int")
    """Frames removed from the end."""

    def __post_init__(self) -> None:
        check_fields(self)


@register_stage
class Trim(ReindexStage):
    """Drops `head` frames at the start and `tail` at the end of each episode; an episode of at most `head + tail` frames is dropped."""

    name = "trim"
    version = 2  # v2: language rows' timestamps follow the time line
    example_params = {"head": 1, "tail": 2}
    Config = TrimConfig

    @override
    def transform_features(self, features: Features) -> Features:
        return features

    @override
    def kept_frames(self, features: Features) -> dict[str, str]:
        return self.carried_cameras(features)  # one contiguous run per episode: copied, cut at its start

    @override
    def reindex(self, episode: Episode, rng: np.random.Generator) -> Iterable[Reindex]:
        n = len(episode)
        start, stop = self.config.head, n - self.config.tail
        if stop <= start:
            return  # nothing left of this episode
        index = np.arange(start, stop)
        yield Reindex(index, rebased_times(episode.frames["timestamp"], index, self.context.fps), cover=(start, stop))

    @classmethod
    @override
    def identity_params(cls, features: Features, fps: int) -> dict[str, Any] | None:
        return {"head": 0, "tail": 0}
