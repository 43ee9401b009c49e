"""Expert success per task over seeded episodes (default 50 per task), for any registered env.

`--env panda-play` (default): the scripted experts (goal >= 0.9). `--env mv-lift,mv-stack,mv-pick-insert,mv-door
--views fixed,multiview`: the multiview envs' experts in both views (goal >= 0.9). `--env door-tactile --expert
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


def _csv(text: str | None) -> list[str]:
    return [x.strip() for x in (text or "").split(",") if x.strip()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="5 seeds per task")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--env", default="panda-play", help="env name(s), comma-separated")
    parser.add_argument("--views", help="comma-separated `view` values for envs that take one (fixed,multiview)")
    parser.add_argument("--expert", default="scripted", help="scripted, or a family expert (e.g. kinesthetic)")
    parser.add_argument("--control-hz", type=int, help="default: the env's first control rate")
    parser.add_argument("--tasks", help="comma-separated (default: all of the env's tasks)")
    parser.add_argument("--replay", action="store_true", help="door-tactile: also replay each episode's x_raw")
    args = parser.parse_args()
    envs = _csv(args.env)
    unknown = [e for e in envs if e not in ENV_TASKS]
    if unknown:
        parser.error(f"unknown env(s) {unknown}; known: {', '.join(ENV_TASKS)}")
    views = _csv(args.views) or [None]
    n = 5 if args.quick else args.episodes
    rates, lengths, failed, replay_rates = {}, {}, {}, {}
    start = time.time()
    print(f"{'task':32s} {'success':>9s} {'mean len':>9s} {'replay':>7s}  failed seeds")
    for env_name in envs:
        family = env_family(env_name)
        record = family.rollout if args.expert == "scripted" else family.experts[args.expert]
        hz = args.control_hz or family.control_rates[0]
        tasks = _csv(args.tasks) or list(ENV_TASKS[env_name])
        for view in views:
            kwargs = {"control_hz": hz} | ({"view": view} if view else {})
            for task in tasks:
                row = "/".join(x for x in (env_name if len(envs) > 1 else "", task, view or "") if x)
                env = make(env_name, task, **kwargs)
                ok, length, fails, replayed = 0, 0, [], 0
                for seed in tqdm(range(n), desc=row, leave=False):
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
                rates[row], lengths[row], failed[row] = ok / n, length / n, fails
                replay = f"{replayed / n:7.2f}" if args.replay else f"{'-':>7s}"
                if args.replay:
                    replay_rates[row] = replayed / n
                print(f"{row:32s} {rates[row]:9.2f} {lengths[row]:9.1f} {replay}  {fails}", flush=True)
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
