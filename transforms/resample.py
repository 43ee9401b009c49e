"""`resample`: put an episode on a regular grid at a new fps.

Irregular recorder timestamps (real teleop logs) are mapped onto `k / fps` for every grid time
inside the recording. Float features are linearly interpolated; integer, bool, string and image
features take the nearest earlier-or-equal frame (interpolating a gripper command or an image
would invent values that never happened). `next.success` / `next.done` are OR-ed over the frames
a grid frame stands for, so downsampling never drops a success.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal, override

import numpy as np

from shiftkit.pipelines.episode import Episode
from shiftkit.pipelines.features import Features
from shiftkit.pipelines.stage import Stage, register_stage
from shiftkit.transforms.episode_events import or_events


@dataclass
class ResampleConfig:
    """Parameters of `resample`."""

    fps: int
    """Output frame rate (frames per second)."""
    method: Literal["linear", "previous"] = "linear"
    """How float features are resampled: linear interpolation or the previous sample."""

    def __post_init__(self) -> None:
        if self.fps < 1:
            raise ValueError("fps must be >= 1")


@register_stage
class Resample(Stage):
    """Puts each episode on the regular grid `k / fps`, interpolating floats and holding the rest."""

    name = "resample"
    version = 2  # v2: episode events OR-ed over the dropped frames
    example_params = {"fps": 5}
    resampling_params = {"fps": [1, 2, 7, 13, 30, 90]}
    Config = ResampleConfig

    @override
    def transform_fps(self, fps: int) -> int:
        return self.config.fps

    @override
    def transform_features(self, features: Features) -> Features:
        return features

    @override
    def process(self, episode: Episode, rng: np.random.Generator) -> Iterable[Episode]:
        ts = episode.frames["timestamp"].astype(np.float64)
        ts = ts - ts[0]
        grid = np.arange(int(np.floor(ts[-1] * self.config.fps + 1e-9)) + 1) / self.config.fps
        prev = np.clip(np.searchsorted(ts, grid + 1e-9, side="right") - 1, 0, len(ts) - 1)
        frames: dict[str, np.ndarray] = {}
        for key, arr in episode.frames.items():
            if key == "timestamp":
                continue
            if arr.dtype.kind == "f" and self.config.method == "linear" and len(ts) > 1:
                flat = arr.reshape(len(arr), -1).astype(np.float64)
                cols = [np.interp(grid, ts, flat[:, j]) for j in range(flat.shape[1])]
                frames[key] = np.stack(cols, axis=1).reshape((len(grid), *arr.shape[1:])).astype(arr.dtype)
            else:
                frames[key] = arr[prev]
        or_events(episode.frames, frames, prev)
        frames["timestamp"] = grid
        meta = dict(episode.meta)
        if "segments" in meta:
            # Segment bounds are frame indices; move them to the grid frame at the same time.
            to_grid = lambda i: int(np.searchsorted(grid, ts[min(i, len(ts) - 1)] - 1e-9)) if i < len(ts) else len(grid)  # noqa: E731
            meta["segments"] = [
                {**s, "start": to_grid(s["start"]), "end": to_grid(s["end"])}
                for s in meta["segments"]
                if to_grid(s["end"]) > to_grid(s["start"])
            ]
        yield Episode(frames, meta)
