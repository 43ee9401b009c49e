"""Shared replay buffer of all interaction (every intention writes to it, every intention samples it).

A circular buffer of (s, a, s') rows in insertion order, with a flag marking the last transition of each
episode. There are no done flags for learning: VPACE bootstraps through time limits (thesis B.2.6). For
n-step returns a sample also carries the states s_t ... s_{t+n-1} (rewards are computed from states by
the reward model at update time) and the state s_{t+k} to bootstrap from, where k <= n stops at the end
of the episode or at the newest row.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass
class ReplaySample:
    """A batch of transitions (numpy, float32)."""

    obs: np.ndarray  # (B, obs_dim) s_t
    act: np.ndarray  # (B, act_dim) a_t
    next_obs: np.ndarray  # (B, obs_dim) s_{t+k}, the state to bootstrap from
    reward_obs: np.ndarray  # (B, n, obs_dim) s_t .. s_{t+n-1}; rows past `steps` repeat the last valid one
    steps: np.ndarray  # (B,) k, the number of rewarded steps (1 <= k <= n)

    def extended(self, obs: np.ndarray, act: np.ndarray, next_obs: np.ndarray) -> ReplaySample:
        """This sample with one-step transitions (rows, ·) appended (LfGP's expert rows)."""
        reward_obs = np.repeat(obs[:, None], self.reward_obs.shape[1], axis=1)
        return ReplaySample(
            np.concatenate([self.obs, obs]),
            np.concatenate([self.act, act]),
            np.concatenate([self.next_obs, next_obs]),
            np.concatenate([self.reward_obs, reward_obs]),
            np.concatenate([self.steps, np.ones(len(obs), self.steps.dtype)]),
        )


class ReplayBuffer:
    """Fixed-capacity circular buffer; the oldest rows are overwritten first."""

    def __init__(self, capacity: int, obs_dim: int, act_dim: int):
        self.capacity = capacity
        self.obs = np.zeros((capacity, obs_dim), np.float32)
        self.act = np.zeros((capacity, act_dim), np.float32)
        self.next_obs = np.zeros((capacity, obs_dim), np.float32)
        self.episode_end = np.zeros(capacity, bool)
        self.pointer = 0  # next row to write
        self.size = 0

    def __len__(self) -> int:
        return self.size

    def add(self, obs: np.ndarray, act: np.ndarray, next_obs: np.ndarray, episode_end: bool) -> None:
        """Writes one transition, overwriting the oldest once the buffer is full."""
        i = self.pointer
        self.obs[i], self.act[i], self.next_obs[i], self.episode_end[i] = obs, act, next_obs, episode_end
        self.pointer = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, rng: np.random.Generator, batch_size: int, n_step: int = 1) -> ReplaySample:
        """A uniform batch of `batch_size` transitions, with up to `n_step` rewarded steps each (fewer where the episode ends)."""
        idx = rng.integers(0, self.size, batch_size)
        rows = np.empty((batch_size, n_step), np.int64)
        rows[:, 0] = idx
        steps = np.ones(batch_size, np.int64)
        alive = np.ones(batch_size, bool)
        for k in range(1, n_step):
            prev = rows[:, k - 1]
            nxt = (prev + 1) % self.capacity
            # The episode continues in the next row unless it ended here or that row is not written yet.
            alive &= ~self.episode_end[prev] & (nxt != self.pointer) & (nxt < self.size)
            rows[:, k] = np.where(alive, nxt, prev)
            steps += alive
        last = rows[np.arange(batch_size), steps - 1]
        return ReplaySample(self.obs[idx], self.act[idx], self.next_obs[last], self.obs[rows], steps)

    _ARRAYS = ("obs", "act", "next_obs", "episode_end")

    def state_dict(self) -> dict:
        """The written rows and the write position, for a checkpoint."""
        # Only the written rows (a checkpoint early in training stays small), as tensors for torch.save.
        return {k: torch.from_numpy(getattr(self, k)[: self.size].copy()) for k in self._ARRAYS} | {
            "pointer": self.pointer,
            "size": self.size,
            "capacity": self.capacity,
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore rows as stored; into a different capacity (a resumed run made longer or shorter) the
        rows are laid out oldest first, keeping the newest that fit."""
        size, pointer = int(state["size"]), int(state["pointer"])
        rows = np.arange(size)
        if int(state["capacity"]) != self.capacity:
            rows = np.roll(rows, -pointer)[-self.capacity :] if size else rows
            pointer = len(rows) % self.capacity
        for k in self._ARRAYS:
            getattr(self, k)[: len(rows)] = state[k].numpy()[rows]
        self.pointer, self.size = pointer, len(rows)
