"""Panda play tasks: success predicates over a snapshot of the scene, and the task registry.

Predicates and thresholds follow the LfGP thesis, appendix A.4, and the reference code
(utiasSTARS/manipulator-learning `PandaPlayGeneric.get_task_successes`). The task object is the
blue block (the reference's `_0` suffix); `stack` puts blue on green. A task succeeds once its
predicate has held for `hold_seconds` (0.5 s = 10 steps at 20 Hz; move-object 1 s = 20 steps).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from shiftkit.envs.panda_play.physics import BLOCK_REST_Z, BRING_TARGETS, INSERT_TARGETS, ContactFlags

REACH_THRESHOLD = 0.015
GRASP_DISTANCE = 0.03
LIFT_HEIGHT = 0.06
MOVE_MIN_SPEED = 0.05
MOVE_MAX_ACCEL = 5.0
BRING_THRESHOLD = 0.03
INSERT_THRESHOLD = 0.0025
NEAR_BLOCK = 0.1
OPEN_CLOSE_MAX_SPEED = 0.08


@dataclass(frozen=True)
class SceneFacts:
    """What the predicates look at, in the base frame (index 0 = blue, 1 = green)."""

    tcp: np.ndarray
    tcp_velocity: np.ndarray
    blocks: np.ndarray
    block_velocity: np.ndarray
    block_acceleration: np.ndarray
    gripper_action: float
    contacts: ContactFlags


def _near_a_block(f: SceneFacts) -> bool:
    return bool(np.min(np.linalg.norm(f.blocks - f.tcp, axis=1)) < NEAR_BLOCK)


def open_gripper(f: SceneFacts) -> bool:
    """Opening command (> 0) near a block with the arm nearly still."""
    return f.gripper_action > 0 and _near_a_block(f) and np.linalg.norm(f.tcp_velocity) < OPEN_CLOSE_MAX_SPEED


def close_gripper(f: SceneFacts) -> bool:
    """Closing command (< 0) near a block with the arm nearly still."""
    return f.gripper_action < 0 and _near_a_block(f) and np.linalg.norm(f.tcp_velocity) < OPEN_CLOSE_MAX_SPEED


def reach(f: SceneFacts) -> bool:
    """TCP within 1.5 cm of the blue block's centre."""
    return bool(np.linalg.norm(f.blocks[0] - f.tcp) < REACH_THRESHOLD)


def grasp(f: SceneFacts) -> bool:
    """Both fingers touch the blue block and it is between them (centre within 3 cm of the TCP)."""
    c = f.contacts
    return c.blue_left_finger and c.blue_right_finger and bool(np.linalg.norm(f.blocks[0] - f.tcp) < GRASP_DISTANCE)


def lift(f: SceneFacts) -> bool:
    """Blue block centre at least 6 cm above its resting height."""
    return bool(f.blocks[0, 2] - BLOCK_REST_Z >= LIFT_HEIGHT)


def move_object(f: SceneFacts) -> bool:
    """Blue block moving faster than 5 cm/s with acceleration below 5 m/s^2."""
    return bool(
        np.linalg.norm(f.block_velocity[0]) > MOVE_MIN_SPEED
        and np.linalg.norm(f.block_acceleration[0]) < MOVE_MAX_ACCEL
    )


def stack(f: SceneFacts) -> bool:
    """Blue touches green and touches neither the tray nor the gripper."""
    c = f.contacts
    return c.blue_green and not c.blue_tray and not c.blue_gripper


def bring(f: SceneFacts) -> bool:
    """Blue within 3 cm of its bring target, resting on the tray, not touched by the gripper."""
    c = f.contacts
    return bool(np.linalg.norm(f.blocks[0] - BRING_TARGETS[0]) < BRING_THRESHOLD) and c.blue_tray and not c.blue_gripper


def insert(f: SceneFacts) -> bool:
    """Blue within 2.5 mm of the inserted pose in its slot, on the tray, not touched by the gripper."""
    c = f.contacts
    return (
        bool(np.linalg.norm(f.blocks[0] - INSERT_TARGETS[0]) < INSERT_THRESHOLD) and c.blue_tray and not c.blue_gripper
    )


@dataclass(frozen=True)
class Task:
    """A registered Panda play task."""

    name: str
    """CLI / dataset task name (lower case, dashes)."""
    gym_name: str
    """CamelCase part of the gymnasium id `shiftkit/PandaPlay-<gym_name>-v0`."""
    predicate: Callable[[SceneFacts], bool]
    """Instantaneous success condition."""
    hold_seconds: float = 0.5
    """How long the predicate must hold before the task counts as solved."""
    green_on_blue: bool = False
    """Reset with the green block stacked on the blue one."""

    @property
    def description(self) -> str:
        """What success means: the predicate's docstring."""
        return (self.predicate.__doc__ or "").strip()

    def hold_steps(self, control_hz: int) -> int:
        """Steps the predicate must hold at `control_hz` to last `hold_seconds` (at least 1)."""
        return max(1, math.ceil(self.hold_seconds * control_hz - 1e-9))


TASKS: dict[str, Task] = {
    t.name: t
    for t in (
        Task("open", "Open", open_gripper),
        Task("close", "Close", close_gripper),
        Task("reach", "Reach", reach),
        Task("grasp", "Grasp", grasp),
        Task("lift", "Lift", lift),
        Task("move-object", "MoveObject", move_object, hold_seconds=1.0),
        Task("stack", "Stack", stack),
        Task("unstack-stack", "UnstackStack", stack, green_on_blue=True),
        Task("bring", "Bring", bring),
        Task("insert", "Insert", insert),
    )
}


def get_task(name: str) -> Task:
    """The task called `name`; a ValueError lists the known ones."""
    try:
        return TASKS[name]
    except KeyError:
        raise ValueError(f"unknown panda-play task {name!r}; known: {', '.join(TASKS)}") from None


class HoldTimer:
    """Counts consecutive steps on which a predicate held; success once it reaches `steps`."""

    def __init__(self, steps: int) -> None:
        self.steps = steps
        self.count = 0

    def reset(self) -> None:
        """Start counting again."""
        self.count = 0

    def update(self, holds: bool) -> bool:
        """Count this step (or start over when `holds` is false); whether the predicate has held `steps` steps."""
        self.count = self.count + 1 if holds else 0
        return self.count >= self.steps
