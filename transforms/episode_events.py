"""Episode events under frame dropping: `next.success` / `next.done` hold for a kept frame when
they held anywhere in the window of frames it stands for, so dropping frames never loses a success."""

from __future__ import annotations

import numpy as np

EVENT_KEYS = ("next.success", "next.done")


def or_events(frames: dict[str, np.ndarray], out: dict[str, np.ndarray], starts: np.ndarray) -> None:
    """Set `out[key]` (one row per kept frame) to the OR of `frames[key]` over each kept frame's
    window `[starts[i], starts[i + 1])`, the last window running to the episode end. `starts` is
    non-decreasing; an empty window (a repeated frame) keeps its own frame's value."""
    for key in EVENT_KEYS:
        if key in frames and key in out and len(starts):
            arr = np.asarray(frames[key])
            out[key] = np.logical_or.reduceat(arr.astype(bool), starts, axis=0).astype(arr.dtype)
