"""The Panda play gymnasium environment: physics (`physics`) + one task (`tasks`).

Observation: the 59-dim reference vector, names in `observation_names` (docs/panda_play.md).
Action: Box(-1, 1, (4,)): delta TCP position (1 = 1 cm per step at 20 Hz, 4 cm at 5 Hz) and the
gripper (> 0 opens, < 0 closes, as thesis appendix A.1 and docs/panda_play.md; the published VPACE data use
the opposite sign, see `vpace_compat`). Reward: 1.0 on steps where the task counts as solved,
else 0. Episodes never terminate on their own; they are truncated after `max_episode_seconds`
(18 s = 360 steps at 20 Hz).
`info` every step: `is_success`, `success_now` (instantaneous predicate), `qpos`, `qvel`.
"""

from __future__ import annotations

from typing import Any, override

import gymnasium as gym
import numpy as np

from shiftkit.envs.cameras import SceneRendering
from shiftkit.envs.panda_play.physics import ACTION_NAMES, CAMERAS, OBS_DIM, OBSERVATION_NAMES, PandaPlayPhysics
from shiftkit.envs.panda_play.tasks import TASKS, HoldTimer, SceneFacts, get_task


class PandaPlayEnv(SceneRendering, gym.Env):
    """Franka Panda, tray, blue and green blocks; one task from `tasks.TASKS`."""

    metadata = {"render_modes": ["rgb_array", "depth_array"], "render_fps": 20}

    def __init__(
        self,
        task: str = "lift",
        control_hz: int = 20,
        max_episode_seconds: float = 18.0,
        render_mode: str | None = None,
        camera: str = "front",
        width: int = 64,
        height: int = 48,
        render_quality: str = "fast",
    ) -> None:
        self.task = get_task(task)
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']}, got {render_mode!r}")
        if camera not in CAMERAS:
            raise ValueError(f"unknown camera {camera!r}; known: {', '.join(CAMERAS)}")
        self.physics = PandaPlayPhysics(control_hz)
        self.control_hz = control_hz
        self.metadata = {**self.metadata, "render_fps": control_hz}
        self.max_episode_steps = int(round(max_episode_seconds * control_hz))
        self.render_mode = render_mode
        self.camera = camera
        self.width, self.height, self.render_quality = width, height, render_quality
        self.observation_names = OBSERVATION_NAMES
        self.action_names = ACTION_NAMES
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (OBS_DIM,), dtype=np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (4,), dtype=np.float32)
        self._timer = HoldTimer(self.task.hold_steps(control_hz))
        self._timers = {name: HoldTimer(t.hold_steps(control_hz)) for name, t in TASKS.items()}
        self._gripper_action = 0.0
        self._steps = 0

    # ----------------------------------------------------------------- gymnasium API
    @override
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        self.physics.reset(self.np_random, green_on_blue=self.task.green_on_blue)
        self._gripper_action = 0.0
        self._steps = 0
        self._timer.reset()
        for t in self._timers.values():
            t.reset()
        now = self.task.predicate(self.facts())
        return self.physics.observation(), self._info(False, now)

    @override
    def step(self, action):
        a = np.asarray(action, dtype=np.float64).reshape(-1)
        if a.shape != (4,) or not np.isfinite(a).all():
            raise ValueError(f"action must be 4 finite numbers, got {action!r}")
        self.physics.step(a)
        self._gripper_action = max(-1.0, min(1.0, float(a[3])))
        self._steps += 1
        now = self.task.predicate(self.facts())
        success = self._timer.update(now)
        truncated = self._steps >= self.max_episode_steps
        return self.physics.observation(), float(success), False, truncated, self._info(success, now)

    # ----------------------------------------------------------------- extras
    def _info(self, success: bool, now: bool) -> dict[str, Any]:
        d = self.physics.data
        return {"is_success": bool(success), "success_now": bool(now), "qpos": d.qpos.copy(), "qvel": d.qvel.copy()}

    def facts(self) -> SceneFacts:
        """Snapshot of the scene for the success predicates."""
        p = self.physics
        return SceneFacts(
            tcp=p.tcp_pos(),
            tcp_velocity=p.tcp_velocity(),
            blocks=p.data.xpos[p.block_body],
            block_velocity=p.block_linvels(),
            block_acceleration=p.block_acc.copy(),
            gripper_action=self._gripper_action,
            contacts=p.contacts(),
        )

    def task_successes(self) -> dict[str, bool]:
        """Held success of every registered task, updated with the current state (call once per
        step; used to label play episodes)."""
        f = self.facts()
        return {name: self._timers[name].update(t.predicate(f)) for name, t in TASKS.items()}

    def set_sim_state(self, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        """Restore a recorded simulator state; returns the observation at that state."""
        self.physics.set_state(np.asarray(qpos), np.asarray(qvel))
        return self.physics.observation()
