"""Scripted experts for the Panda play tasks, play-based task sequences, and the rollout loop.

Each expert is a small state machine over the privileged simulator state (block poses, finger
contacts, the controller's desired TCP). Every expert starts from whatever state the scene is in
(it skips grasping when the block is already held), so experts chain into play episodes: one reset,
then a sequence of tasks (e.g. reach, lift, stack, open), each run until its success holds, each
labelled as a segment.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from shiftkit.envs.panda_play.env import PandaPlayEnv
from shiftkit.envs.panda_play.physics import (
    BLOCK_HALF,
    BLOCK_REST_Z,
    INSERT_TARGETS,
    TRAY_CENTER,
    WORKSPACE_HIGH,
    WORKSPACE_LOW,
    ZONE_XY,
)
from shiftkit.envs.panda_play.tasks import INSERT_THRESHOLD, TASKS
from shiftkit.envs.registry import Registry
from shiftkit.envs.rollout import Rollout, RolloutRecorder, expert_rollout

CARRY_Z = 0.23
ABOVE = 0.05
TURN_YAW = np.deg2rad(20.0)
TURN_OFFSET = 0.012
HELD_YAW = np.deg2rad(6.0)
# a block held more tilted than this cannot enter its slot (0.5 mm clearance per side)
MAX_INSERT_TILT = np.deg2rad(3.0)
# spots on the flat tray floor, clear of the slots, to put a block down
FREE_SPOTS = TRAY_CENTER + np.array([[-0.09, -0.08], [0.09, -0.08], [-0.09, 0.08], [0.09, 0.08], [0.0, 0.09]])
# handcrafted play sequences (thesis section 6.4: "Reach, Lift, Main, Open-Gripper, ...")
PLAY_SEQUENCES: dict[str, tuple[str, ...]] = {
    "stack": ("reach", "lift", "stack", "open"),
    "bring": ("reach", "grasp", "lift", "bring", "open"),
    "insert": ("reach", "lift", "insert", "open"),
    "lift": ("reach", "grasp", "lift", "move-object", "close"),
}


# The script of each task: `PandaPlayExpert` methods registered by task name.
TASK_EXPERTS: Registry[Callable[[PandaPlayExpert], np.ndarray]] = Registry("panda-play task expert")


class PandaPlayExpert:
    """Scripted controller for one task; `act()` returns the next action from the current state."""

    def __init__(self, env: PandaPlayEnv, task: str | None = None) -> None:
        self.env = env
        self.task = task or env.task.name
        if self.task not in TASKS:
            raise ValueError(f"no expert for task {self.task!r}")
        self.reset()

    def reset(self) -> None:
        """Back to the start of the task's script."""
        self.above = ABOVE  # height of the hover point before a grasp
        self.phase = "start"
        self.timer = 0
        self.aim = np.zeros(3)
        self.released = False
        self.turning = False
        self.turns = 0
        self.circle: tuple[np.ndarray, float] | None = None
        self.reseat: np.ndarray | None = None

    # ----------------------------------------------------------------- state helpers
    @property
    def p(self):
        """The env's physics."""
        return self.env.physics

    def holding(self, i: int) -> bool:
        """Whether both fingers touch block `i` (0: blue, 1: green) with the gripper closed."""
        c = self.p.contacts()
        left, right = (
            (c.blue_left_finger, c.blue_right_finger) if i == 0 else (c.green_left_finger, c.green_right_finger)
        )
        return left and right and self.p.gripper_closed

    def _toward(self, target: np.ndarray, speed: float = 1.0) -> np.ndarray:
        """Delta action moving the desired TCP straight towards `target` (clipped to the bounds)."""
        target = np.clip(target, WORKSPACE_LOW, WORKSPACE_HIGH)
        delta = (target - self.p.desired_tcp) / self.p.max_step
        norm = np.max(np.abs(delta))
        return delta * (speed / norm) if norm > speed else delta

    def _at(self, target: np.ndarray, tol: float = 0.004) -> bool:
        target = np.clip(target, WORKSPACE_LOW, WORKSPACE_HIGH)
        return bool(np.linalg.norm(self.p.tcp_pos() - target) < tol)

    def _steps(self, seconds: float) -> int:
        """Control steps in `seconds` (timers are in time, so experts run at 5 and 20 Hz alike)."""
        return max(1, math.ceil(seconds * self.p.control_hz - 1e-9))

    @staticmethod
    def _act(move: np.ndarray, close: bool) -> np.ndarray:
        return np.array([*np.clip(move, -1, 1), -1.0 if close else 1.0], dtype=np.float32)

    # ----------------------------------------------------------------- grasping
    def _grasp(self, i: int, grip_height: float = 0.0) -> np.ndarray | None:
        """Actions that pick block `i` up (TCP `grip_height` above its centre); None once held.

        Closing parallel fingers squares a block up only when its faces are within ~20 degrees of
        the pads; a more rotated block is first turned by a grasp offset 1.2 cm along the pads
        (the off-centre squeeze rotates it), released, and then grasped centred."""
        if self.phase == "start":
            self.phase = "close" if self.holding(i) else "above"
            self.timer = 0
        if self.phase not in ("above", "descend", "close"):
            return None
        block = self.p.block_pos(i)
        turn = abs(self.p.block_yaw_error(i)) > TURN_YAW
        # alternate the side: near 45 degrees one side may leave the block where it was
        side = 1.0 if self.turns % 2 == 0 else -1.0
        offset = np.array([0.0, side * TURN_OFFSET if turn else 0.0, 0.0])
        if self.phase == "above":
            target = block + offset + [0.0, 0.0, self.above]
            if self.p.gripper_closed or np.min(self.p.fingers()) < 0.95:
                return self._act(self._toward(np.r_[self.p.desired_tcp[:2], target[2]]), False)
            if self._at(target, 0.006):
                self.phase, self.turning, self.timer = "descend", turn, 0
            return self._act(self._toward(target), False)
        if self.phase == "descend":
            target = block + offset + [0.0, 0.0, grip_height]
            self.timer += 1
            if self._at(target, 0.004) or self.timer > self._steps(2.0):  # or stalled on something
                self.phase, self.timer = "close", 0
                self.turns += int(self.turning)
            return self._act(self._toward(target, 0.6), False)
        # close
        self.timer += 1
        closed = self.timer >= self._steps(0.4)
        if closed and (self.turning or self.timer > self._steps(1.5) or not self.holding(i)):
            self.phase = "above"  # turned, or missed: approach again
            self.turning = False
            return self._act(np.zeros(3), False)
        if closed and abs(self.p.block_yaw_error(i)) < HELD_YAW:
            self.phase = "held"
            return None
        return self._act(np.zeros(3), True)

    # ----------------------------------------------------------------- tasks
    def act(self) -> np.ndarray:
        """The next action of the task's script."""
        return TASK_EXPERTS.get(self.task)(self)

    @TASK_EXPERTS.named("open")
    def _task_open(self) -> np.ndarray:
        return self._hover_then(False)

    @TASK_EXPERTS.named("close")
    def _task_close(self) -> np.ndarray:
        return self._hover_then(True)

    def _hover_then(self, close: bool) -> np.ndarray:
        target = self.p.block_pos(0) + [0.0, 0.0, ABOVE]
        if self.phase == "start":
            self.phase = "go"
        if self.phase == "go":
            if self._at(target, 0.01):
                self.phase = "still"
            return self._act(self._toward(target), self.p.gripper_closed)
        return self._act(np.zeros(3), close)

    @TASK_EXPERTS.named("reach")
    def _task_reach(self) -> np.ndarray:
        if self.phase == "start":
            self.phase = "above" if not self.p.gripper_closed else "release"
        if self.phase == "release":
            self.phase = "above"
            return self._act(np.zeros(3), False)
        block = self.p.block_pos(0)
        if self.phase == "above":
            target = block + [0.0, 0.0, ABOVE]
            if self._at(target, 0.006):
                self.phase = "descend"
            return self._act(self._toward(target), False)
        return self._act(self._toward(block, 0.6), False)

    @TASK_EXPERTS.named("grasp")
    def _task_grasp(self) -> np.ndarray:
        a = self._grasp(0)
        return a if a is not None else self._act(np.zeros(3), True)

    @TASK_EXPERTS.named("lift")
    def _task_lift(self) -> np.ndarray:
        a = self._grasp(0)
        if a is not None:
            return a
        return self._act(self._toward(np.r_[self.p.desired_tcp[:2], CARRY_Z], 0.7), True)

    @TASK_EXPERTS.named("move-object")
    def _task_move_object(self) -> np.ndarray:
        a = self._grasp(0)
        if a is not None:
            return a
        if self.circle is None:
            if self.p.desired_tcp[2] < 0.19:
                return self._act(self._toward(np.r_[self.p.desired_tcp[:2], 0.2], 0.7), True)
            radius = 0.05
            centre = np.r_[TRAY_CENTER, 0.2]
            start = self.p.desired_tcp - centre
            self.circle = (centre, float(np.arctan2(start[1], start[0])))
            self.aim = centre + radius * np.r_[np.cos(self.circle[1]), np.sin(self.circle[1]), 0.0]
            return self._act(self._toward(self.aim, 0.6), True)
        centre, angle = self.circle
        if not self._at(self.aim, 0.02) and self.timer == 0:
            return self._act(self._toward(self.aim, 0.6), True)
        self.timer += 1
        angle += 0.12 * self.p.control_dt / 0.05  # 0.12 m/s on a 5 cm circle
        self.circle = (centre, angle)
        self.aim = centre + 0.05 * np.r_[np.cos(angle), np.sin(angle), 0.0]
        return self._act(self._toward(self.aim), True)

    def _place(self, i: int, xy: np.ndarray, z_block: float, precise: bool = False) -> np.ndarray:
        """Carry held block `i` over `xy`, lower its centre to `z_block`, open, retreat."""
        block = self.p.block_pos(i)
        offset = block - self.p.tcp_pos()  # where the block sits in the hand
        if self.phase == "held":
            self.phase = "carry"
        if self.phase in ("carry", "lower") and not self.holding(i):
            self.phase = "start"  # dropped it: the caller grasps again
            return self._act(np.zeros(3), False)
        if self.phase == "carry":
            target = np.r_[xy - offset[:2], CARRY_Z]
            if self._at(target, 0.006):
                self.phase = "lower"
            return self._act(self._toward(target), True)
        if self.phase == "lower":
            target = np.r_[xy - offset[:2], z_block - offset[2]]
            err = xy - block[:2]
            if precise:
                # integral correction on the measured block position: servo error below 1 mm
                target[:2] = self.p.desired_tcp[:2] + 0.5 * err
            if self._at(target, 0.003) and (not precise or np.max(np.abs(err)) < 0.0004):
                self.phase, self.timer = "release", 0
            return self._act(self._toward(target, 0.4), True)
        if self.phase == "release":
            self.timer += 1
            if self.timer > self._steps(0.3):
                self.phase = "retreat"
            return self._act(np.zeros(3), False)
        target = np.r_[self.p.desired_tcp[:2], min(CARRY_Z, block[2] + 0.07)]
        return self._act(self._toward(target, 0.5), False)

    @TASK_EXPERTS.named("stack")
    def _task_stack(self) -> np.ndarray:
        a = self._grasp(0)
        if a is not None:
            return a
        green = self.p.block_pos(1)
        return self._place(0, green[:2], green[2] + 2 * BLOCK_HALF + 0.004)

    def _relocate_green(self, avoid: np.ndarray) -> np.ndarray | None:
        """Move the green block to the free spot farthest from the `avoid` points (xy rows);
        None once done."""
        if self.released:
            return None
        a = self._grasp(1)
        if a is not None:
            return a
        if not np.any(self.aim):
            self.aim = np.r_[_free_spot(avoid), 0.0]
        a = self._place(1, self.aim[:2], BLOCK_REST_Z + 0.003)
        if self.phase == "retreat" and self.p.tcp_pos()[2] > self.p.block_pos(1)[2] + 0.06:
            self.released = True
            self.phase = "start"
            return None
        return a

    def _clear_then(self, target_xy: np.ndarray) -> np.ndarray | None:
        """Relocate green first when it sits within 8 cm of `target_xy` (where blue goes)."""
        if (
            self.phase == "start"
            and not self.released
            and not self.holding(0)
            and np.linalg.norm(self.p.block_pos(1)[:2] - target_xy) > 0.08
        ):
            self.released = True
        if not self.released:
            return self._relocate_green(np.array([target_xy, self.p.block_pos(0)[:2]]))
        return None

    @TASK_EXPERTS.named("unstack-stack")
    def _task_unstack_stack(self) -> np.ndarray:
        if self.phase == "start" and not self.released:
            blue, green = self.p.block_pos(0), self.p.block_pos(1)
            if not (green[2] > blue[2] + BLOCK_HALF and not self.holding(0)):
                self.released = True  # nothing to unstack
        if not self.released:
            a = self._relocate_green(self.p.block_pos(0)[None, :2])
            if a is not None:
                return a
        return self._task_stack()

    @TASK_EXPERTS.named("bring")
    def _task_bring(self) -> np.ndarray:
        a = self._clear_then(ZONE_XY[0])
        if a is not None:
            return a
        a = self._grasp(0)
        if a is not None:
            return a
        return self._place(0, ZONE_XY[0], BLOCK_REST_Z + 0.004)

    @TASK_EXPERTS.named("insert")
    def _task_insert(self) -> np.ndarray:
        a = self._clear_then(ZONE_XY[0])
        if a is not None:
            return a
        # grasp 8 mm above the centre so the held block can go 1 cm down into the slot
        a = self._grasp(0, grip_height=0.008)
        if a is not None:
            return a
        if self.phase == "held" and self.p.block_tilt(0) > MAX_INSERT_TILT:
            # picked up tilted (e.g. out of a slot it fell into): put it down flat, grasp again
            self.reseat = _free_spot(np.vstack([ZONE_XY, self.p.block_pos(1)[:2]]))
        if self.reseat is not None:
            # centre 8 mm up: the lowest corner of a block tilted up to 30 degrees clears the floor
            a = self._place(0, self.reseat, BLOCK_REST_Z + 0.008)
            if self.phase == "retreat" and self.p.tcp_pos()[2] > self.p.block_pos(0)[2] + 0.06:
                self.reseat, self.phase = None, "start"
            return a
        a = self._place(0, INSERT_TARGETS[0, :2], INSERT_TARGETS[0, 2] + 0.0015, precise=True)
        block = self.p.block_pos(0)
        if (
            self.phase == "retreat"
            and self.p.tcp_pos()[2] > block[2] + 0.06
            and np.linalg.norm(block - INSERT_TARGETS[0]) > INSERT_THRESHOLD
        ):
            self.phase = "start"  # it did not go in: grasp again
        return a


class ExpertPolicy:
    """The scripted expert in the policy interface of `shiftkit.policies.evaluation` (a baseline on the
    same seeds as a learned policy). It reads the simulator, so it asks for no observation features."""

    features: dict[str, dict] = {}

    def __init__(self, env: PandaPlayEnv) -> None:
        self.env = env
        self.expert = PandaPlayExpert(env)

    def reset(self) -> None:
        """A fresh expert for the next episode."""
        self.expert = PandaPlayExpert(self.env)

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """The expert's next action (`obs` unused)."""
        return self.expert.act()


# --------------------------------------------------------------------------- the suboptimal expert
# A person demonstrating by teleoperation is not the scripted expert: each demonstration goes at its own
# pace and approaches the block its own way (thesis 5.4.3, Fig. 5.3: "due to the suboptimality of
# human demonstrations, behavioural cloning has high variance", the setting FIRE is meant for). The
# suboptimal expert is the scripted one (still closed-loop on the true state, so it still finishes)
# with that variance, drawn per episode from its own seeded generator. Its demonstrations are slower
# than the scripted expert's and varied, and BC needs more of them (docs/fire.md).
#
# Why only these two: motion noise or misjudged grasps added to the pace, or hesitations and detours
# with them, left BC from 40 demonstrations at 0-2 of 30 held-out successes (seed 0, docs/fire.md): its
# policies reach over the block and stop 1-2 cm above it without ever closing the fingers.
SUBOPTIMAL_SPEED = (0.4, 1.0)
"""Range of the per-episode speed scale of the free motion (each demonstrator keeps a pace); the final
descent and the closing of the fingers stay as the scripted expert does them."""
SUBOPTIMAL_HOVER = (0.03, 0.08)
"""Range of the per-episode height (m) above the block from which grasps descend (the scripted: 5 cm)."""
# phases of the scripted grasp done at the scripted expert's own pace
_CAREFUL = ("descend", "close")


class SuboptimalExpert:
    """The scripted expert of `task` with a person's pace and approach (`SUBOPTIMAL_*` above); `seed`
    draws them."""

    def __init__(self, env: PandaPlayEnv, seed: int, task: str | None = None) -> None:
        self.base = PandaPlayExpert(env, task)
        self.rng = np.random.default_rng([seed, 0x5B0])
        self.reset()

    def reset(self) -> None:
        """A new demonstration: a new pace and hover height."""
        self.base.reset()
        self.speed = self.rng.uniform(*SUBOPTIMAL_SPEED)
        self.base.above = self.rng.uniform(*SUBOPTIMAL_HOVER)

    def act(self) -> np.ndarray:
        """The scripted action, its free motion at this demonstration's pace."""
        action = self.base.act()
        if self.base.phase not in _CAREFUL:
            action[:3] *= self.speed
        return action


class SuboptimalExpertPolicy(ExpertPolicy):
    """The suboptimal expert in the policy interface (`ExpertPolicy`); `seed` draws its variance."""

    def __init__(self, env: PandaPlayEnv, seed: int = 0) -> None:
        self.env, self.seed = env, seed
        self.expert = SuboptimalExpert(env, seed)

    def reset(self) -> None:
        """A fresh suboptimal expert (the same draws for the same seed)."""
        self.expert = SuboptimalExpert(self.env, self.seed)


def suboptimal_rollout(
    env: PandaPlayEnv, seed: int, cameras: tuple[str, ...] = (), depth: bool = False, extra_steps: int = 0
) -> Rollout:
    """One episode of the suboptimal expert from `reset(seed=seed)` (its variance drawn from `seed`),
    recorded as `rollout` records the scripted expert (`shiftkit collect --expert suboptimal`)."""
    return expert_rollout(env, seed, lambda e: SuboptimalExpert(e, seed), cameras, depth, extra_steps)


def _free_spot(avoid: np.ndarray) -> np.ndarray:
    """The FREE_SPOTS entry farthest from the `avoid` points (xy rows)."""
    clearance = np.min(np.linalg.norm(FREE_SPOTS[:, None] - avoid[None], axis=2), axis=1)
    return FREE_SPOTS[np.argmax(clearance)]


def rollout(
    env: PandaPlayEnv,
    seed: int,
    cameras: tuple[str, ...] = (),
    depth: bool = False,
    extra_steps: int = 0,
) -> Rollout:
    """Run the env's task expert from `reset(seed=seed)` until success has held (plus `extra_steps`)
    or the episode is truncated (`envs.rollout.expert_rollout`)."""
    return expert_rollout(env, seed, PandaPlayExpert, cameras, depth, extra_steps)


def play_rollout(
    env: PandaPlayEnv,
    seed: int,
    sequence: tuple[str, ...],
    segment_seconds: float = 8.0,
    cameras: tuple[str, ...] = (),
    depth: bool = False,
) -> Rollout:
    """One play episode: a single reset, then each task of `sequence` run by its expert until that
    task's success holds (or `segment_seconds` pass). Segments record task, start, end (exclusive)
    and success; `success[t]` is the current segment's held success."""
    unknown = [t for t in sequence if t not in TASKS]
    if unknown:
        raise ValueError(f"unknown play task(s) {unknown}; known: {', '.join(TASKS)}")
    rec = RolloutRecorder(env, cameras, depth)
    obs, info = env.reset(seed=seed)
    rec.frame(obs, info)
    segments: list[dict[str, Any]] = []
    limit = int(round(segment_seconds * env.control_hz))
    truncated = False
    for task in sequence:
        expert = PandaPlayExpert(env, task)
        start = len(rec.actions)
        ok = False
        for _ in range(limit):
            action = expert.act()
            obs, _, _, truncated, info = env.step(action)
            ok = env.task_successes()[task]
            rec.actions.append(action)
            rec.success.append(ok)
            rec.frame(obs, info)
            if ok or truncated:
                break
        segments.append({"task": task, "start": start, "end": len(rec.actions), "success": bool(ok)})
        if truncated:
            break
    return rec.done(segments=segments)
