"""Scripted experts for the multiview tasks and the recording loop.

Each expert is closed-loop on the privileged simulator state expressed in the base frame (object
and TCP poses, finger contacts); it keeps no plan between steps beyond what the state shows, so it
can take over from any state (e.g. after a policy's mistakes). Actions are velocities in the base
frame, as the env takes them.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from shiftkit.envs.base_pose import TABLE_Z
from shiftkit.envs.multiview.env import MultiviewEnv
from shiftkit.envs.multiview.physics import (
    BLOCK_HALF,
    CYLINDER_HALF_LENGTH,
    HOLE_DEPTH,
    MAX_TCP_ROT_SPEED,
    MAX_TCP_SPEED,
    MultiviewPhysics,
)
from shiftkit.envs.multiview.tasks import BLOCK_REST_Z, LIFT_HEIGHT, hole_centre
from shiftkit.envs.registry import Registry
from shiftkit.envs.rollout import Rollout, expert_rollout

STEP = MAX_TCP_SPEED / 10  # metres per 10 Hz step at |action| = 1
ROT_STEP = MAX_TCP_ROT_SPEED / 10
CLOSED = 0.08  # finger opening (fraction) below which the gripper closed on nothing


def hand_yaw(p: MultiviewPhysics) -> float:
    """Yaw (base frame) of the finger closing axis (the site's y axis), in (-pi, pi]."""
    r = p.tcp_rot()
    return float(np.arctan2(r[1, 1], r[0, 1]))


def _wrap_half_turn(angle: float) -> float:
    """Angle wrapped to [-pi/2, pi/2) (the two fingers are interchangeable)."""
    return float((angle + np.pi / 2) % np.pi - np.pi / 2)


# The scripted controller of each task: `MultiviewExpert` methods registered by task name.
TASK_EXPERTS: Registry[Callable[[MultiviewExpert], np.ndarray]] = Registry("multiview task expert")


class MultiviewExpert:
    """Scripted controller for one task; `act()` gives the next action from the current state."""

    def __init__(self, env: MultiviewEnv) -> None:
        self.env = env
        self.task = env.task

    @property
    def p(self) -> MultiviewPhysics:
        """The env's physics."""
        return self.env.physics

    def _action(self, move: np.ndarray, gripper: float, yaw_rate: float = 0.0) -> np.ndarray:
        move = np.clip(np.asarray(move, dtype=np.float64) / STEP, -1.0, 1.0)
        if not self.task.rotation:
            return np.array([*move, gripper], dtype=np.float32)
        rot = np.clip(yaw_rate / ROT_STEP, -1.0, 1.0)
        return np.array([*move, 0.0, 0.0, rot, gripper], dtype=np.float32)

    def _toward(
        self, target: np.ndarray, gripper: float, gain: float = 1.0, yaw_rate: float = 0.0, max_step: float = STEP
    ) -> np.ndarray:
        move = gain * (np.asarray(target) - self.p.tcp_pos())
        norm = np.linalg.norm(move)
        return self._action(move * min(1.0, max_step / norm) if norm > 0 else move, gripper, yaw_rate)

    def _pick(self, name: str, grasp_offset: float, clearance: float, xy_tol: float = 0.008) -> np.ndarray | None:
        """Actions that bring the open hand onto object `name` and close it; None once it is held.
        `grasp_offset`: TCP height above the object's centre at the grasp; `clearance`: hover height."""
        p = self.p
        geom = p.object_geom[name]
        if p.holding(geom):
            return None
        obj = p.object_pos(name)
        grasp = obj + [0.0, 0.0, grasp_offset]
        tcp = p.tcp_pos()
        if p.gripper_closed:
            near = np.linalg.norm(tcp - grasp) < 0.015
            if near and p.fingers().mean() > CLOSED and np.abs(np.diff(p.finger_history, axis=0)).max() > 1e-3:
                return self._action(np.zeros(3), -1.0)  # still closing around it
            if near and p.fingers().mean() > CLOSED:
                return self._action(np.zeros(3), -1.0)
            return self._action([0.0, 0.0, 0.02], 1.0)  # missed: open and back off
        xy_err = np.linalg.norm(grasp[:2] - tcp[:2])
        if xy_err > 0.015:
            hover = np.array([*grasp[:2], max(grasp[2] + clearance, min(tcp[2], grasp[2] + 0.1))])
            if tcp[2] < grasp[2] + clearance - 0.01:
                hover = np.array([*tcp[:2], grasp[2] + clearance])  # rise before moving across
            return self._toward(hover, 1.0)
        # close in xy: descend while correcting, stopping 2 cm short until aligned, slowing at the end
        target = grasp if xy_err <= xy_tol else grasp + [0.0, 0.0, 0.02]
        if np.linalg.norm(target - tcp) > 0.005 or xy_err > xy_tol:
            return self._toward(target, 1.0, max_step=STEP if tcp[2] - target[2] > 0.03 else 0.008)
        return self._action(np.zeros(3), -1.0)

    def act(self) -> np.ndarray:
        """The next action of the task's script."""
        return TASK_EXPERTS.get(self.task.name)(self)

    # ----------------------------------------------------------------- tasks
    @TASK_EXPERTS.named("lift")
    def _lift(self) -> np.ndarray:
        a = self._pick("block", 0.0, 0.06)
        if a is not None:
            return a
        block = self.p.object_pos("block")
        return self._toward([*block[:2], BLOCK_REST_Z + LIFT_HEIGHT + 0.05], -1.0)

    @TASK_EXPERTS.named("stack")
    def _stack(self) -> np.ndarray:
        p = self.p
        blue, green = p.object_pos("blue"), p.object_pos("green")
        on_green = np.linalg.norm(blue[:2] - green[:2]) < 0.015 and abs(blue[2] - green[2] - 2 * BLOCK_HALF) < 0.006
        if on_green and not p.holding(p.object_geom["blue"]):
            tcp = p.tcp_pos()  # released on the tower: open and retreat upwards
            return self._toward([*tcp[:2], green[2] + 0.15], 1.0)
        a = self._pick("blue", 0.0, 0.06)
        if a is not None:
            return a
        offset = p.tcp_pos() - blue  # where the block sits in the grasp
        place = green + [0.0, 0.0, 2 * BLOCK_HALF + 0.004]
        carry_z = green[2] + 2 * BLOCK_HALF + 0.05
        if np.linalg.norm(place[:2] - blue[:2]) > 0.004:
            target = [*place[:2], max(carry_z, blue[2])] if blue[2] < carry_z - 0.01 else [*place[:2], carry_z]
            if blue[2] < carry_z - 0.01 and np.linalg.norm(place[:2] - blue[:2]) > 0.02:
                target = [*blue[:2], carry_z]  # lift clear before moving across
            return self._toward(np.asarray(target) + offset, -1.0)
        if blue[2] - place[2] > 0.003:
            return self._toward(place + offset, -1.0, gain=0.5)
        return self._action(np.zeros(3), 1.0)

    @TASK_EXPERTS.named("pick-insert")
    def _pick_insert(self) -> np.ndarray:
        p = self.p
        a = self._pick("cylinder", CYLINDER_HALF_LENGTH - 0.02, 0.06, xy_tol=0.003)
        if a is not None:
            return a
        cyl = p.object_pos("cylinder")
        axis = p.object_rot("cylinder")[:, 2]
        bottom = cyl - np.sign(axis[2]) * CYLINDER_HALF_LENGTH * axis
        hole = hole_centre(p)
        # align the cylinder's bottom (not its centre: it may hang tilted in the grasp) with the hole
        shift = np.array([*(hole[:2] - bottom[:2]), 0.0])
        xy_err = float(np.linalg.norm(shift))
        hover = hole[2] + 0.015 - bottom[2]  # bottom 1.5 cm above the opening
        if bottom[2] > hole[2] - 0.002 or xy_err > 0.003:  # not in the hole yet
            if xy_err > 0.02 and hover > 0.005:  # rise clear of the fixture first
                return self._toward(p.tcp_pos() + [0.0, 0.0, hover], -1.0)
            if xy_err > 0.02:  # carried gently: a fast start swings the cylinder in the grasp
                return self._toward(p.tcp_pos() + shift + [0.0, 0.0, max(hover, 0.0)], -1.0, max_step=0.015)
            if xy_err > 0.0015:
                return self._toward(p.tcp_pos() + shift + [0.0, 0.0, max(hover, 0.0) * 0.5], -1.0, max_step=0.01)
            return self._toward(p.tcp_pos() + shift + [0.0, 0.0, -0.01], -1.0, max_step=0.005)
        depth = hole[2] - HOLE_DEPTH + 0.003 - bottom[2]
        return self._toward(p.tcp_pos() + shift + [0.0, 0.0, depth], -1.0, max_step=0.005)

    @TASK_EXPERTS.named("door")
    def _door(self) -> np.ndarray:
        p = self.p
        handle, hinge = p.handle_pos(), p.hinge_pos()
        arm = handle[:2] - hinge[:2]
        # fingers close across the handle arm (perpendicular to it)
        yaw_err = _wrap_half_turn(np.arctan2(arm[1], arm[0]) + np.pi / 2 - hand_yaw(p))
        top = TABLE_Z + 0.182  # the handle post's top (door panel 12 cm + post 6 cm above it)
        grasp = np.array([*handle[:2], top - 0.03])
        geom = p.model.geom("door_handle").id
        held = p.holding(geom)
        tcp = p.tcp_pos()
        if held:
            ahead = 0.35  # rad of door travel the hand leads by
            c, s = np.cos(ahead), np.sin(ahead)
            target_xy = hinge[:2] + np.array([c * arm[0] - s * arm[1], s * arm[0] + c * arm[1]])
            target = np.array([*target_xy, grasp[2]]) + (tcp - grasp) * [1, 1, 0]
            return self._toward(target, -1.0, gain=0.6, yaw_rate=yaw_err)
        if p.gripper_closed:
            near = np.linalg.norm(tcp - grasp) < 0.015
            if near and p.fingers().mean() > CLOSED:
                return self._action(np.zeros(3), -1.0)
            return self._action([0.0, 0.0, 0.02], 1.0)
        xy_err = np.linalg.norm(grasp[:2] - tcp[:2])
        if xy_err > 0.006 or abs(yaw_err) > 0.05:
            z = max(top + 0.03, tcp[2]) if xy_err > 0.015 else top + 0.03
            return self._toward([*grasp[:2], z], 1.0, yaw_rate=yaw_err)
        if np.linalg.norm(grasp - tcp) > 0.006:
            return self._toward(grasp, 1.0, gain=0.7, yaw_rate=yaw_err)
        return self._action(np.zeros(3), -1.0)


class ExpertPolicy:
    """The scripted expert as a policy (`act(obs)` ignores the observation and reads the state)."""

    def __init__(self, env: MultiviewEnv) -> None:
        self.expert = MultiviewExpert(env)

    def reset(self) -> None:
        """Nothing to reset: the expert reads the simulator state."""

    def act(self, obs: Any) -> np.ndarray:
        """The expert's next action (`obs` unused)."""
        return self.expert.act()


def rollout(
    env: MultiviewEnv,
    seed: int,
    cameras: tuple[str, ...] = (),
    depth: bool = False,
    extra_steps: int = 0,
) -> Rollout:
    """Run the task expert from `reset(seed=seed)` until success has held (plus `extra_steps`) or
    the episode is truncated (`envs.rollout.expert_rollout`); `meta["cameras"]` carries intrinsics,
    extrinsics and the base pose."""
    r = expert_rollout(env, seed, MultiviewExpert, cameras, depth, extra_steps)
    r.meta = {"cameras": env.camera_metadata(), "view": env.view}
    return r
