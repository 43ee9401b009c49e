"""`trim`: drop frames at the start and end of each episode (timestamps restart at 0)."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import override

import numpy as np

from shiftkit.pipelines.episode import Episode
from shiftkit.pipelines.features import Features
from shiftkit.pipelines.stage import Stage, register_stage


@dataclass
class TrimConfig:
    """Parameters of `trim`."""

    head: int = 0
    """Frames removed from the start."""
    tail: int = 0
    """Frames removed from the end."""

    def __post_init__(self) -> None:
        if self.head < 0 or self.tail < 0:
            raise ValueError("head and tail must be >= 0")


@register_stage
class Trim(Stage):
    """Drops `head` frames at the start and `tail` at the end of each episode; an episode of at most `head + tail` frames is dropped."""

    name = "trim"
    version = 1
    example_params = {"head": 1, "tail": 2}
    Config = TrimConfig

    @override
    def transform_features(self, features: Features) -> Features:
        return features

    @override
    def process(self, episode: Episode, rng: np.random.Generator) -> Iterable[Episode]:
        n = len(episode)
        start, stop = self.config.head, n - self.config.tail
        if stop <= start:
            return  # nothing left of this episode
        out = episode.select(slice(start, stop))
        out.frames["timestamp"] = out.frames["timestamp"] - out.frames["timestamp"][0]
        if "segments" in out.meta:
            out.meta["segments"] = _shift_segments(out.meta["segments"], start, stop)
        yield out


def _shift_segments(segments: list[dict], start: int, stop: int) -> list[dict]:
    kept = []
    for seg in segments:
        s, e = max(seg["start"], start), min(seg["end"], stop)
        if s < e:
            kept.append({**seg, "start": s - start, "end": e - start})
    return kept
