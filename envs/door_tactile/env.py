"""The door + tactile finger gymnasium environment: physics (`physics`), STS (`shiftkit.envs.sts`),
marker-based wrench estimate (`shiftkit.envs.tactile_estimation`) and one task (`tasks`).

Action: Box(-1, 1, (7,)) at 10 Hz: a relative pose change in the end-effector (sensor) frame,
translation (1 = `MAX_TRANSLATION` m) and rotation vector (1 = `MAX_ROTATION` rad), applied to the
current pose to give the impedance controller's target (so a target inside an object becomes a
contact force of 550 N/m x depth), plus the STS mode (> 0.5 tactile, else visual: datasets label it
1 / 0, so a policy regressing the label switches where it crosses half way). With
`sensor_mode="visual"` or `"tactile"` (the fixed-mode baselines of thesis Fig. 4.13) the sensor stays
in that mode for the whole episode and the action has 6 dims, without `sts_mode` (`action_names`).
Observation (flat, `observation_names`): the sensor pose relative to the episode's initial pose
(position in the initial sensor frame, quaternion xyzw; thesis §4.4.1) now and one step before, the
STS wrench estimate from the marker image (pixels, unscaled; zero in visual mode, when the markers
are dark) and the mode; then privileged state: door angle and speed and the true contact wrench on
the pad (sensor frame). Images: `render_rgb("wrist")` (the wrist camera) and `sts_image()` (= `render_rgb("sts")`, the STS
image of the active mode), both `height` x `width`.
`info` every step: `is_success`, `qpos`, `qvel`, `door_angle`, `slammed`, `handle_contact`,
`sts_mode` (the active mode); `episode_extras()` sums up the modes driven since the reset.
"""

from __future__ import annotations

from typing import Any, override

import gymnasium as gym
import numpy as np

from shiftkit.envs.cameras import SceneRendering
from shiftkit.envs.door_tactile.physics import CAMERAS, DoorTactilePhysics
from shiftkit.envs.door_tactile.tasks import (
    SLAM_SPEED,
    START_OFFSET_ALONG_NORMAL,
    START_OFFSET_BACK,
    get_task,
    sample_start,
)
from shiftkit.envs.geometry import quat_xyzw, rotation_from_vector, rotation_z
from shiftkit.envs.sts import STSSensor
from shiftkit.envs.tactile_estimation import MarkerWrenchEstimator

MAX_TRANSLATION = 0.025
MAX_ROTATION = 0.15
POSE_NAMES = ("x", "y", "z", "qx", "qy", "qz", "qw")
OBSERVATION_NAMES: tuple[str, ...] = (
    *(f"rel_{n}" for n in POSE_NAMES),
    *(f"prev_rel_{n}" for n in POSE_NAMES),
    "sts_fx",
    "sts_fy",
    "sts_fz",
    "sts_tau_z",
    "sts_mode",
    "door_angle",
    "door_velocity",
    "contact_fx",
    "contact_fy",
    "contact_fz",
    "contact_tau_z",
)
OBS_DIM = len(OBSERVATION_NAMES)
STATE_INDICES = np.r_[0:19]
ENVIRONMENT_STATE_INDICES = np.r_[19:OBS_DIM]
ACTION_NAMES = ("dx", "dy", "dz", "drx", "dry", "drz", "sts_mode")
MODE_THRESHOLD = 0.5  # sts_mode above it selects the tactile mode (labels: 1 tactile, 0 visual)
SENSOR_MODES = ("policy", "visual", "tactile")  # "policy": the action's last dim drives the mode


class DoorTactileEnv(SceneRendering, gym.Env):
    """Franka Panda with an STS finger, a spring-hinged cabinet door; one task from `tasks.TASKS`."""

    metadata = {"render_modes": ["rgb_array", "depth_array"], "render_fps": 10}

    def __init__(
        self,
        task: str = "flat-handle-open",
        control_hz: int = 10,
        max_episode_seconds: float = 20.0,
        render_mode: str | None = None,
        camera: str = "wrist",
        width: int = 64,
        height: int = 48,
        render_quality: str = "fast",
        sensor_mode: str = "policy",
    ) -> None:
        self.task = get_task(task)
        if sensor_mode not in SENSOR_MODES:
            raise ValueError(f"sensor_mode must be one of {', '.join(SENSOR_MODES)}, got {sensor_mode!r}")
        if control_hz != 10:
            raise ValueError(f"control_hz must be 10 for door-tactile, got {control_hz}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']}, got {render_mode!r}")
        if camera not in CAMERAS:
            raise ValueError(f"unknown camera {camera!r}; known: {', '.join(CAMERAS)}")
        self.physics = DoorTactilePhysics(self.task.variant, control_hz)
        # the STS image has the cameras' size, so that datasets and policies see one image size
        self.sensor = STSSensor(self.physics.model, self.physics.pad_geom, self.physics.ee_site, "sts", width, height)
        self.estimator = MarkerWrenchEstimator()
        self.control_hz = control_hz
        self.max_episode_steps = int(round(max_episode_seconds * control_hz))
        self.render_mode, self.camera = render_mode, camera
        self.width, self.height, self.render_quality = width, height, render_quality
        self.observation_names = OBSERVATION_NAMES
        self.sensor_mode = sensor_mode
        self.fixed_mode = None if sensor_mode == "policy" else sensor_mode
        self.action_names = ACTION_NAMES if self.fixed_mode is None else ACTION_NAMES[:-1]
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (OBS_DIM,), dtype=np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (len(self.action_names),), dtype=np.float32)
        self._init_pos, self._init_rot = np.zeros(3), np.eye(3)
        self._prev_rel = np.zeros(7)
        self._estimate = np.zeros(4)
        self._tactile: np.ndarray | None = None
        self.slammed = False
        self._steps = 0
        self._tactile_steps, self._first_tactile_step, self._first_contact_step = 0, None, None

    # ----------------------------------------------------------------- gymnasium API
    @override
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        p = self.physics
        angle, offset, yaw = sample_start(self.task, self.np_random)
        pos, rot = p.grasp_pose(angle)
        nominal = pos + rot[:, 2] * START_OFFSET_ALONG_NORMAL + p.door_outward(angle) * START_OFFSET_BACK
        p.reset(nominal + offset, rotation_z(yaw) @ rot, angle)
        self.sensor.reset(int(self.np_random.integers(2**31)), mode=self.fixed_mode or "visual")
        self.estimator.reset(self.sensor.tactile_image(p.data))
        self._init_pos, self._init_rot = p.ee_pos(), p.ee_rot()
        self._prev_rel = self._relative_pose()
        self._estimate = np.zeros(4)
        self._tactile = None
        self.slammed = False
        self._steps = 0
        self._tactile_steps, self._first_tactile_step, self._first_contact_step = 0, None, None
        return self._observation(), self._info()

    @override
    def step(self, action):
        a = np.asarray(action, dtype=np.float64).reshape(-1)
        if a.shape != (len(self.action_names),) or not np.isfinite(a).all():
            raise ValueError(f"action must be {len(self.action_names)} finite numbers, got {action!r}")
        a = a.clip(-1.0, 1.0)
        pos, rot = self.physics.ee_pos(), self.physics.ee_rot()
        target_rot = rot @ rotation_from_vector(a[3:6] * MAX_ROTATION)
        mode = self.fixed_mode or ("tactile" if a[6] > MODE_THRESHOLD else "visual")
        return self.step_pose(pos + rot @ (a[:3] * MAX_TRANSLATION), target_rot, mode)

    def step_pose(self, target_pos: np.ndarray, target_rot: np.ndarray, mode: str = "tactile"):
        """One control period towards an absolute sensor pose target (base frame) under the impedance
        controller, e.g. replaying recorded poses; returns what `step` returns. A fixed
        `sensor_mode` overrides `mode` (as in `step_freedrive`)."""
        p = self.physics
        p.target_pos, p.target_rot = np.asarray(target_pos, float).copy(), np.asarray(target_rot, float).copy()
        return self._advance(lambda: p.simulate(p.n_substeps), mode)

    def step_freedrive(self, teacher, mode: str = "tactile"):
        """One control period with the arm in freedrive (zero stiffness, damping only) while
        `teacher(physics)` applies a wrench at the sensor every physics step (kinesthetic teaching);
        returns what `step` returns."""
        p = self.physics
        return self._advance(lambda: p.simulate(p.n_substeps, stiffness_scale=0.0, teacher=teacher), mode)

    def _advance(self, simulate, mode: str):
        mode = self.fixed_mode or mode
        self._prev_rel = self._relative_pose()
        self.sensor.set_mode(mode)
        if mode == "tactile":
            self._tactile_steps += 1
            if self._first_tactile_step is None:
                self._first_tactile_step = self._steps
        free_closing = simulate()
        self.slammed = self.slammed or free_closing > SLAM_SPEED
        self._steps += 1
        if self._first_contact_step is None and self.physics.handle_contact():
            self._first_contact_step = self._steps  # the first observation that shows contact
        if mode == "tactile":
            self._tactile = self.sensor.tactile_image(self.physics.data)
            self._estimate = self.estimator.update(self._tactile)
        else:
            self._tactile = None
            self._estimate = np.zeros(4)
        info = self._info()
        truncated = self._steps >= self.max_episode_steps
        return self._observation(), float(info["is_success"]), False, truncated, info

    @override
    def close(self) -> None:
        super().close()
        self.sensor.close()

    # ----------------------------------------------------------------- extras
    def _relative_pose(self) -> np.ndarray:
        p = self.physics
        rel_pos = self._init_rot.T @ (p.ee_pos() - self._init_pos)
        return np.concatenate([rel_pos, quat_xyzw(self._init_rot.T @ p.ee_rot())])

    def _observation(self) -> np.ndarray:
        p = self.physics
        return np.concatenate(
            [
                self._relative_pose(),
                self._prev_rel,
                self._estimate,
                [1.0 if self.sensor.mode == "tactile" else 0.0],
                [p.door_angle(), p.door_velocity()],
                self.sensor.contact_wrench(p.data),
            ]
        ).astype(np.float32)

    def _info(self) -> dict[str, Any]:
        p, d = self.physics, self.physics.data
        return {
            "is_success": bool(self.task.succeeded(p.door_angle(), self.slammed)),
            "qpos": d.qpos.copy(),
            "qvel": d.qvel.copy(),
            "door_angle": p.door_angle(),
            "slammed": self.slammed,
            "handle_contact": p.handle_contact(),
            "sts_mode": self.sensor.mode,
        }

    def episode_extras(self) -> dict[str, Any]:
        """The STS modes driven since the reset (what `shiftkit eval` records per episode): the
        sensor-mode setting, the steps run in tactile mode and the first of them, and the first
        observation touching the handle (None: never). `first_tactile_step - first_contact_step`
        is a policy's switch timing, in the convention of the labels' `sts_mode_switch_minus_contact`."""
        return {
            "sensor_mode": self.sensor_mode,
            "tactile_steps": self._tactile_steps,
            "first_tactile_step": self._first_tactile_step,
            "first_contact_step": self._first_contact_step,
        }

    def ee_pose(self) -> np.ndarray:
        """Sensor pose in the base frame: position and quaternion xyzw (the raw format's `ee_pose`)."""
        return np.concatenate([self.physics.ee_pos(), quat_xyzw(self.physics.ee_rot())])

    def sts_image(self) -> np.ndarray:
        """The STS image of the active mode (the marker image of the last step in tactile mode)."""
        if self.sensor.mode == "tactile":
            if self._tactile is None:
                self._tactile = self.sensor.tactile_image(self.physics.data)
            return self._tactile
        return self.sensor.visual_image(self.physics.data)

    def render_rgb(self, camera: str | None = None) -> np.ndarray:
        """RGB of a camera; "sts" gives the STS image of the active mode (what datasets record)."""
        if (camera or self.camera) == "sts":
            return self.sts_image()
        return super().render_rgb(camera)

    def set_sim_state(self, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        """Restore a recorded simulator state; returns the observation at that state (poses relative
        to the episode's initial pose as set by the last reset)."""
        self.physics.set_state(np.asarray(qpos), np.asarray(qvel))
        return self._observation()
