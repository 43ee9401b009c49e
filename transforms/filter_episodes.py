"""`filter`: keep or drop whole episodes by source index, task, outcome or length."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, override

import numpy as np

from shiftkit.datasets.episode import Episode
from shiftkit.datasets.features import Features
from shiftkit.pipelines.stage import FrameStage, register_stage


@dataclass
class FilterConfig:
    """Parameters of `filter`; an episode is kept when it meets every criterion."""

    indices: list[int] | None = None
    """Keep only these source episode indices (None: all)."""
    tasks: list[str] | None = None
    """Keep only episodes whose task (any frame's) is in this list."""
    outcomes: list[str] | None = None
    """Keep only episodes whose `outcome` metadata is in this list (e.g. ["success"])."""
    min_length: int = 1
    """Drop episodes with fewer frames."""
    max_length: int | None = None
    """Drop episodes with more frames (None: no limit)."""
    keep_fraction: float = 1.0
    """Keep each remaining episode with this probability (seeded), e.g. to subsample a dataset."""

    def __post_init__(self) -> None:
        if not 0.0 < self.keep_fraction <= 1.0:
            raise ValueError(f"keep_fraction must be in (0, 1], got {self.keep_fraction}")
        if self.min_length < 1 or (self.max_length is not None and self.max_length < self.min_length):
            raise ValueError("need 1 <= min_length <= max_length")


@register_stage
class FilterEpisodes(FrameStage):
    """Keeps or drops whole episodes by source index, task, outcome, length and a seeded draw."""

    name = "filter"
    version = 1
    example_params = {"min_length": 2, "keep_fraction": 0.7}
    Config = FilterConfig

    @override
    def transform_features(self, features: Features) -> Features:
        return features

    @override
    def process(self, episode: Episode, rng: np.random.Generator) -> Iterable[Episode]:
        c = self.config
        # Draw first so the decision for one episode never depends on the other criteria.
        draw = rng.random()
        keep = (
            (c.indices is None or episode.meta.get("source_episode_index") in c.indices)
            and (c.tasks is None or bool(set(episode.tasks) & set(c.tasks)))
            and (c.outcomes is None or episode.meta.get("outcome") in c.outcomes)
            and c.min_length <= len(episode)
            and (c.max_length is None or len(episode) <= c.max_length)
            and draw < c.keep_fraction
        )
        self.report("episodes_dropped", int(not keep))
        if keep:
            yield episode

    @classmethod
    @override
    def identity_params(cls, features: Features, fps: int) -> dict[str, Any] | None:
        return {}
