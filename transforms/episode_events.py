"""Episode events under frame dropping: `next.success` / `next.done` hold for a kept frame when
they held anywhere in the window of frames it stands for, so dropping frames never loses a success;
likewise lerobot's `language_events` (messages fired at a frame) of a window all land on the frame
that stands for it."""

from __future__ import annotations

import numpy as np

from shiftkit.pipelines.features import object_column

EVENT_KEYS = ("next.success", "next.done")
LANGUAGE_EVENTS = "language_events"  # lerobot.datasets.language.LANGUAGE_EVENTS


def or_events(frames: dict[str, np.ndarray], out: dict[str, np.ndarray], starts: np.ndarray) -> None:
    """Set `out[key]` (one row per kept frame) to the OR of `frames[key]` over each kept frame's
    window `[starts[i], starts[i + 1])`, the last window running to the episode end. `starts` is
    non-decreasing; an empty window (a repeated frame) keeps its own frame's value."""
    for key in EVENT_KEYS:
        if key in frames and key in out and len(starts):
            arr = np.asarray(frames[key])
            out[key] = np.logical_or.reduceat(arr.astype(bool), starts, axis=0).astype(arr.dtype)
    if LANGUAGE_EVENTS in frames and LANGUAGE_EVENTS in out and len(starts):
        # A window's messages, in order, on its frame; a repeated frame (empty window) fires none.
        events, ends = frames[LANGUAGE_EVENTS], np.r_[starts[1:], len(frames[LANGUAGE_EVENTS])]
        rows = [[row for i in range(s, e) for row in (events[i] or [])] for s, e in zip(starts, ends, strict=True)]
        out[LANGUAGE_EVENTS] = object_column(rows)
