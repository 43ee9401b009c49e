"""`map_tasks`: task strings to a common vocabulary (sources that name one task differently, e.g.
"open the door" and "door-open", become one task of the merged dataset). Play episodes' task
segments (`meta["segments"]`) are mapped too."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any, override

import numpy as np

from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import DatasetError
from shiftkit.datasets.features import Features
from shiftkit.pipelines.stage import FrameStage, register_stage


@dataclass
class MapTasksConfig:
    """Parameters of `map_tasks`."""

    mapping: dict[str, str] = field(default_factory=dict)
    """Task as recorded -> task in the output."""
    default: str | None = None
    """The task of every task the mapping does not list (unset: such tasks stay as they are)."""
    strict: bool = False
    """An episode with a task the mapping does not list is an error (and `default` is not used)."""

    def __post_init__(self) -> None:
        if any(not v.strip() for v in self.mapping.values()) or (self.default is not None and not self.default.strip()):
            raise ValueError("a task cannot become an empty string")


@register_stage
class MapTasks(FrameStage):
    """Rewrites each episode's task strings through `mapping` (and `default`)."""

    name = "map_tasks"
    version = 1
    example_params = {"mapping": {"reach": "reach the goal"}}
    Config = MapTasksConfig

    @override
    def transform_features(self, features: Features) -> Features:
        return features

    def _map(self, task: str, where: str) -> str:
        if task in self.config.mapping:
            return self.config.mapping[task]
        if self.config.strict:
            raise DatasetError(f"map_tasks: {where} has task {task!r}, which the mapping does not list")
        return self.config.default if self.config.default is not None else task

    @override
    def process(self, episode: Episode, rng: np.random.Generator) -> Iterable[Episode]:
        where = f"episode {episode.meta.get('source_episode_index')}"
        mapped = {t: self._map(t, where) for t in episode.tasks}
        tasks = np.array([mapped[str(t)] for t in episode.frames["task"]], dtype=object)
        out = episode.with_frames(task=tasks)
        if "segments" in out.meta:
            out.meta["segments"] = [
                {**s, "task": self._map(str(s["task"]), where)} if "task" in s else s for s in out.meta["segments"]
            ]
        if "task" in out.meta:
            out.meta["task"] = self._map(str(out.meta["task"]), where)
        yield out

    @override
    def carried_features(self, features: Features) -> dict[str, str]:
        return {k: v for k, v in super().carried_features(features).items() if k != "task"}

    @classmethod
    @override
    def identity_params(cls, features: Features, fps: int) -> dict[str, Any] | None:
        return {"mapping": {}}
