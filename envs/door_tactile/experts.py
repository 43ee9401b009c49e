"""Door + tactile finger experts: a scripted policy (env actions), the simulated kinesthetic teacher
(freedrive arm pushed by a scripted "human" hand) and plain position replay of a kinesthetic
episode (thesis §4.3).

All three approach the handle from the hinge side, press the STS pad against it and drag it along
the door's arc ("press and pull", thesis fig. 4.2b): the door moves by friction at the pad, so
what matters is the pressing force.

* `rollout` (the family's "scripted" expert) commands impedance targets inside the handle
  (`PRESS_ACTION`) and along the swing (`DRAG_ACTION`): 550 N/m x depth of pressing and pulling.
* `kinesthetic_rollout` ("kinesthetic"): the arm in freedrive (zero stiffness, damping only); a hand
  applies a wrench at the finger: spring-damper towards a scripted pose plus a pressing force
  `HUMAN_PRESS` along the pad normal, the door angle following a schedule at a human pace.
  Recording starts once the sensor has moved 0.5 mm and holds x_raw (`ee_pose`), F~_raw
  (`wrench_raw`), the simulator state and the wrist / STS images; the operator's mode-switch press
  lands near the true first contact with seeded jitter (`meta`).
* `replay_positions`: replays an episode's x_raw through the impedance controller (no force
  matching): the pressing force of the demonstration is lost.
"""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np

from shiftkit.envs.door_tactile.env import MAX_ROTATION, MAX_TRANSLATION, DoorTactileEnv
from shiftkit.envs.door_tactile.physics import HANDLE_RADIUS, DoorTactilePhysics
from shiftkit.envs.door_tactile.tasks import CLOSED_ANGLE, OPEN_ANGLE
from shiftkit.envs.geometry import quat_xyzw_to_matrix, rotation_vector
from shiftkit.envs.rollout import Rollout, RolloutRecorder, expert_rollout

PRE_CONTACT = 0.012  # m before the handle face at the end of the approach
PRESS_ACTION = 0.9  # scripted press: targets 2.25 cm inside the handle (about 12 N)
SCRIPTED_PRESS_STEPS = 3
DRAG_ACTION = {"flat": 0.7, "knob": 0.6}  # scripted drag: 1.75 / 1.5 cm along the swing (9.6 / 8.3 N)
HUMAN_PRESS = {"flat": 12.0, "knob": 15.0}  # N: how hard the teacher presses the pad on the handle
HUMAN_STIFFNESS, HUMAN_DAMPING = 400.0, 50.0  # N/m, Ns/m: the hand guiding the finger
HUMAN_ROT_STIFFNESS, HUMAN_ROT_DAMPING = 6.0, 0.5  # Nm/rad, Nms/rad
HUMAN_MAX_FORCE = 30.0  # N: approach
HUMAN_MAX_DRAG = 9.0  # N: in the pad plane while pressing (a person feels the finger start to slip)
HUMAN_PACE = 0.3  # rad/s: how fast the teacher swings the door
HUMAN_PACE_GAIN = 60.0  # N per m/s of handle speed below the pace
HUMAN_START_PUSH = 3.5  # N along the swing when opening (the self-closing spring holds ~3 N)
LOST_SUBSTEPS = 100  # 0.2 s off the handle and the teacher re-grasps
PRESS_DWELL = 300  # 0.6 s of pressing on the handle before the swing starts
RECORD_THRESHOLD = 0.0005  # m of motion before kinesthetic recording starts
REPLAY_SETTLE_STEPS = 10  # replay: hold the last pose 1 s
SWITCH_JITTER = 1.5  # steps (std) of the operator's mode-switch press around first contact
SWITCH_JITTER_MAX = 4


def relative_action(pos: np.ndarray, rot: np.ndarray, target_pos: np.ndarray, target_rot: np.ndarray) -> np.ndarray:
    """The 6-DOF action (scaled, clipped to [-1, 1]) that moves a sensor at (pos, rot) towards the
    target pose, in the sensor frame."""
    trans = rot.T @ (target_pos - pos) / MAX_TRANSLATION
    turn = rotation_vector(rot.T @ target_rot) / MAX_ROTATION
    return np.concatenate([trans, turn]).clip(-1.0, 1.0)


def _done(env: DoorTactileEnv) -> bool:
    angle = env.physics.door_angle()
    return angle >= OPEN_ANGLE + 0.05 if env.task.opening else angle <= CLOSED_ANGLE / 3


def _recorder(env: DoorTactileEnv, cameras: tuple[str, ...], depth: bool) -> RolloutRecorder:
    """The STS image of the active mode is recorded every frame, whatever the cameras."""
    return RolloutRecorder(env, cameras, depth, sensors={"sts": env.sts_image})


# ----------------------------------------------------------------------------- scripted policy
class ScriptedDoorExpert:
    """Approach the hinge side of the handle, switch the STS to tactile, press until in contact for
    `SCRIPTED_PRESS_STEPS` steps, then drag along the arc; back to the approach if the handle is lost.
    An env with a fixed sensor mode takes the action without its mode dim."""

    def __init__(self, env: DoorTactileEnv) -> None:
        self.env = env
        self.phase = "approach"
        self.pressed = 0

    def act(self) -> np.ndarray:
        """The next action, without the mode dim when the env's sensor mode is fixed."""
        return self._act()[: len(self.env.action_names)]

    def _act(self) -> np.ndarray:
        p = self.env.physics
        pos, rot = p.ee_pos(), p.ee_rot()
        g_pos, g_rot = p.grasp_pose(p.door_angle())
        if self.phase == "approach":
            goal = g_pos - g_rot[:, 2] * PRE_CONTACT
            if np.linalg.norm(goal - pos) >= 0.004:
                return np.append(relative_action(pos, rot, goal, g_rot), 0.0)
            self.phase, self.pressed = "press", 0
        if _done(self.env):
            return np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
        contact = p.handle_contact()
        if self.phase == "press":
            self.pressed = self.pressed + 1 if contact else 0
            if self.pressed >= SCRIPTED_PRESS_STEPS:
                self.phase = "drag"
        elif not contact:
            self.phase = "approach"
        # hold the pad on the handle's middle (sensor y and the rotation), press along the pad normal
        # and drag along the finger axis, which the yaw keeps on the door's swing direction
        hold = relative_action(pos, rot, g_pos, g_rot)
        drag = 0.0
        if self.phase == "drag":
            drag = DRAG_ACTION[self.env.task.variant] * (-1.0 if self.env.task.opening else 1.0)
        return np.array([drag if self.phase == "drag" else hold[0], hold[1], PRESS_ACTION, *hold[3:], 1.0])


def rollout(
    env: DoorTactileEnv, seed: int, cameras: tuple[str, ...] = (), depth: bool = False, extra_steps: int = 0
) -> Rollout:
    """One scripted-expert episode from `reset(seed=seed)`; frame t holds the observation before
    action t, `success[t]` the env's success after it. Images: the requested cameras and "sts"
    (the active mode's STS image)."""
    return expert_rollout(env, seed, ScriptedDoorExpert, cameras, depth, extra_steps, sensors={"sts": env.sts_image})


# ----------------------------------------------------------------------------- kinesthetic teacher
class KinestheticTeacher:
    """The scripted person's hand on the finger: a wrench at the sensor every physics step.

    Approach: a spring-damper pulls the finger to just before the hinge side of the handle. Press:
    a force along the pad normal, held for `PRESS_DWELL` steps in contact. Drag: the press continues while a force along the door's swing
    keeps the door at the person's pace (plus a start-up push against the self-closing spring when
    opening) and re-centres the pad on the handle when it creeps; in-plane errors are held by the
    spring-damper. A finger that lost the handle for 0.2 s goes back to the approach (a person
    re-grasps); once the task is done the hand lets go."""

    def __init__(self, env: DoorTactileEnv) -> None:
        self.env = env
        self.phase = "approach"
        self.press = HUMAN_PRESS[env.task.variant]
        self.sign = 1.0 if env.task.opening else -1.0
        self.lost = 0
        self.pressed = 0

    def __call__(self, p: DoorTactilePhysics) -> np.ndarray:
        """The (6,) wrench the person's hand applies to the sensor now: force (N), torque (Nm), world frame."""
        vel = np.zeros(6)
        mujoco.mj_objectVelocity(p.model, p.data, mujoco.mjtObj.mjOBJ_SITE, p.ee_site, vel, 0)
        ang, lin = vel[:3], vel[3:]
        pos, rot = p.ee_pos(), p.ee_rot()
        angle = p.door_angle()
        goal, goal_rot = p.grasp_pose(angle)
        normal = goal_rot[:, 2]
        if self.phase == "release" or (self.phase == "drag" and _done(self.env)):
            self.phase = "release"  # let go: the hand only damps
            return np.concatenate([-HUMAN_DAMPING * lin, -HUMAN_ROT_DAMPING * ang])
        if self.phase == "approach":
            goal = goal - normal * PRE_CONTACT
            if np.linalg.norm(goal - pos) < 0.003 and np.linalg.norm(lin) < 0.05:
                self.phase = "press"
            force = HUMAN_STIFFNESS * (goal - pos) - HUMAN_DAMPING * lin
            size = np.linalg.norm(force)
            if size > HUMAN_MAX_FORCE:
                force *= HUMAN_MAX_FORCE / size
        else:
            contact = p.handle_contact()
            self.pressed = self.pressed + 1 if self.phase == "press" and contact else 0
            if self.pressed > PRESS_DWELL:
                self.phase = "drag"
            self.lost = 0 if contact else self.lost + 1
            if self.phase == "drag" and self.lost > LOST_SUBSTEPS:
                self.phase, self.lost = "approach", 0
            err = goal - pos
            err -= normal * (normal @ err)
            swing = p.door_outward(angle) * self.sign  # handle motion direction that does the task
            across = lin - normal * (normal @ lin) - swing * (swing @ lin)  # the pace term handles the swing
            in_plane = HUMAN_STIFFNESS * (err - swing * (swing @ err)) - HUMAN_DAMPING * across
            if self.phase == "drag":
                speed = self.sign * p.door_velocity() * HANDLE_RADIUS
                push = HUMAN_START_PUSH if self.env.task.opening else 0.0
                drag = push + HUMAN_PACE_GAIN * (HUMAN_PACE * HANDLE_RADIUS - speed) + HUMAN_STIFFNESS * (swing @ err)
                in_plane += swing * float(np.clip(drag, -HUMAN_MAX_DRAG, HUMAN_MAX_DRAG))
            size = np.linalg.norm(in_plane)
            if size > HUMAN_MAX_DRAG:
                in_plane *= HUMAN_MAX_DRAG / size
            force = in_plane + normal * self.press
        torque = HUMAN_ROT_STIFFNESS * rotation_vector(goal_rot @ rot.T) - HUMAN_ROT_DAMPING * ang
        return np.concatenate([force, torque])


def kinesthetic_rollout(
    env: DoorTactileEnv, seed: int, cameras: tuple[str, ...] = (), depth: bool = False, extra_steps: int = 0
) -> Rollout:
    """One simulated kinesthetic demonstration (see the module docstring). Arrays: `ee_pose` (x_raw,
    position + quaternion xyzw, base frame) and `wrench_raw` (F~_raw); actions are the relative
    pose changes between recorded frames plus the operator's mode label (1 tactile / 0 visual);
    meta: `first_contact_step`, `mode_switch_step` (frame indices), `recording_start_step`. In an env
    with a fixed sensor mode every frame is in that mode and the actions have no mode dim."""
    cameras = tuple(c for c in cameras if c != "sts")  # "sts" is always recorded
    obs, info = env.reset(seed=seed)
    teacher = KinestheticTeacher(env)
    rng = np.random.default_rng([seed, 1])  # the operator's timing, apart from the env's streams
    start = env.physics.ee_pos()
    waited = 0
    while np.linalg.norm(env.physics.ee_pos() - start) < RECORD_THRESHOLD:
        obs, _, _, truncated, info = env.step_freedrive(teacher)
        waited += 1
        if truncated:
            break
    frames: list[dict[str, Any]] = []

    def capture(obs: np.ndarray, info: dict[str, Any]) -> None:
        frames.append(
            {
                "obs": obs,
                "info": info,
                "pose": env.ee_pose(),
                "rot": env.physics.ee_rot(),
                "wrench": env.sensor.raw_wrench(obs[21:25]),
                "contact": info["handle_contact"],
                "tactile": env.sts_image(),
                "visual": env.sensor.visual_image(env.physics.data),
                "images": {c: env.render_rgb(c) for c in cameras},
                "depth": {c: env.render_depth(c) for c in cameras} if depth else {},
            }
        )

    capture(obs, info)
    success: list[bool] = []
    left = None
    while True:
        obs, _, _, truncated, info = env.step_freedrive(teacher)
        success.append(info["is_success"])
        if info["is_success"] and left is None:
            left = extra_steps
        capture(obs, info)  # the state after the last action closes the pose sequence
        if truncated or (left is not None and left <= 0):
            break
        if left is not None:
            left -= 1
    n = len(success)
    contact = [i for i, f in enumerate(frames[:n]) if f["contact"]]
    first_contact = contact[0] if contact else n - 1
    jitter = int(np.clip(np.round(rng.normal(0.0, SWITCH_JITTER)), -SWITCH_JITTER_MAX, SWITCH_JITTER_MAX))
    switch = int(np.clip(first_contact + jitter, 0, n - 1))
    mode = (np.arange(n) >= switch).astype(np.float32)
    if env.fixed_mode is not None:
        mode[:] = float(env.fixed_mode == "tactile")
    actions = np.zeros((n, 7), dtype=np.float32)
    for t in range(n):
        a, b = frames[t], frames[t + 1]
        actions[t, :6] = relative_action(a["pose"][:3], a["rot"], b["pose"][:3], b["rot"])
        actions[t, 6] = mode[t]
    body = frames[:n]
    return Rollout(
        observations=np.array([f["obs"] for f in body], dtype=np.float32),
        actions=actions[:, : len(env.action_names)],
        success=np.array(success, dtype=bool),
        qpos=np.array([f["info"]["qpos"] for f in body]),
        qvel=np.array([f["info"]["qvel"] for f in body]),
        images={
            **{c: np.array([f["images"][c] for f in body], dtype=np.uint8) for c in cameras},
            "sts": np.array([f["tactile"] if m else f["visual"] for f, m in zip(body, mode, strict=True)], np.uint8),
        },
        depth={c: np.array([f["depth"][c] for f in body], dtype=np.float32) for c in (cameras if depth else ())},
        arrays={
            "ee_pose": np.array([f["pose"] for f in body]),
            "wrench_raw": np.array([f["wrench"] for f in body]),
        },
        meta={
            "first_contact_step": int(first_contact),
            "mode_switch_step": switch,
            "recording_start_step": waited,
            "kinesthetic": True,
        },
    )


# ----------------------------------------------------------------------------- plain replay
def replay_positions(
    env: DoorTactileEnv,
    seed: int,
    ee_pose: np.ndarray,
    modes: np.ndarray | None = None,
    warmup_steps: int = 0,
    settle_steps: int = REPLAY_SETTLE_STEPS,
    cameras: tuple[str, ...] = (),
    depth: bool = False,
) -> Rollout:
    """Position replay (no force matching): from `reset(seed=seed)`, the impedance controller's
    target is set to each recorded pose in turn: x_raw[0] for `warmup_steps` steps (the steps the
    demonstration spent before recording started), then x_raw[t + 1] for step t (`ee_pose`: position
    + quaternion xyzw, base frame), then the last pose for `settle_steps` more steps (the controller
    lags the targets by a few steps; the outcome is judged once it has caught up). `modes` (T,)
    gives the STS mode per step (default tactile). The recorded actions are the relative poses of
    those targets from the pose at each step (clipped to the action range: what a policy trained on
    the replay would output)."""
    poses = np.asarray(ee_pose, dtype=np.float64)
    rots = quat_xyzw_to_matrix(poses[:, 3:7])
    targets = [*range(1, len(poses)), *[len(poses) - 1] * settle_steps]
    rec = _recorder(env, cameras, depth)
    obs, info = env.reset(seed=seed)
    for _ in range(warmup_steps):
        obs, _, _, _, info = env.step_pose(poses[0, :3], rots[0], "visual")
    rec.frame(obs, info)
    for i, t in enumerate(targets):
        p = env.physics
        tactile = modes is None or modes[min(t, len(modes)) - 1] > 0.5
        rec.actions.append(np.append(relative_action(p.ee_pos(), p.ee_rot(), poses[t, :3], rots[t]), float(tactile)))
        obs, _, _, truncated, info = env.step_pose(poses[t, :3], rots[t], "tactile" if tactile else "visual")
        rec.success.append(info["is_success"])
        if truncated or i == len(targets) - 1:
            break
        rec.frame(obs, info)
    return rec.done()
