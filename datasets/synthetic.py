"""Synthetic raw datasets: a seeded point-reaching recording with the raw format's usual arrays,
for tests, benchmarks and trying pipelines without a robot or simulator."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from shiftkit.datasets.sources.raw import RawDatasetWriter


def write_synthetic_raw(
    out_dir: str | Path,
    episodes: int = 4,
    length: int = 20,
    seed: int = 0,
    fps: int = 10,
    camera: tuple[int, int] | None = None,
    tasks: tuple[str, ...] = ("reach",),
) -> Path:
    """A point robot moves towards a random goal under a P-controller with noise.

    State (x, y, z, gripper), environment state = goal (x, y, z), action = commanded delta
    (dx, dy, dz, gripper); `success` once within 2 cm of the goal. `camera=(h, w)` adds an RGB
    image that draws the robot and goal as coloured squares.
    """
    rng = np.random.default_rng(seed)
    names = {
        "state": ["ee_x", "ee_y", "ee_z", "gripper"],
        "environment_state": ["goal_x", "goal_y", "goal_z"],
        "action": ["dx", "dy", "dz", "gripper"],
    }
    with RawDatasetWriter(out_dir, fps=fps, robot="point", env="synthetic", names=names) as writer:
        for e in range(episodes):
            n = int(length + rng.integers(-length // 4, length // 4 + 1)) if length >= 4 else length
            pos = rng.uniform(-0.1, 0.1, 3)
            goal = rng.uniform(-0.1, 0.1, 3)
            states, actions, success = [], [], []
            for _ in range(n):
                delta = np.clip(0.3 * (goal - pos) + rng.normal(0, 0.002, 3), -0.02, 0.02)
                grip = 1.0 if np.linalg.norm(goal - pos) > 0.03 else -1.0
                states.append([*pos, grip])
                actions.append([*delta, grip])
                pos = pos + delta
                success.append(bool(np.linalg.norm(goal - pos) < 0.02))
            arrays = {
                "timestamp": np.arange(n, dtype=np.float64) / fps,
                "state": np.asarray(states, dtype=np.float32),
                "environment_state": np.repeat(goal[None].astype(np.float32), n, axis=0),
                "action": np.asarray(actions, dtype=np.float32),
                "success": np.asarray(success),
            }
            images = {}
            if camera is not None:
                images["front"] = np.stack([_draw(s[:3], goal, camera) for s in arrays["state"]])
            task = tasks[e % len(tasks)]
            writer.add_episode(
                arrays,
                images=images,
                meta={
                    "task": task,
                    "outcome": "success" if success[-1] else "failure",
                    "seed": seed * 100003 + e,
                },
            )
    return Path(out_dir)


def _draw(pos: np.ndarray, goal: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    h, w = size
    img = np.full((h, w, 3), 40, dtype=np.uint8)
    for p, colour in ((goal, (0, 200, 0)), (pos, (220, 60, 60))):
        r, c = int((p[1] + 0.15) / 0.3 * (h - 1)), int((p[0] + 0.15) / 0.3 * (w - 1))
        img[max(r - 1, 0) : r + 2, max(c - 1, 0) : c + 2] = colour
    return img
