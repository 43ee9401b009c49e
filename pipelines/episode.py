"""The in-memory unit every stage works on: one episode as per-frame arrays."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

# Columns the LeRobot writer derives itself; an Episode never carries them.
DERIVED_KEYS = ("frame_index", "episode_index", "index", "task_index")


@dataclass
class Episode:
    """One episode: every per-frame feature as an array whose first axis is the frame.

    `frames` is keyed by LeRobot feature name (`observation.state`, `action`, ...) and always holds
    `timestamp` (seconds from the episode start) and `task` (one string per frame, so play-based
    episodes can label task segments). `meta` holds episode-level, JSON-serialisable facts
    (`outcome`, `seed`, `segments`, `source_episode_index`, ...).
    """

    frames: dict[str, np.ndarray]
    meta: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(len(self.frames["timestamp"]))

    def select(self, index: np.ndarray | slice) -> Episode:
        """A new episode made of the frames picked by `index` (arrays are copied, meta too)."""
        # subok: camera frames read from PNG keep their source bytes (pipelines/encoded_frames.py)
        return Episode({k: np.array(v[index], subok=True) for k, v in self.frames.items()}, dict(self.meta))

    def with_frames(self, **updates: np.ndarray) -> Episode:
        """A new episode with some feature arrays replaced or added (meta copied)."""
        frames = dict(self.frames)
        frames.update(updates)
        return Episode(frames, dict(self.meta))

    @property
    def tasks(self) -> list[str]:
        """Distinct tasks in order of first appearance."""
        return list(dict.fromkeys(str(t) for t in self.frames["task"]))
