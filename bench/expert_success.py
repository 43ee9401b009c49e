"""Scripted-expert success per Panda play task over seeded episodes (default 50 per task).

Prints a table, then as its last line JSON with metric `min_success_rate` (goal >= 0.9).
"""

from __future__ import annotations

import argparse
import json
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

from shiftkit.envs import ENV_TASKS, make  # noqa: E402
from shiftkit.envs.panda_play.experts import rollout  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="5 seeds per task (under a minute)")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--control-hz", type=int, default=20, choices=(5, 20))
    parser.add_argument("--tasks", default=",".join(ENV_TASKS["panda-play"]))
    args = parser.parse_args()
    n = 5 if args.quick else args.episodes
    rates, lengths, failed = {}, {}, {}
    start = time.time()
    print(f"{'task':15s} {'success':>9s} {'mean len':>9s}  failed seeds")
    for task in args.tasks.split(","):
        env = make("panda-play", task, control_hz=args.control_hz)
        results = [rollout(env, seed) for seed in range(n)]
        env.close()
        rates[task] = sum(r.succeeded for r in results) / n
        lengths[task] = sum(len(r.actions) for r in results) / n
        failed[task] = [s for s, r in enumerate(results) if not r.succeeded]
        print(f"{task:15s} {rates[task]:9.2f} {lengths[task]:9.1f}  {failed[task]}", flush=True)
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
                "control_hz": args.control_hz,
                "success": rates,
                "mean_length": lengths,
                "failed_seeds": failed,
                "seconds": round(time.time() - start, 1),
            }
        )
    )


if __name__ == "__main__":
    main()
