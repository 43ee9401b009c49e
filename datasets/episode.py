"""The in-memory unit every stage works on: one episode as per-frame arrays, with the map from each
of its frames to the source frame it stands for."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

# Columns the LeRobot writer derives itself; an Episode never carries them.
DERIVED_KEYS = ("frame_index", "episode_index", "index", "task_index")
META_COLUMN = "shiftkit/meta"  # where a dataset stores `Episode.meta` (JSON): a column of meta/episodes/*.parquet


@dataclass
class Episode:
    """One episode: every per-frame feature as an array whose first axis is the frame.

    `frames` is keyed by LeRobot feature name (`observation.state`, `action`, ...) and always holds
    `timestamp` (seconds from the episode start) and `task` (one string per frame, so play-based
    episodes can label task segments). `meta` holds episode-level, JSON-serialisable facts
    (`outcome`, `seed`, `segments`, `source_episode_index`, ...).

    `source_frames` is the frame map: per frame, the index of the frame of the *source* episode
    (the one a pipeline read) that this frame stands for. It is never written to a dataset. A
    source's episode maps frame k to k; `select` and `reindexed` carry the map through frames a
    stage keeps, drops, repeats or resamples; an episode a stage builds anew frame for frame from
    its input leaves it None and the runner takes the input's (`follow`). What the map makes
    possible: checking every kept frame against its source frame, moving events and segments in
    one place (`pipelines/frame_map.py`), and copying unchanged frames instead of re-encoding them.
    """

    frames: dict[str, np.ndarray]
    meta: dict[str, Any] = field(default_factory=dict)
    source_frames: np.ndarray | None = None

    def __len__(self) -> int:
        return int(len(self.frames["timestamp"]))

    def origin(self) -> np.ndarray:
        """The frame map as an int64 array (frame k -> k while none was set)."""
        if self.source_frames is None:
            return np.arange(len(self), dtype=np.int64)
        return np.asarray(self.source_frames, dtype=np.int64)

    def select(self, index: np.ndarray | slice | list[int]) -> Episode:
        """A new episode made of the frames picked by `index` (arrays are copied, meta too); its frame
        map follows the picked frames."""
        # subok: camera frames read from PNG keep their source bytes (datasets/encoded_frames.py);
        # frames still encoded pick their own (`video_copy.VideoRef.select_frames`: stay encoded where they can)
        return Episode(
            {
                k: v.select_frames(index) if hasattr(v, "select_frames") else np.array(v[index], subok=True)
                for k, v in self.frames.items()
            },
            dict(self.meta),
            self.origin()[index],
        )

    def with_frames(self, **updates: np.ndarray) -> Episode:
        """A new episode with some feature arrays replaced or added (meta copied, frame map kept)."""
        frames = dict(self.frames)
        frames.update(updates)
        return Episode(frames, dict(self.meta), self.source_frames)

    def follow(self, parent: Episode, stage: str) -> Episode:
        """This episode, made by `stage` from `parent`, with its frame map: its own when the stage
        set one, else `parent`'s frame for frame. A stage that changed the number of frames must say
        which frame each one stands for (`select`, `frame_map.reindexed`); guessing would attach
        events and values to the wrong frames."""
        if self.source_frames is not None:
            if len(self.source_frames) != len(self):
                raise ValueError(f"stage {stage!r}: frame map of {len(self.source_frames)} for {len(self)} frames")
            return self
        if len(self) != len(parent):
            raise ValueError(
                f"stage {stage!r} made an episode of {len(self)} frames from one of {len(parent)} without a "
                "frame map: build it with Episode.select or frame_map.reindexed"
            )
        self.source_frames = parent.origin()
        return self

    @property
    def tasks(self) -> list[str]:
        """Distinct tasks in order of first appearance."""
        return list(dict.fromkeys(str(t) for t in self.frames["task"]))
