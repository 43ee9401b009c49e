"""`subsample`: keep every k-th frame; the dataset's fps becomes fps / k.

A kept frame stands for the frames up to the next kept one: `next.success` / `next.done` are OR-ed
over that window, so an episode that ends in success still does."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import override

import numpy as np

from shiftkit.pipelines.episode import Episode
from shiftkit.pipelines.errors import ConfigError
from shiftkit.pipelines.features import Features
from shiftkit.pipelines.stage import Stage, register_stage
from shiftkit.transforms.episode_events import or_events


@dataclass
class SubsampleConfig:
    """Parameters of `subsample`."""

    every: int = 2
    """Keep one frame out of `every`; it must divide the input fps (LeRobot fps are integers)."""
    offset: int = 0
    """Index of the first kept frame (0 <= offset < every)."""

    def __post_init__(self) -> None:
        if self.every < 1 or not 0 <= self.offset < self.every:
            raise ValueError("need every >= 1 and 0 <= offset < every")


@register_stage
class Subsample(Stage):
    """Keeps every `every`-th frame from `offset`; the output fps is the input fps / `every`."""

    name = "subsample"
    version = 2  # v2: episode events OR-ed over the dropped frames
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
    def process(self, episode: Episode, rng: np.random.Generator) -> Iterable[Episode]:
        if len(episode) <= self.config.offset:
            return
        out = episode.select(slice(self.config.offset, None, self.config.every))
        starts = np.arange(self.config.offset, len(episode), self.config.every)
        starts[0] = 0  # events before the first kept frame belong to it
        or_events(episode.frames, out.frames, starts)
        out.frames["timestamp"] = np.arange(len(out), dtype=np.float64) / self.transform_fps(self.context.fps)
        if "segments" in out.meta:
            k, o = self.config.every, self.config.offset
            out.meta["segments"] = [
                {**s, "start": -(-(s["start"] - o) // k), "end": -(-(s["end"] - o) // k)}
                for s in out.meta["segments"]
                if -(-(s["end"] - o) // k) > -(-(s["start"] - o) // k)
            ]
        yield out
