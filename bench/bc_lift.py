"""BC learning check on Panda lift: BC from 50 scripted-expert episodes
(state observations) must succeed on >= 80% of 50 held-out seeds.

Steps, all through shiftkit's own entry points:
1. `shiftkit collect --env panda-play --task lift --episodes 50 --seed 0 --lerobot ...` (seeds 0-49);
2. `shiftkit train bc` on `observation.state` + `observation.environment_state` (default regime:
   early stopping on a 20% episode hold-out; one network, `--ensemble 5` for the thesis' ensemble);
3. evaluation on seeds 1000-1049, which no training episode used; the baseline, in the same run, is
   the scripted expert on the same seeds.

    python bench/bc_lift.py [--quick] [--regime early-stop|fixed] [--ensemble N] [--workdir DIR]

Last line: {"bench": "bc_lift", "metric": "success_rate", "value": ..., "goal": 0.8, ...}
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import _device  # bench/, beside this file

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="smoke run: 10 episodes, short training, 5 eval seeds")
    parser.add_argument("--regime", choices=("early-stop", "fixed"), default="early-stop")
    parser.add_argument("--ensemble", type=int, default=1, help="BC ensemble members (default 1, the trainer's)")
    parser.add_argument("--episodes", type=int, help="training episodes (default 50, quick 10)")
    parser.add_argument("--eval-episodes", type=int, help="held-out evaluation seeds (default 50, quick 5)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    parser.add_argument("--workdir", help="keep dataset and run here (default: a temporary folder)")
    args = parser.parse_args()
    episodes = args.episodes or (10 if args.quick else 50)
    eval_episodes = args.eval_episodes or (5 if args.quick else 50)
    tmp = None if args.workdir else tempfile.TemporaryDirectory(prefix="bench-bc-lift-")
    work = Path(args.workdir or tmp.name)
    work.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("HF_DATASETS_CACHE", str(work / "hf-cache"))

    from shiftkit.app.collect import CollectConfig, collect
    from shiftkit.envs import make
    from shiftkit.envs.panda_play.experts import ExpertPolicy
    from shiftkit.policies.bc_policy import load_policy
    from shiftkit.policies.evaluation import evaluate, record_evaluation, run_episodes, wilson_interval
    from shiftkit.policies.trainers.bc.args import BCArgs
    from shiftkit.policies.trainers.bc.training import train

    dataset, run = work / f"lift{episodes}", work / f"bc-{args.regime}"
    t0 = time.perf_counter()
    if not dataset.exists():
        collect(
            CollectConfig(task="lift", episodes=episodes, seed=0, lerobot=f"local/lift{episodes}", root=str(dataset))
        )
    collect_s = time.perf_counter() - t0

    t0 = time.perf_counter()
    quick = dict(steps=600) if args.quick else {}
    train(
        BCArgs(
            datasets=[str(dataset)],
            output_dir=str(run),
            regime=args.regime,
            threads=args.threads,
            inputs=["observation.state", "observation.environment_state"],
            ensemble_size=args.ensemble,
            resume=run.exists(),
            **quick,
        )
    )
    train_s = time.perf_counter() - t0

    t0 = time.perf_counter()
    policy = load_policy(run)
    report = evaluate(policy, "panda-play", "lift", eval_episodes, seed=1000, policy_name=str(run))
    record_evaluation(report, run)
    eval_s = time.perf_counter() - t0

    env = make("panda-play", "lift")
    expert = run_episodes(ExpertPolicy(env), env, eval_episodes, seed=1000)
    env.close()
    expert_rate = sum(e.success for e in expert) / len(expert)

    s = report.summary()
    train_steps = json.loads((run / "metrics.jsonl").read_text().splitlines()[-1])["step"]
    print(f"collect {collect_s:.0f}s, train {train_s:.0f}s ({train_steps} steps/member), eval {eval_s:.0f}s")
    print(
        f"BC success {s['successes']}/{s['episodes']} = {s['success_rate']:.0%}, 95% CI "
        f"[{s['ci95'][0]:.0%}, {s['ci95'][1]:.0%}]; expert on the same seeds {expert_rate:.0%}"
    )
    print(
        json.dumps(
            {
                "bench": "bc_lift",
                "metric": "success_rate",
                "value": s["success_rate"],
                "goal": 0.8,
                "higher_is_better": True,
                "ci95": s["ci95"],
                "expert_success_rate": expert_rate,
                "expert_ci95": list(wilson_interval(sum(e.success for e in expert), len(expert))),
                "train_episodes": episodes,
                "eval_episodes": eval_episodes,
                "eval_seeds": [1000, 1000 + eval_episodes - 1],
                "regime": args.regime,
                "ensemble": args.ensemble,
                "train_steps": train_steps,
                "collect_s": round(collect_s, 1),
                "train_s": round(train_s, 1),
                "eval_s": round(eval_s, 1),
                # the trainer's --device auto trains on it when present
                "gpu": _device.gpu_info(),
                "quick": args.quick,
            }
        )
    )


if __name__ == "__main__":
    main()
