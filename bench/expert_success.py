"""Scripted-expert success per task over seeded episodes (default 50 per task).

`--env panda-play` (default) runs the Panda play tasks; `--env multiview` runs the four multiview
envs (mv-lift, mv-stack, mv-pick-insert, mv-door) in both views (fixed, multiview).
Prints a table, then as its last line JSON with metric `min_success_rate` (goal >= 0.9).
"""

from __future__ import annotations

import argparse
import json
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

from shiftkit.envs import ENV_TASKS, env_family, make  # noqa: E402

MULTIVIEW_ENVS = ("mv-lift", "mv-stack", "mv-pick-insert", "mv-door")


def _runs(args: argparse.Namespace) -> list[tuple[str, str, str, dict]]:
    """(row label, env, task, make kwargs) for every row of the table."""
    if args.env == "multiview":
        return [
            (f"{env}/{view}", env, ENV_TASKS[env][0], {"view": view})
            for env in MULTIVIEW_ENVS
            for view in ("fixed", "multiview")
        ]
    tasks = args.tasks.split(",") if args.tasks else ENV_TASKS[args.env]
    return [(task, args.env, task, {"control_hz": args.control_hz}) for task in tasks]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="5 seeds per task (under a minute)")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--env", default="panda-play", help="panda-play, or multiview (the four mv-* envs)")
    parser.add_argument("--control-hz", type=int, default=20, choices=(5, 20), help="panda-play only")
    parser.add_argument("--tasks", default="", help="comma-separated panda-play tasks (default: all)")
    args = parser.parse_args()
    n = 5 if args.quick else args.episodes
    rates, lengths, failed = {}, {}, {}
    start = time.time()
    print(f"{'task':25s} {'success':>9s} {'mean len':>9s}  failed seeds")
    for task, env_name, env_task, kwargs in _runs(args):
        env = make(env_name, env_task, **kwargs)
        rollout = env_family(env_name).rollout
        results = [rollout(env, seed) for seed in range(n)]
        env.close()
        rates[task] = sum(r.succeeded for r in results) / n
        lengths[task] = sum(len(r.actions) for r in results) / n
        failed[task] = [s for s, r in enumerate(results) if not r.succeeded]
        print(f"{task:25s} {rates[task]:9.2f} {lengths[task]:9.1f}  {failed[task]}", flush=True)
    worst = min(rates, key=rates.get)
    print(
        json.dumps(
            {
                "bench": "expert_success",
                "metric": "min_success_rate",
                "value": rates[worst],
                "goal": 0.9,
                "higher_is_better": True,
                "worst_task": worst,
                "episodes_per_task": n,
                "env": args.env,
                "success": rates,
                "mean_length": lengths,
                "failed_seeds": failed,
                "seconds": round(time.time() - start, 1),
            }
        )
    )


if __name__ == "__main__":
    main()
