"""`resample`: put an episode on a regular grid at a new fps.

Grid frame k is at time k / fps, for every grid time inside the recording. A recorded frame within
a hundredth of a frame period of a grid time (`frame_map.REGULAR_TOLERANCE`: lerobot stores float32
timestamps, 3.8 s reads back as 3.7999999 s) *is* that grid frame, its values copied exactly: a
regular dataset resampled to its own fps is the identity, to an integer fraction of it a
subsample. Between recorded frames (irregular recorder timestamps, or a rate that does not divide),
float features are linearly interpolated; integer, bool, string and camera features (RGB and
depth) take the nearest earlier frame, since interpolating a gripper command or an image would
invent values that never happened. Each grid frame stands for the recorded frames from its own up
to the next grid frame's (`pipelines/frame_map.py`): their events (`next.success` / `next.done`,
language events) land on it, so downsampling keeps the last frame's success on the last frame.
Downsampled video cameras are copied where their kept frames are keyframes (`datasets/video_copy.py`).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, Literal, override

import numpy as np

from shiftkit.datasets.dataclass_config import check_fields, option
from shiftkit.datasets.episode import Episode
from shiftkit.datasets.features import NUMERIC_DTYPES, Features
from shiftkit.pipelines.frame_map import REGULAR_TOLERANCE
from shiftkit.pipelines.stage import Reindex, ReindexStage, register_stage


@dataclass
class ResampleConfig:
    """Parameters of `resample`."""

    fps: int = option(rule="positive_int")
    """Output frame rate (frames per second)."""
    method: Literal["linear", "previous"] = "linear"
    """How float features are resampled between recorded frames: linear interpolation or the
    previous sample (camera features always take the previous frame)."""

    def __post_init__(self) -> None:
        check_fields(self)


def resampling_grid(timestamps: np.ndarray, fps_in: int, fps_out: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For recorded `timestamps` (from 0, increasing) at nominal `fps_in`: the grid times at `fps_out`
    inside the recording, per grid frame the last recorded frame at or before it (within the
    tolerance) and the fraction of the way to the next recorded frame (0 where a recorded frame is
    at the grid time)."""
    ts = np.asarray(timestamps, dtype=np.float64)
    tol = REGULAR_TOLERANCE / max(fps_in, fps_out)
    grid = np.arange(int(np.floor((ts[-1] + tol) * fps_out)) + 1) / fps_out
    prev = np.clip(np.searchsorted(ts, grid + tol, side="right") - 1, 0, len(ts) - 1)
    offset = grid - ts[prev]
    nxt = np.minimum(prev + 1, len(ts) - 1)
    span = ts[nxt] - ts[prev]
    exact = (np.abs(offset) <= tol) | (span <= 0)
    frac = np.where(exact, 0.0, offset / np.where(span > 0, span, 1.0))
    return grid, prev, np.clip(frac, 0.0, 1.0)


@register_stage
class Resample(ReindexStage):
    """Puts each episode on the regular grid `k / fps`, interpolating floats and holding the rest."""

    name = "resample"
    version = 3  # v3: grid with a tolerance (no lost last frame), cameras held, events moved by the frame map
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
    def kept_frames(self, features: Features) -> dict[str, str]:
        # Downsampling holds source frames, each once and in order (regular timestamps, as lerobot
        # writes them): copied as `subsample`'s are. Upsampling shows a frame twice: encoded.
        return self.carried_cameras(features) if self.config.fps <= self.context.fps else {}

    def _interpolates(self, dtype: np.dtype, frame_shape: tuple[int, ...]) -> bool:
        """Float scalars and vectors are interpolated; images, depth maps and the rest are held."""
        return self.config.method == "linear" and dtype.kind == "f" and len(frame_shape) <= 1

    @override
    def carried_features(self, features: Features) -> dict[str, str]:
        carried = super().carried_features(features)
        return {
            k: v
            for k, v in carried.items()
            if k == "task"
            or features[v]["dtype"] not in NUMERIC_DTYPES
            or not self._interpolates(np.dtype(features[v]["dtype"]), tuple(features[v]["shape"]))
        }

    @override
    def reindex(self, episode: Episode, rng: np.random.Generator) -> Iterable[Reindex]:
        ts = episode.frames["timestamp"].astype(np.float64)
        grid, prev, frac = resampling_grid(ts - ts[0], self.context.fps, self.config.fps)
        between = np.flatnonzero(frac > 0)
        frames: dict[str, np.ndarray] = {}
        for key, arr in episode.frames.items():
            if key == "timestamp" or not self._interpolates(arr.dtype, arr.shape[1:]):
                continue
            out = np.array(arr[prev])
            lo, hi = arr[prev[between]].astype(np.float64), arr[prev[between] + 1].astype(np.float64)
            w = frac[between].reshape((-1,) + (1,) * (arr.ndim - 1))
            out[between] = (lo + (hi - lo) * w).astype(arr.dtype)
            frames[key] = out
        yield Reindex(prev, grid, frames)

    @classmethod
    @override
    def identity_params(cls, features: Features, fps: int) -> dict[str, Any] | None:
        return {"fps": fps}
