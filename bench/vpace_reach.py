"""VPACE learning check on Panda reach (acceptance check, docs/vpace.md): from 200 success examples per task,
the main intention must reach >= 90% success.

Steps, all through shiftkit's own entry points:
1. one LeRobot example dataset with 200 examples per task, from either source (`--examples`):
   * `published` (default): `shiftkit import vpace` of the VPACE authors' reach and lift example files
     (shared/data/vpace beside the checkout, or beside a folder above it), recorded in their own simulator; auxiliary task lift;
   * `scene`: final states of scripted-expert episodes in shiftkit's Panda play scene,
     `shiftkit collect --task reach|open --control-hz 5 --only-successful` + the `success_examples`
     stage; auxiliary task open (the thesis' pairing for reach). See docs/vpace.md for how the two
     compare;
2. `shiftkit train vpace --main-task reach --aux-tasks open|lift --env-kwarg control_hz=5
   --examples-per-task 200` with the thesis hyperparameters, evaluating the main intention (mean action)
   every `--eval-every` environment steps (the success curve);
3. a final evaluation on `--final-episodes` seeds that neither training nor the curve used, of the
   policy at its best curve point (checkpoints/best.safetensors, the value) and of the last checkpoint; the
   baseline, in the same run, is the scripted reach expert on the same seeds.

    python bench/vpace_reach.py [--quick] [--examples published|scene] [--total-steps N] [--workdir DIR]

Last line: {"bench": "vpace_reach", "metric": "success_rate", "value": (best checkpoint), "goal": 0.9,
            "last_success_rate": ..., "curve": ...}
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

PUBLISHED_FILES = ("examples_1200_4_reach.gz", "examples_1200_3_lift.gz")
AUX_TASK = {"published": "lift", "scene": "open"}  # the auxiliary task each example source provides
FINAL_SEED = 5000  # training resets use seed * 1e6 + episode; periodic evaluations 1_000_003 + ...
COLLECT_SEED = 100_000  # scripted episodes for scene examples: seeds no training or evaluation reset uses
COLLECT_EPISODES = 240  # scripted episodes per task (failures skipped), enough for the 200 examples kept


def scene_examples(dest: Path, work: Path, tasks: list[str]) -> None:
    """200 final states per task of successful scripted-expert episodes at 5 Hz, one example dataset at
    `dest`; the raw episodes are kept in `work` (written atomically, so a rerun reuses them)."""
    from shiftkit.app.collect import CollectConfig, collect
    from shiftkit.datasets.sources import SourceConfig
    from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, StageSpec
    from shiftkit.pipelines.runner import run_pipeline

    raws = []
    for i, task in enumerate(tasks):
        raw = work / f"{task}-raw"
        if not raw.exists():
            collect(
                CollectConfig(
                    env="panda-play",
                    task=task,
                    episodes=COLLECT_EPISODES,
                    control_hz=5,
                    seed=COLLECT_SEED + i * COLLECT_EPISODES,
                    out=str(raw),
                    only_successful=True,
                )
            )
        raws.append(SourceConfig(path=str(raw)))
    run_pipeline(
        PipelineConfig(
            sources=raws,
            destination=DestinationConfig(root=str(dest), repo_id="local/panda-examples"),
            stages=[StageSpec("success_examples", {"n_per_task": 200, "states": "final"})],
        ),
        progress=False,
    )


def default_data() -> Path:
    """The first `shared/data/vpace` beside the checkout or beside one of its parent folders."""
    checkout = Path(__file__).resolve().parents[1]
    candidates = [parent / "shared" / "data" / "vpace" for parent in checkout.parents]
    return next((c for c in candidates if c.is_dir()), candidates[0])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="smoke run: 2500 steps, 5 evaluation episodes")
    parser.add_argument("--total-steps", type=int, help="environment steps (default 100000)")
    parser.add_argument("--eval-every", type=int, help="steps between curve points (default 10000)")
    parser.add_argument("--eval-episodes", type=int, default=20, help="episodes per curve point")
    parser.add_argument("--final-episodes", type=int, help="episodes of the final evaluation (default 50)")
    parser.add_argument(
        "--examples",
        choices=("published", "scene"),
        default="published",
        help="example source: the published files (default) or scripted episodes in shiftkit's scene",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    parser.add_argument(
        "--data",
        default=str(default_data()),
        help="folder with the published VPACE example files (default: shared/data/vpace next to the"
        " checkout or next to a folder above it, as for a git worktree)",
    )
    parser.add_argument("--workdir", help="keep dataset and run here (default: a temporary folder)")
    args = parser.parse_args()
    quick = dict(total_steps=2500, buffer_warmup=1500, random_steps=1500, eval_every=2500) if args.quick else {}
    total_steps = args.total_steps or quick.get("total_steps", 100_000)
    eval_every = args.eval_every or quick.get("eval_every", 10_000)
    final_episodes = args.final_episodes or (5 if args.quick else 50)
    eval_episodes = 5 if args.quick else args.eval_episodes
    tmp = None if args.workdir else tempfile.TemporaryDirectory(prefix="bench-vpace-reach-")
    work = Path(args.workdir or tmp.name)
    work.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("HF_DATASETS_CACHE", str(work / "hf-cache"))

    from shiftkit.app.importers.vpace import import_vpace
    from shiftkit.envs import make
    from shiftkit.envs.panda_play.experts import ExpertPolicy
    from shiftkit.policies.evaluation import evaluate, run_episodes, wilson_interval
    from shiftkit.policies.run_dir import BEST, RunDir, load_checkpoint
    from shiftkit.policies.trainers.vpace.args import VPACEArgs
    from shiftkit.policies.trainers.vpace.training import load_policy, train

    aux = AUX_TASK[args.examples]
    examples, run = work / f"{args.examples}-examples", work / f"vpace-reach-{args.examples}-seed{args.seed}"
    if not examples.exists():
        if args.examples == "scene":
            scene_examples(examples, work, ["reach", aux])
        else:
            import_vpace([Path(args.data) / f for f in PUBLISHED_FILES], "local/vpace-examples", examples)
    env_kwargs = {"control_hz": 5}
    t0 = time.perf_counter()
    train(
        VPACEArgs.for_variant(
            "vpace",
            examples=[str(examples)],
            env="panda-play",
            main_task="reach",
            aux_tasks=[aux],
            output_dir=str(run),
            examples_per_task=200,
            env_kwargs=env_kwargs,
            seed=args.seed,
            torch_threads=args.threads,
            eval_episodes=eval_episodes,
            resume=run.exists(),
            **(quick | dict(total_steps=total_steps, eval_every=eval_every)),
        )
    )
    train_s = time.perf_counter() - t0

    t0 = time.perf_counter()
    best = run / "checkpoints" / BEST  # absent when no curve point was taken (--total-steps < --eval-every)
    held_out = {
        name: evaluate(
            load_policy(path),
            "panda-play",
            "reach",
            final_episodes,
            seed=FINAL_SEED,
            policy_name=str(path),
            env_kwargs=env_kwargs,
        ).summary()
        for name, path in (("best", best), ("last", run))
        if path.exists()
    }
    eval_s = time.perf_counter() - t0
    env = make("panda-play", "reach", **env_kwargs)
    expert = run_episodes(ExpertPolicy(env), env, final_episodes, seed=FINAL_SEED)
    env.close()
    expert_successes = sum(e.success for e in expert)

    curve = [[r["step"], r["success_rate"]] for r in RunDir(run, resume=True).read_metrics() if r["split"] == "eval"]
    best_step = load_checkpoint(best)["step"] if best.exists() else None
    for step, rate in curve:
        print(f"step {step:>7}: main-task success {rate:.0%} ({eval_episodes} episodes)")
    print(f"train {train_s:.0f}s for {total_steps} env steps, final evaluations {eval_s:.0f}s")
    for name, s in held_out.items():
        print(
            f"VPACE reach, {name} checkpoint: success {s['successes']}/{s['episodes']} = {s['success_rate']:.0%}, "
            f"95% CI [{s['ci95'][0]:.0%}, {s['ci95'][1]:.0%}]"
        )
    print(f"expert on the same seeds {expert_successes}/{len(expert)}; best curve point at step {best_step}")
    s = held_out.get("best", held_out["last"])
    print(
        json.dumps(
            {
                "bench": "vpace_reach",
                "metric": "success_rate",
                "value": s["success_rate"],
                "goal": 0.9,
                "higher_is_better": True,
                "ci95": s["ci95"],
                "best_step": best_step,
                "last_success_rate": held_out["last"]["success_rate"],
                "last_ci95": held_out["last"]["ci95"],
                "expert_success_rate": expert_successes / len(expert),
                "expert_ci95": list(wilson_interval(expert_successes, len(expert))),
                "curve": curve,
                "env_steps": total_steps,
                "examples": args.examples,
                "aux_task": aux,
                "examples_per_task": 200,
                "final_episodes": final_episodes,
                "final_seeds": [FINAL_SEED, FINAL_SEED + final_episodes - 1],
                "seed": args.seed,
                "train_s": round(train_s, 1),
                "eval_s": round(eval_s, 1),
                # the trainer's --device auto trains on it when present
                "gpu": _device.gpu_info(),
                "threads": args.threads,
                "quick": args.quick,
            }
        )
    )


if __name__ == "__main__":
    main()
