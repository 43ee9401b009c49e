"""Door + tactile finger tasks: which handle, where the door starts, the start-pose distribution and
the success rule (thesis §4.4.1).

* open: the door starts closed; success once it is past `OPEN_ANGLE` within the time limit;
* close: the door starts open (held by the hinge friction above the spring zone); success once it
  is shut (`CLOSED_ANGLE`) without having slammed: a door swinging shut faster than `SLAM_SPEED`
  while the finger is off the handle is a slam and the episode can no longer succeed.

The end-effector (sensor) start pose is the task's nominal pose plus a uniform offset in a 3 cm
cube and a yaw in +-0.15 rad about the world z axis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

OPEN_ANGLE = 0.8
CLOSED_ANGLE = 0.03
SLAM_SPEED = 0.6  # rad/s towards closed with no finger on the handle
START_HALF = 0.015
START_YAW = 0.15
# nominal start relative to the contact point on the handle (world frame, door at its start angle):
# back from the door and towards the hinge, clear of the handle
START_OFFSET_ALONG_NORMAL = -0.04  # along the pad normal (negative: away from the handle)
START_OFFSET_BACK = 0.07  # away from the door face


@dataclass(frozen=True)
class DoorTask:
    """One door task: handle variant, direction (open or close) and the reset ranges."""

    name: str
    gym_name: str
    variant: str
    """"flat" (flat handle) or "knob" (spherical knob)."""
    opening: bool
    door_start: tuple[float, float]
    """Door angle range at reset (rad)."""

    def succeeded(self, door_angle: float, slammed: bool) -> bool:
        """Whether the door is open past `OPEN_ANGLE` (opening tasks), or closed and not slammed."""
        if self.opening:
            return door_angle >= OPEN_ANGLE
        return door_angle <= CLOSED_ANGLE and not slammed


TASKS: dict[str, DoorTask] = {
    t.name: t
    for t in (
        DoorTask("flat-handle-open", "FlatHandleOpen", "flat", True, (0.0, 0.0)),
        DoorTask("flat-handle-close", "FlatHandleClose", "flat", False, (0.85, 0.95)),
        DoorTask("knob-open", "KnobOpen", "knob", True, (0.0, 0.0)),
        DoorTask("knob-close", "KnobClose", "knob", False, (0.85, 0.95)),
    )
}


def get_task(name: str) -> DoorTask:
    """The door task `name`; ValueError for an unknown one."""
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}; known: {', '.join(TASKS)}")
    return TASKS[name]


def sample_start(task: DoorTask, rng: np.random.Generator) -> tuple[float, np.ndarray, float]:
    """Door angle, sensor position offset (3,) and yaw offset for one reset (all from `rng`)."""
    lo, hi = task.door_start
    angle = float(rng.uniform(lo, hi)) if hi > lo else lo
    return angle, rng.uniform(-START_HALF, START_HALF, 3), float(rng.uniform(-START_YAW, START_YAW))
