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
        """Whether success held after any action."""
        return bool(self.success.any())


class RolloutRecorder:
    """Collects one episode's frames: `frame(obs, info)` before each action (observation, simulator
    state, camera images), `actions` / `success` appended after it; `done()` gives the `Rollout`
    (frames beyond the last action dropped). `sensors` name extra images recorded every frame
    (e.g. a tactile sensor's), each from a callable or passed to `frame`."""

    def __init__(self, env: Any, cameras: tuple[str, ...], depth: bool, sensors: dict[str, Any] | None = None) -> None:
        self.sensors = dict(sensors or {})
        self.env, self.cameras = env, tuple(c for c in cameras if c not in self.sensors)
        self.depth_cameras = self.cameras if depth else ()
        self.obs: list[np.ndarray] = []
        self.actions: list[np.ndarray] = []
        self.success: list[bool] = []
        self.qpos: list[np.ndarray] = []
        self.qvel: list[np.ndarray] = []
        self.images: dict[str, list[np.ndarray]] = {c: [] for c in (*self.cameras, *self.sensors)}
        self.depth: dict[str, list[np.ndarray]] = {c: [] for c in self.depth_cameras}

    def frame(self, obs: np.ndarray, info: dict[str, Any], **sensor_images: np.ndarray) -> None:
        """Record the frame before an action: observation, qpos/qvel, camera images (and depth), sensor
        images (from their callables, or given here)."""
        self.obs.append(obs)
        self.qpos.append(info["qpos"])
        self.qvel.append(info["qvel"])
        for cam in self.cameras:
            self.images[cam].append(self.env.render_rgb(cam))
        for cam in self.depth_cameras:
            self.depth[cam].append(self.env.render_depth(cam))
        for name, read in self.sensors.items():
            self.images[name].append(sensor_images[name] if name in sensor_images else read())

    def done(self, **extra: Any) -> Rollout:
        """The recorded `Rollout`, frames beyond the last action dropped (`extra`: further fields)."""
        n = len(self.actions)
        return Rollout(
            observations=np.array(self.obs[:n], dtype=np.float32),
            actions=np.array(self.actions, dtype=np.float32),
            success=np.array(self.success, dtype=bool),
            qpos=np.array(self.qpos[:n]),
            qvel=np.array(self.qvel[:n]),
            images={k: np.array(v[:n], dtype=np.uint8) for k, v in self.images.items()},
            depth={k: np.array(v[:n], dtype=np.float32) for k, v in self.depth.items()},
            **extra,
        )


def expert_rollout(
    env: Any,
    seed: int,
    make_expert: Any,
    cameras: tuple[str, ...] = (),
    depth: bool = False,
    extra_steps: int = 0,
    sensors: dict[str, Any] | None = None,
) -> Rollout:
    """Run `make_expert(env).act()` from `reset(seed=seed)` until success has held (plus
    `extra_steps`) or the episode is truncated. Frame t holds the observation before action t and
    `success[t]` the env's `is_success` after it (LeRobot's `next.success`); `sensors` as for
    `RolloutRecorder`."""
    rec = RolloutRecorder(env, cameras, depth, sensors)
    obs, info = env.reset(seed=seed)
    expert = make_expert(env)
    rec.frame(obs, info)
    left = None
    while True:
        action = expert.act()
        obs, _, _, truncated, info = env.step(action)
        rec.actions.append(action)
        rec.success.append(info["is_success"])
        if info["is_success"] and left is None:
            left = extra_steps
        if truncated or (left is not None and left <= 0):
            break
        if left is not None:
            left -= 1
        rec.frame(obs, info)
    return rec.done()
