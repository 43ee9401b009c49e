"""Panda play throughput: env steps/s at 20 Hz control vs a bare `mj_step` loop on the same model
with the same substeps, and 64x48 RGB render fps vs a bare `mujoco.Renderer` loop on the same
scene (same camera, geom groups and scene flags), measured in one run.

Last line: JSON with metric `step_ratio` (goal >= 0.7) and `render_ratio` (goal >= 0.8) in details.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections.abc import Callable

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from shiftkit.envs import make  # noqa: E402
from shiftkit.envs.cameras import disable_costly_flags, scene_option  # noqa: E402


def _best_rates(
    loops: dict[str, Callable[[int], None]], n: int, rounds: int, prepare: Callable[[], None] = lambda: None
) -> dict[str, float]:
    """Calls per CPU second of each `loops[name](n)` (after an untimed `prepare()`), best of
    `rounds`. CPU time, not wall time: on the shared machine this process is often descheduled.
    The loops alternate inside every round, so what other processes still cost (caches, memory
    bandwidth) hits them alike, and the best rounds are the least disturbed ones."""
    best = dict.fromkeys(loops, 0.0)
    for _ in range(rounds):
        for name, fn in loops.items():
            prepare()
            t = time.process_time()
            fn(n)
            best[name] = max(best[name], n / (time.process_time() - t))
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="short run (under a minute)")
    args = parser.parse_args()
    steps, frames, rounds = (200, 100, 8) if args.quick else (500, 300, 20)

    env = make("panda-play", "lift", control_hz=20, width=64, height=48, render_quality="fast")
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (steps, 4)).astype(np.float32)

    def env_loop(n: int) -> None:
        for i in range(n):
            env.step(actions[i % len(actions)])

    # the baseline replays the controls the env produced, from the same reset state, so both
    # loops simulate the same motion and contacts
    model = env.physics.model
    env.reset(seed=0)
    start = (env.physics.data.qpos.copy(), env.physics.data.qvel.copy())
    controls = []
    for a in actions:
        env.step(a)
        controls.append(env.physics.data.ctrl.copy())
    data = mujoco.MjData(model)
    substeps = env.physics.n_substeps

    def bare_loop(n: int) -> None:
        for i in range(n):
            data.ctrl[:] = controls[i % len(controls)]
            mujoco.mj_step(model, data, nstep=substeps)

    def to_start() -> None:
        env.reset(seed=0)
        data.qpos[:], data.qvel[:] = start

    rates = _best_rates({"env": env_loop, "bare": bare_loop}, steps, rounds, prepare=to_start)
    env_sps, bare_sps = rates["env"], rates["bare"]

    env.render_rgb()  # create the renderer before timing

    def env_render(n: int) -> None:
        for _ in range(n):
            env.render_rgb("front")

    renderer = mujoco.Renderer(model, height=48, width=64)
    option = scene_option("fast")
    disable_costly_flags(renderer.scene)
    bare_data = env.physics.data

    def bare_render(n: int) -> None:
        for _ in range(n):
            renderer.update_scene(bare_data, camera="front", scene_option=option)
            renderer.render()

    fps = _best_rates({"env": env_render, "bare": bare_render}, frames, rounds)
    env_fps, bare_fps = fps["env"], fps["bare"]
    renderer.close()
    env.close()
    result = {
        "bench": "env_throughput",
        "metric": "step_ratio",
        "value": round(env_sps / bare_sps, 3),
        "goal": 0.7,
        "higher_is_better": True,
        "env_steps_per_s": round(env_sps, 1),
        "bare_mj_step_loops_per_s": round(bare_sps, 1),
        "substeps": substeps,
        "render_ratio": round(env_fps / bare_fps, 3),
        "render_goal": 0.8,
        "env_render_fps": round(env_fps, 1),
        "bare_render_fps": round(bare_fps, 1),
        "image": "64x48 rgb, fast geometry, shadows/reflections/skybox off",
        "quick": args.quick,
    }
    print(json.dumps(result))


if __name__ == "__main__":
    main()
