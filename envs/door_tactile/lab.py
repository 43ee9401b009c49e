"""The door-tactile arm as a lab's robot: it executes commanded sensor poses through its impedance
controller, as a real arm executes a plan that shiftkit wrote for it, and returns what the lab's
logger records (docs/real_robot.md). Two plans exist: calibration pushes against the door's handle
or knob (`execute_pushes`) and force-matched replay targets of a demonstration (`replay_targets`,
which the `force_match` stage also runs in the simulator directly).

Poses are position + quaternion x, y, z, w (the raw format's `ee_pose` order).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from shiftkit.envs.controllers import rotation_vector
from shiftkit.envs.door_tactile.env import (
    ENVIRONMENT_STATE_INDICES,
    STATE_INDICES,
    DoorTactileEnv,
    rotation_from_vector,
)
from shiftkit.envs.door_tactile.experts import relative_action
from shiftkit.envs.geometry import matrix_to_quat_xyzw, quat_xyzw_to_matrix

STS_VISUAL = "observation.images.sts_visual"
STS_TACTILE = "observation.images.sts_tactile"
STS_IMAGE = "observation.images.sts"
CAMERA_PREFIX = "observation.images."


# ----------------------------------------------------------------------------- calibration pushes
PUSH_KINDS = ("normal", "shear_x", "shear_y", "torque")


@dataclass
class PushConfig:
    """The autonomous calibration procedure (thesis §4.4.1): pushes of the sensor pad against a
    fixed object through the impedance controller, sampled once settled after every step."""

    step: float = 0.001
    """Normal step of the commanded pose (m)."""
    travel: float = 0.035
    """Normal travel of a push (m)."""
    start_gap: tuple[float, float] = (0.001, 0.003)
    """Range of the distance between pad and object at a push's start (m)."""
    jitter: float = 0.001
    """Lateral start perturbation (m, uniform +-) that makes pushes differ."""
    press: tuple[float, float] = (0.004, 0.015)
    """Range of the commanded depth past first contact at which shear / torque moves start (m)."""
    shear: float = 0.01
    """Lateral travel of a shear move (m), in steps of `step`."""
    rotation: float = 1.0
    """Rotation of a torque move about the pad normal (rad)."""
    rotation_step: float = 0.05
    """Rotation per step of a torque move (rad)."""
    settle_periods: int = 3
    """Control periods waited after each step before sampling."""
    contact_reading: float = 0.5
    """Rise of the raw normal reading over its start value that counts as contact."""
    contact_depth: float = 0.0035
    """Depth past the object's face at which a plan (`plan_push`) expects the reading to have risen
    by `contact_reading` (m; the simulated STS behind the impedance controller: about 3.5 mm)."""


def pose_error(target_pos: np.ndarray, target_rot: np.ndarray, pos: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """e = x_d - x in the sensor frame of the measured pose (rot): ex, ey, ez (m), erz (rad)."""
    return np.append(rot.T @ (target_pos - pos), rotation_vector(rot.T @ target_rot)[2])


def simulate_push(
    env: DoorTactileEnv, kind: str, seed: int, config: PushConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One push of the env's tactile sensor against its calibration object (the door-tactile knob or
    handle, door shut against its stop), reacting to contact as the thesis' robot does (shear and
    torque moves start a drawn depth past the first contact). `env` is a door-tactile environment
    (`physics` with `grasp_pose`, `reset`, `simulate`, the impedance targets; `sensor` with the raw
    reading). Returns per settled sample the sensor-frame e = x_d - x (n, 4), the raw reading (n, 4)
    and whether it was taken during the shear / torque move (n,)."""
    if kind not in PUSH_KINDS:
        raise ValueError(f"unknown push kind {kind!r}; known: {', '.join(PUSH_KINDS)}")
    rng = np.random.default_rng([seed, PUSH_KINDS.index(kind)])
    env.reset(seed=int(rng.integers(2**31)))  # seeds the sensor's noise
    p, sensor = env.physics, env.sensor
    contact_pos, rot = p.grasp_pose(0.0)
    normal, lateral = rot[:, 2], rot[:, :2]
    start = contact_pos - normal * rng.uniform(*config.start_gap) + lateral @ rng.uniform(-1, 1, 2) * config.jitter
    p.reset(start, rot, 0.0)
    samples_e, samples_f, moving = [], [], []

    def sample(move: bool = False) -> np.ndarray:
        p.simulate(p.n_substeps * config.settle_periods)
        f = sensor.raw_wrench(sensor.contact_wrench(p.data))
        samples_e.append(pose_error(p.target_pos, p.target_rot, p.ee_pos(), p.ee_rot()))
        samples_f.append(f)
        moving.append(move)
        return f

    rest = sample()[2]  # the normal axis
    steps = int(round(config.travel / config.step))
    press_after = None
    for k in range(1, steps + 1):
        p.target_pos = start + normal * config.step * k
        reading = sample()[2]
        if kind == "normal":
            continue
        if press_after is None and reading - rest > config.contact_reading:
            press_after = int(round(rng.uniform(*config.press) / config.step))
        if press_after is not None:
            press_after -= 1
            if press_after <= 0:
                break
    if kind in ("shear_x", "shear_y"):
        direction = lateral[:, 0 if kind == "shear_x" else 1] * rng.choice([-1.0, 1.0])
        base = p.target_pos.copy()
        for k in range(1, int(round(config.shear / config.step)) + 1):
            p.target_pos = base + direction * config.step * k
            sample(True)
    elif kind == "torque":
        sign = rng.choice([-1.0, 1.0])
        base = p.target_rot.copy()
        for k in range(1, int(round(config.rotation / config.rotation_step)) + 1):
            p.target_rot = base @ rotation_from_vector(np.array([0.0, 0.0, sign * config.rotation_step * k]))
            sample(True)
    return np.array(samples_e), np.array(samples_f), np.array(moving, bool)


def execute_pushes(env: DoorTactileEnv, seed: int, commanded: np.ndarray) -> dict[str, np.ndarray]:
    """Execute one calibration push against the handle / knob (door shut against its stop): the
    controller holds commanded pose t (T, 7), given in the sensor frame of the contact pose (pad
    just touching the face, normal +z into it), for one control period each, from the first
    pose at rest. Returns, per period, what the logger records at its end: `action` (the commanded
    pose in effect), `ee_pose` (the measured sensor pose, contact frame), `wrench_raw` (the STS's
    raw reading) and the simulator state. `seed` seeds the sensor's noise."""
    commanded = np.asarray(commanded, dtype=np.float64)
    env.reset(seed=seed)
    p, sensor = env.physics, env.sensor
    start, rot = p.grasp_pose(0.0)
    first = quat_xyzw_to_matrix(commanded[:1, 3:7])[0]
    p.reset(start + rot @ commanded[0, :3], rot @ first, 0.0)
    targets = quat_xyzw_to_matrix(commanded[:, 3:7])
    rows: dict[str, list[np.ndarray]] = {"ee_pose": [], "wrench_raw": [], "sim_qpos": [], "sim_qvel": []}
    for pose, target_rot in zip(commanded, targets, strict=True):
        p.target_pos, p.target_rot = start + rot @ pose[:3], rot @ target_rot
        p.simulate(p.n_substeps)
        measured_rot = rot.T @ p.ee_rot()
        rows["ee_pose"].append(np.concatenate([rot.T @ (p.ee_pos() - start), matrix_to_quat_xyzw(measured_rot)]))
        rows["wrench_raw"].append(sensor.raw_wrench(sensor.contact_wrench(p.data)))
        rows["sim_qpos"].append(p.data.qpos.copy())
        rows["sim_qvel"].append(p.data.qvel.copy())
    return {"action": commanded, **{k: np.array(v) for k, v in rows.items()}}


# ----------------------------------------------------------------------------- replay targets
@dataclass
class Replay:
    """One replay: frame t holds the state before action t (the last target's state is not kept)."""

    frames: dict[str, np.ndarray]
    """Per-frame arrays by LeRobot feature name."""
    success: bool
    first_contact_step: int | None


def replay_targets(
    env: DoorTactileEnv,
    seed: int,
    targets: np.ndarray,
    modes: np.ndarray,
    warmup_steps: int,
    cameras: tuple[str, ...] = (),
    sts_images: Literal["none", "active", "both"] = "none",
    hold_steps: int = 0,
) -> Replay:
    """Replay T + 1 sensor target poses through the env's impedance controller, as the family's
    position replay does: reset with the demonstration's seed, set the controller's target to the
    first pose for `warmup_steps` (the steps the demonstration spent before recording started),
    then to target t + 1 at step t (the mode from the (T,) `modes`), then hold the last target for
    `hold_steps` more steps. Records, per step, the env's observation split into state /
    environment state, the simulator state, the reached pose, the true and raw contact wrench, the
    requested cameras and the STS image of the active mode (`sts_images` "active") or both STS
    images ("both"); `action` is the env action (the target's relative pose from the pose reached,
    clipped to the action range, plus the mode: what a policy trained on the replay outputs) and
    `target` the commanded pose + mode (what a robot is sent)."""
    targets = np.asarray(targets, dtype=np.float64)
    rots = quat_xyzw_to_matrix(targets[:, 3:7])
    rows: dict[str, list[np.ndarray]] = {}
    actions, sent, success, contact = [], [], [], None

    def record(obs: np.ndarray, info: dict[str, Any]) -> None:
        data = env.physics.data
        wrench = env.sensor.contact_wrench(data)
        values = {
            "observation.state": obs[STATE_INDICES],
            "observation.environment_state": obs[ENVIRONMENT_STATE_INDICES],
            "sim.qpos": info["qpos"],
            "sim.qvel": info["qvel"],
            "observation.ee_pose": env.ee_pose(),
            "contact_wrench": wrench,
            "observation.wrench": env.sensor.raw_wrench(wrench),
            **{CAMERA_PREFIX + c: env.render_rgb(c) for c in cameras},
        }
        if sts_images == "both":
            values[STS_VISUAL] = env.sensor.visual_image(data)
            values[STS_TACTILE] = env.sensor.tactile_image(data)
        elif sts_images == "active":
            values[STS_IMAGE] = env.sts_image()
        for key, value in values.items():
            rows.setdefault(key, []).append(np.asarray(value))

    obs, info = env.reset(seed=seed)
    for _ in range(warmup_steps):
        obs, _, _, _, info = env.step_pose(targets[0, :3], rots[0], "visual")
    n = len(targets) - 1
    for t in range(n + hold_steps):
        if contact is None and info["handle_contact"]:
            contact = t
        record(obs, info)
        k, tactile = min(t + 1, n), bool(modes[min(t, n - 1)] > 0.5)
        p = env.physics
        actions.append(np.append(relative_action(p.ee_pos(), p.ee_rot(), targets[k, :3], rots[k]), float(tactile)))
        sent.append(np.append(targets[k], float(tactile)))
        obs, _, _, truncated, info = env.step_pose(targets[k, :3], rots[k], "tactile" if tactile else "visual")
        success.append(bool(info["is_success"]))
        if truncated:
            break
    frames = {k: np.stack(v) for k, v in rows.items()}
    frames["action"] = np.array(actions)
    frames["target"] = np.array(sent)
    frames["next.success"] = np.array(success)
    return Replay(frames, bool(any(success)), contact)
