"""A growing in-memory set of frames (feature -> array), sampled in batches: FIRE's expert set D_E and
policy set D_pi (thesis Algorithm 2), which gain frames after every episode."""

from __future__ import annotations

import numpy as np
import torch


class FrameBuffer:
    """Frames of fixed features; `add` appends, `sample` draws a batch with replacement."""

    def __init__(self, keys: list[str]) -> None:
        self.keys = list(keys)
        self._parts: dict[str, list[np.ndarray]] = {k: [] for k in self.keys}
        self._arrays: dict[str, np.ndarray] | None = None
        self._len = 0

    def __len__(self) -> int:
        return self._len

    def add(self, frames: dict[str, np.ndarray]) -> None:
        """Append frames (every key, same first-axis length)."""
        n = len(frames[self.keys[0]])
        if n == 0:
            return
        for k in self.keys:
            if len(frames[k]) != n:
                raise ValueError(f"frame count of {k!r} ({len(frames[k])}) differs from {n}")
            self._parts[k].append(np.asarray(frames[k]))
        self._arrays = None
        self._len += n

    def arrays(self) -> dict[str, np.ndarray]:
        """Every frame, one array per key (concatenated once per change)."""
        if self._arrays is None:
            self._arrays = {k: np.concatenate(v) for k, v in self._parts.items()}
            self._parts = {k: [a] for k, a in self._arrays.items()}
        return self._arrays

    def gather(self, rows: np.ndarray, device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
        """The frames at `rows` as tensors."""
        return {k: torch.from_numpy(v[rows]).to(device) for k, v in self.arrays().items()}

    def sample(self, batch_size: int, rng: np.random.Generator, device: torch.device | str = "cpu"):
        """`batch_size` frames drawn uniformly with replacement."""
        return self.gather(rng.integers(0, self._len, batch_size), device)

    def state_dict(self) -> dict[str, np.ndarray]:
        """The frames held, one array per key (empty when none), for a checkpoint."""
        return dict(self.arrays()) if self._len else {}

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        """Replaces the frames by what `state_dict` returned."""
        self._parts = {k: [] for k in self.keys}
        self._arrays, self._len = None, 0
        if state:
            self.add(state)
