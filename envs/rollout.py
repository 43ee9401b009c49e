"""The recorded episode every family's expert rollout returns (what `shiftkit collect` writes)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class Rollout:
    """One recorded episode: arrays indexed by frame (frame t holds the observation before action t)."""

    observations: np.ndarray
    """(T, obs_dim) flat observations, split into dataset features by the family's layout."""
    actions: np.ndarray
    success: np.ndarray
    """(T,) bool: the env's held success after action t (LeRobot `next.success`)."""
    qpos: np.ndarray
    qvel: np.ndarray
    segments: list[dict[str, Any]] = field(default_factory=list)
    """Play episodes: task, start, end (exclusive), success per segment."""
    images: dict[str, np.ndarray] = field(default_factory=dict)
    """Camera (or sensor image) name -> (T, H, W, 3) uint8."""
    depth: dict[str, np.ndarray] = field(default_factory=dict)
    """Camera name -> (T, H, W) float32 metres."""
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    """Further per-frame arrays the family records (raw-format names, e.g. a tactile wrench)."""
    meta: dict[str, Any] = field(default_factory=dict)
    """Further episode metadata (e.g. operator labels, per-episode camera poses)."""

    @property
    def succeeded(self) -> bool:
        return bool(self.success.any())
