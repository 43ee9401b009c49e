"""The multiview gymnasium environment: physics (`physics`) + one task (`tasks`).

Observation: proprioception (TCP pose, fingers now, t-1, t-2) then object state, all in the base
frame (`observation_names`). Action: Box(-1, 1): TCP velocity in the base frame (1 = 25 cm/s), for
6-DOF tasks also the angular velocity (1 = 1 rad/s), and the gripper (> 0 opens, < 0 closes).
Control at 10 Hz. `view="multiview"` samples the base pose per episode (`physics.SAMPLER`, from the
episode seed); `view="fixed"` uses the centre pose; `options={"base_pose": BasePose}` forces one,
`options={"base_yaw": yaw}` an aimed pose at that yaw with the x, y noise (yaw sweeps).
Reward 1.0 while success holds; episodes are truncated after `max_episode_seconds`.
`info` every step: `is_success`, `success_now`, `qpos`, `qvel`, `base_pose`.
"""

from __future__ import annotations

from typing import Any, override

import gymnasium as gym
import numpy as np

from shiftkit.envs.base_pose import CAMERA_NAME, SAMPLER, BasePose
from shiftkit.envs.cameras import SceneRendering, camera_extrinsics, camera_intrinsics
from shiftkit.envs.multiview.physics import CONTROL_HZ, MultiviewPhysics
from shiftkit.envs.multiview.tasks import STATE_NAMES, get_task

VIEWS = ("multiview", "fixed")


class MultiviewEnv(SceneRendering, gym.Env):
    """Panda on a mobile base with a base-mounted RGB-D camera; one task from `tasks.TASKS`."""

    metadata = {"render_modes": ["rgb_array", "depth_array"], "render_fps": CONTROL_HZ}

    def __init__(
        self,
        task: str = "lift",
        view: str = "multiview",
        control_hz: int = CONTROL_HZ,
        render_mode: str | None = None,
        camera: str = CAMERA_NAME,
        width: int = 64,
        height: int = 48,
        render_quality: str = "fast",
        max_episode_seconds: float | None = None,
    ) -> None:
        self.task = get_task(task)
        if view not in VIEWS:
            raise ValueError(f"view must be one of {VIEWS}, got {view!r}")
        if control_hz != CONTROL_HZ:
            raise ValueError(f"control_hz must be {CONTROL_HZ}, got {control_hz}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']}, got {render_mode!r}")
        if camera != CAMERA_NAME:
            raise ValueError(f"unknown camera {camera!r}; known: {CAMERA_NAME}")
        self.view = view
        self.physics = MultiviewPhysics(self.task.model_id, self.task.name, self.task.objects)
        self.control_hz = control_hz
        self.max_episode_steps = int(round((max_episode_seconds or self.task.max_episode_seconds) * control_hz))
        self.render_mode, self.camera = render_mode, camera
        self.width, self.height, self.render_quality = width, height, render_quality
        self.observation_names = STATE_NAMES + self.task.environment_names
        self.action_names = self.task.action_names
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (len(self.observation_names),), dtype=np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (len(self.action_names),), dtype=np.float32)
        self._held = 0
        self._steps = 0

    # ----------------------------------------------------------------- gymnasium API
    @override
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        rng = self.np_random
        options = options or {}
        forced = options.get("base_pose")
        if forced is not None:
            pose = forced if isinstance(forced, BasePose) else BasePose.from_dict(forced)
        elif options.get("base_yaw") is not None:
            pose = SAMPLER.sample_at(float(options["base_yaw"]), rng)
        elif self.view == "multiview":
            pose = SAMPLER.sample(rng)
        else:
            pose = SAMPLER.centre_pose()
        self.physics.reset(pose, lambda p: self.task.reset(p, rng))
        self._held = 0
        self._steps = 0
        now = self.task.predicate(self.physics)
        return self._observation(), self._info(False, now)

    @override
    def step(self, action):
        a = np.asarray(action, dtype=np.float64).reshape(-1)
        if a.shape != self.action_space.shape or not np.isfinite(a).all():
            raise ValueError(f"action must be {self.action_space.shape[0]} finite numbers, got {action!r}")
        a = a.clip(-1.0, 1.0)
        rotate = a[3:6] if self.task.rotation else np.zeros(3)
        self.physics.step(a[:3], rotate, float(a[-1]))
        self._steps += 1
        now = self.task.predicate(self.physics)
        self._held = self._held + 1 if now else 0
        success = self._held >= self.task.hold_steps
        truncated = self._steps >= self.max_episode_steps
        return self._observation(), float(success), False, truncated, self._info(success, now)

    # ----------------------------------------------------------------- extras
    def _observation(self) -> np.ndarray:
        p = self.physics
        return np.concatenate([p.proprioception(), p.object_state()]).astype(np.float32)

    def _info(self, success: bool, now: bool) -> dict[str, Any]:
        d = self.physics.data
        return {
            "is_success": bool(success),
            "success_now": bool(now),
            "qpos": d.qpos.copy(),
            "qvel": d.qvel.copy(),
            "base_pose": self.physics.base_pose.as_dict(),
        }

    @property
    def base_pose(self) -> BasePose:
        """The robot base's pose in the world for this episode."""
        return self.physics.base_pose

    def camera_metadata(self) -> dict[str, dict[str, Any]]:
        """The camera-metadata contract entry for the current episode: intrinsics, extrinsics in the
        base frame (the MuJoCo frame here) and the base pose in the world."""
        m = self.physics.model
        return {
            CAMERA_NAME: {
                "intrinsics": camera_intrinsics(m, CAMERA_NAME, self.width, self.height),
                "extrinsics": {"frame": "base", **camera_extrinsics(m, self.physics.data, CAMERA_NAME)},
                "base_pose": self.physics.base_pose.as_dict(),
            }
        }

    def set_base_pose(self, pose: BasePose) -> None:
        """Move the base (the world around it) to `pose`; call `set_sim_state` after it."""
        self.physics.set_base_pose(pose)

    def set_sim_state(self, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        """Restore a simulator state recorded at the current base pose; returns the observation."""
        self.physics.set_state(np.asarray(qpos), np.asarray(qvel))
        self._held = 0
        return self._observation()
