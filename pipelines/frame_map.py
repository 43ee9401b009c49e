"""Re-indexing an episode through its frame map: what a stage that keeps, drops, repeats or resamples
frames (`trim`, `subsample`, `resample`, ...) does to everything that is not a per-frame value.

An output frame k stands for source frame `index[k]` (`Episode.source_frames`). Every source frame
the output covers (`cover`, default all) belongs to one output frame, its *window*: a frame stood
for belongs to the first output frame that stands for it; a dropped frame to the last output frame
before it (the frames before the first stood-for frame to the first output frame). So a kept frame
stands for the frames up to the next kept one, the last output frame keeps the end of the episode,
and of several output frames standing for one source frame (upsampling) only the first fires its
events. Then, in one place:

* per-frame values are the stood-for frame's (`Episode.select`), unless the stage computes them;
* events, what happens *at* a frame (`next.success`, `next.done`, lerobot's `language_events`),
  land on the output frame whose window holds their frame, never on an earlier one: flags are
  OR-ed over the window, message rows concatenated in order, so dropping frames never loses a
  success and a repeated frame never fires one twice;
* task segments (`meta["segments"]`, frame-index bounds) hold the output frames whose stood-for
  frame lies in them;
* lerobot's `language_persistent` rows carry the time they became active (`timestamp`); it is moved
  onto the output time line so that the row active at an output frame is the one active at the
  frame it stands for (lerobot's `active_at`), and rows keep their order.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from shiftkit.datasets.episode import Episode
from shiftkit.datasets.features import object_column

EVENT_KEYS = ("next.success", "next.done")
LANGUAGE_EVENTS = "language_events"  # lerobot.datasets.language.LANGUAGE_EVENTS
LANGUAGE_PERSISTENT = "language_persistent"  # lerobot.datasets.language.LANGUAGE_PERSISTENT
# A recorded time within this fraction of a frame period of a frame's nominal time is that time:
# lerobot stores float32 timestamps (frame_index / fps rounded: 3.8 s reads back as 3.7999999 s).
REGULAR_TOLERANCE = 0.01


def windows(index: np.ndarray, cover: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Per output frame, the source frames [start, end) that belong to it (see the module
    docstring). `index` is non-decreasing."""
    index = np.asarray(index, dtype=np.int64)
    if not len(index):
        return index.copy(), index.copy()
    step = index[1:] > index[:-1]
    first, last = np.r_[True, step], np.r_[step, True]  # of each run of frames standing for one
    starts, ends = index.copy(), index.copy()  # frames inside a run: empty windows
    ends[first] = index[first] + 1
    starts[last & ~first] = index[last & ~first] + 1
    ends[last] = np.r_[index[1:][step], cover[1]]
    starts[0] = min(cover[0], index[0])
    return starts, ends


def reindexed(
    source: Episode,
    index: np.ndarray,
    timestamps: np.ndarray,
    frames: dict[str, np.ndarray] | None = None,
    cover: tuple[int, int] | None = None,
) -> Episode:
    """The episode whose frame k stands for `source` frame `index[k]` (non-decreasing), at
    `timestamps`. `frames`: per-frame values the stage computed itself (e.g. interpolated); every
    other feature takes the stood-for frame's value. `cover`: the source frames [start, stop) the
    output stands for (default: all of them; `trim` covers only the frames it keeps)."""
    index = np.asarray(index, dtype=np.int64)
    if len(index) and (np.any(np.diff(index) < 0) or index[0] < 0 or index[-1] >= len(source)):
        raise ValueError(f"a frame map must be non-decreasing within the {len(source)} source frames")
    cover = (0, len(source)) if cover is None else cover
    out = source.select(index)
    out.frames.update(frames or {})
    out.frames["timestamp"] = np.asarray(timestamps, dtype=np.float64)
    starts, ends = windows(index, cover)
    for key in EVENT_KEYS:
        if key in source.frames and key in out.frames:
            out.frames[key] = _or_over(np.asarray(source.frames[key]), starts, ends)
    if LANGUAGE_EVENTS in source.frames and LANGUAGE_EVENTS in out.frames:
        events = source.frames[LANGUAGE_EVENTS]
        out.frames[LANGUAGE_EVENTS] = object_column(
            [[row for i in range(s, e) for row in (events[i] or [])] for s, e in zip(starts, ends, strict=True)]
        )
    if LANGUAGE_PERSISTENT in out.frames:
        src_times = np.asarray(source.frames["timestamp"], dtype=np.float64)[index]
        out.frames[LANGUAGE_PERSISTENT] = _move_persistent(
            out.frames[LANGUAGE_PERSISTENT], index, src_times, timestamps
        )
    if "segments" in out.meta:
        out.meta["segments"] = move_segments(out.meta["segments"], index)
    return out


def rebased_times(timestamps: np.ndarray, index: np.ndarray, fps: int) -> np.ndarray:
    """The times of the frames at `index` (consecutive) from the first of them: `k / fps` when the
    recording is regular at `fps` (what lerobot's writer stores: frame_index / fps, so a trimmed
    lerobot dataset has lerobot's own timestamps), else the recorded differences."""
    ts = np.asarray(timestamps, dtype=np.float64)
    if np.all(np.abs(ts - ts[0] - np.arange(len(ts)) / fps) <= REGULAR_TOLERANCE / fps):
        return np.arange(len(index), dtype=np.float64) / fps
    return ts[index] - ts[index[0]]


def _or_over(flags: np.ndarray, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """Per window, whether any frame in it has the flag (an empty window: False), as `flags`' dtype."""
    per_frame = flags.reshape(len(flags), -1).astype(bool)
    counts = np.concatenate([np.zeros((1, per_frame.shape[1]), np.int64), np.cumsum(per_frame, axis=0)])
    hit = (counts[ends] - counts[starts]) > 0
    return hit.reshape((len(starts), *flags.shape[1:])).astype(flags.dtype)


def move_segments(segments: list[dict[str, Any]], index: np.ndarray) -> list[dict[str, Any]]:
    """Task segments ([start, end) in source frames) in the output frames whose stood-for frame lies in
    them; a segment no output frame stands in is left out."""
    moved = []
    for seg in segments:
        start, end = (int(np.searchsorted(index, seg[b], side="left")) for b in ("start", "end"))
        if end > start:
            moved.append({**seg, "start": start, "end": end})
    return moved


def _move_persistent(column: np.ndarray, index: np.ndarray, src_times: np.ndarray, out_times: np.ndarray) -> np.ndarray:
    """Each persistent row's `timestamp` mapped from the source's time line to the output's: linearly
    between the times of consecutive stood-for frames (a row that became active at a frame between
    two kept ones becomes active at the later one, as its values do), shifted before the first and
    after the last."""
    first = np.r_[True, np.diff(index) > 0] if len(index) else np.zeros(0, bool)
    xs, ys = src_times[first], np.asarray(out_times, dtype=np.float64)[first]

    def move(t: float) -> float:
        if t < xs[0]:
            return float(t - xs[0] + ys[0])
        if t > xs[-1]:
            return float(t - xs[-1] + ys[-1])
        return float(np.interp(t, xs, ys))  # a stood-for frame's time becomes its output frame's exactly

    moved: dict[int, list] = {}  # lerobot broadcasts one list to every frame: move each once
    rows = []
    for value in column:
        key = id(value)
        if key not in moved:
            moved[key] = [
                {**row, "timestamp": move(float(row["timestamp"]))} if row.get("timestamp") is not None else row
                for row in (value or [])
            ]
        rows.append(moved[key])
    return object_column(rows)
