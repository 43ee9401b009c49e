"""Expert success per task over seeded episodes (default 50 per task), for any registered env.

`--env panda-play` (default): the scripted experts (goal >= 0.9). `--env door-tactile --expert
kinesthetic`: the simulated kinesthetic teacher (goal >= 0.95); with `--replay`, every teacher
episode is also replayed by plain position replay (x_raw through the impedance controller, no force
matching) and its success is reported beside it (the thesis expects it to fail often).
Prints a table, then as its last line JSON with metric `min_success_rate`.
"""

from __future__ import annotations

import argparse
import json
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

from tqdm import tqdm  # noqa: E402

from shiftkit.envs import ENV_TASKS, env_family, make  # noqa: E402

GOALS = {"scripted": 0.9, "kinesthetic": 0.95}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="5 seeds per task")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--env", default="panda-play", choices=tuple(ENV_TASKS))
    parser.add_argument("--expert", default="scripted", help="scripted, or a family expert (e.g. kinesthetic)")
    parser.add_argument("--control-hz", type=int, help="default: the env's first control rate")
    parser.add_argument("--tasks", help="comma-separated (default: all of the env's tasks)")
    parser.add_argument("--replay", action="store_true", help="door-tactile: also replay each episode's x_raw")
    args = parser.parse_args()
    family = env_family(args.env)
    record = family.rollout if args.expert == "scripted" else family.experts[args.expert]
    hz = args.control_hz or family.control_rates[0]
    n = 5 if args.quick else args.episodes
    tasks = args.tasks.split(",") if args.tasks else list(ENV_TASKS[args.env])
    rates, lengths, failed, replay_rates = {}, {}, {}, {}
    start = time.time()
    print(f"{'task':18s} {'success':>9s} {'mean len':>9s} {'replay':>7s}  failed seeds")
    for task in tasks:
        env = make(args.env, task, control_hz=hz)
        ok, length, fails, replayed = 0, 0, [], 0
        for seed in tqdm(range(n), desc=task, leave=False):
            r = record(env, seed)
            ok += r.succeeded
            length += len(r.actions)
            if not r.succeeded:
                fails.append(seed)
            if args.replay:
                from shiftkit.envs.door_tactile import replay_positions

                warmup = r.meta["recording_start_step"]
                replayed += replay_positions(env, seed, r.arrays["ee_pose"], r.actions[:, 6], warmup).succeeded
        env.close()
        rates[task], lengths[task], failed[task] = ok / n, length / n, fails
        replay = f"{replayed / n:7.2f}" if args.replay else f"{'-':>7s}"
        if args.replay:
            replay_rates[task] = replayed / n
        print(f"{task:18s} {rates[task]:9.2f} {lengths[task]:9.1f} {replay}  {fails}", flush=True)
    worst = min(rates, key=rates.get)
    result = {
        "bench": "expert_success",
        "metric": "min_success_rate",
        "value": rates[worst],
        "goal": GOALS.get(args.expert, 0.9),
        "higher_is_better": True,
        "env": args.env,
        "expert": args.expert,
        "worst_task": worst,
        "episodes_per_task": n,
        "control_hz": hz,
        "success": rates,
        "mean_length": lengths,
        "failed_seeds": failed,
        "seconds": round(time.time() - start, 1),
    }
    if args.replay:
        result["position_replay_success"] = replay_rates
    print(json.dumps(result))


if __name__ == "__main__":
    main()
