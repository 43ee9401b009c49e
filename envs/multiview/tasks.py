"""The multiview tasks (thesis Table 3.1): objects, reset distributions, actions and success.

Reset boxes are in the task (world) frame around the task centre, so they do not move with the
base; the TCP start is in the base frame (the robot starts in its own home posture).
PickAndInsert uses a square hole with 1 mm clearance per side around a 3 cm cylinder (the thesis'
"< 1 mm tolerance").
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from shiftkit.envs.base_pose import AIM, TABLE_Z
from shiftkit.envs.multiview.physics import (
    BLOCK_HALF,
    CYLINDER_HALF_LENGTH,
    CYLINDER_RADIUS,
    HOLE_CLEARANCE,
    HOLE_DEPTH,
    HOLE_XY,
    MultiviewPhysics,
)

BLOCK_REST_Z = TABLE_Z + BLOCK_HALF
LIFT_HEIGHT = 0.075
CYLINDER_START_XY = np.array([-0.06, 0.0])
DOOR_OPEN_ANGLE = np.pi / 2


@dataclass(frozen=True)
class MultiviewTask:
    """One task: scene objects, action size, reset and success predicate."""

    name: str
    env: str
    """CLI env name (`--env`), one family per task."""
    gym_name: str
    objects: tuple[str, ...]
    rotation: bool
    """6-DOF velocity actions (else translation only)."""
    reset: Callable[[MultiviewPhysics, np.random.Generator], np.ndarray]
    """Places the objects (physics.place_object) and returns the base-frame TCP start."""
    predicate: Callable[[MultiviewPhysics], bool]
    hold_steps: int = 3
    max_episode_seconds: float = 15.0
    environment_names: tuple[str, ...] = ()

    @property
    def action_names(self) -> tuple[str, ...]:
        """Action dims: translation velocities, rotation rates when `rotation`, gripper."""
        move = ("vel_x", "vel_y", "vel_z")
        return (*move, "rot_x", "rot_y", "rot_z", "gripper_open") if self.rotation else (*move, "gripper_open")

    @property
    def model_id(self) -> str:
        """Simulator model id (`<env>-v1`)."""
        return f"{self.env}-v1"


def _pose_names(name: str) -> tuple[str, ...]:
    return tuple(f"{name}_{k}" for k in ("pos_x", "pos_y", "pos_z", "quat_x", "quat_y", "quat_z", "quat_w"))


def _tcp_start(rng: np.random.Generator) -> np.ndarray:
    return AIM + [0.0, -0.05, 0.14]


def _reset_lift(p: MultiviewPhysics, rng: np.random.Generator) -> np.ndarray:
    p.place_object("block", rng.uniform(-0.125, 0.125, 2), BLOCK_REST_Z + 1e-4, rng.uniform(0, 2 * np.pi))
    return _tcp_start(rng)


def _reset_stack(p: MultiviewPhysics, rng: np.random.Generator) -> np.ndarray:
    blue = rng.uniform(-0.075, 0.075, 2)
    while True:
        green = rng.uniform(-0.075, 0.075, 2)
        if np.linalg.norm(green - blue) >= 0.07:
            break
    p.place_object("blue", blue, BLOCK_REST_Z + 1e-4, rng.uniform(0, 2 * np.pi))
    p.place_object("green", green, BLOCK_REST_Z + 1e-4, rng.uniform(0, 2 * np.pi))
    return _tcp_start(rng)


def _reset_insert(p: MultiviewPhysics, rng: np.random.Generator) -> np.ndarray:
    xy = CYLINDER_START_XY + rng.uniform(-0.0125, 0.0125, 2)
    p.place_object("cylinder", xy, TABLE_Z + CYLINDER_HALF_LENGTH + 1e-4, rng.uniform(0, 2 * np.pi))
    return _tcp_start(rng)


def _reset_door(p: MultiviewPhysics, rng: np.random.Generator) -> np.ndarray:
    # gripper start in a 12 x 5 x 5 cm box (base frame, in front of the door)
    return AIM + [0.0, -0.1, 0.16] + rng.uniform([-0.06, -0.025, -0.025], [0.06, 0.025, 0.025])


def lifted(p: MultiviewPhysics) -> bool:
    """Whether the block is more than `LIFT_HEIGHT` above its rest height."""
    return bool(p.object_pos("block")[2] > BLOCK_REST_Z + LIFT_HEIGHT)


def stacked(p: MultiviewPhysics) -> bool:
    """Whether blue rests on green and the gripper has let go of it."""
    blue, green = p.object_pos("blue"), p.object_pos("green")
    on_top = np.linalg.norm(blue[:2] - green[:2]) < 0.02 and abs(blue[2] - green[2] - 2 * BLOCK_HALF) < 0.005
    return bool(on_top and not p.touching(p.object_geom["blue"], "left") and not p.gripper_closed)


def hole_centre(p: MultiviewPhysics) -> np.ndarray:
    """Base-frame centre of the hole's top opening."""
    return p.base_pose.to_base(np.array([*HOLE_XY, TABLE_Z + HOLE_DEPTH]))


def inserted(p: MultiviewPhysics) -> bool:
    """Whether the cylinder's bottom is down in the hole, within its radius of the centre."""
    c = p.object_pos("cylinder")
    hole = hole_centre(p)
    bottom = c[2] - CYLINDER_HALF_LENGTH
    return bool(
        np.linalg.norm(c[:2] - hole[:2]) < CYLINDER_RADIUS and bottom < hole[2] - HOLE_DEPTH + 0.01 + HOLE_CLEARANCE
    )


def door_open(p: MultiviewPhysics) -> bool:
    """Whether the door is open past `DOOR_OPEN_ANGLE`."""
    return p.door_angle() > DOOR_OPEN_ANGLE


TASKS: dict[str, MultiviewTask] = {
    t.name: t
    for t in (
        MultiviewTask(
            "lift", "mv-lift", "Lift", ("block",), False, _reset_lift, lifted, environment_names=_pose_names("block")
        ),
        MultiviewTask(
            "stack",
            "mv-stack",
            "Stack",
            ("blue", "green"),
            True,
            _reset_stack,
            stacked,
            max_episode_seconds=20.0,
            environment_names=_pose_names("blue") + _pose_names("green"),
        ),
        MultiviewTask(
            "pick-insert",
            "mv-pick-insert",
            "PickInsert",
            ("cylinder",),
            True,
            _reset_insert,
            inserted,
            environment_names=_pose_names("cylinder"),
        ),
        MultiviewTask(
            "door",
            "mv-door",
            "Door",
            (),
            True,
            _reset_door,
            door_open,
            max_episode_seconds=20.0,
            environment_names=("handle_pos_x", "handle_pos_y", "handle_pos_z", "door_angle"),
        ),
    )
}

STATE_NAMES = (
    "tcp_pos_x",
    "tcp_pos_y",
    "tcp_pos_z",
    "tcp_quat_x",
    "tcp_quat_y",
    "tcp_quat_z",
    "tcp_quat_w",
    "finger_left",
    "finger_right",
    "finger_left_t-1",
    "finger_right_t-1",
    "finger_left_t-2",
    "finger_right_t-2",
)


def get_task(name: str) -> MultiviewTask:
    """The multiview task `name`; ValueError for an unknown one."""
    if name not in TASKS:
        raise ValueError(f"unknown multiview task {name!r}; known: {', '.join(TASKS)}")
    return TASKS[name]
