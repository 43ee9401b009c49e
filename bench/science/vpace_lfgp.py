"""VPACE learns lift from success examples alone (thesis ch. 7) and LfGP beats single-task DAC (thesis
ch. 6), in the panda-play env at 5 Hz (90-step episodes), over seeds, at the reference code's settings.

Task sets and interaction budgets of the reference code at 5 Hz (utiasSTARS/vpace `env_default_configs.py`):
* VPACE on lift: main task lift, auxiliary tasks open, close and reach (`expert_filenames =
  0_stack-open,1_close,3_lift,4_reach`), weighted random scheduler without handcrafted sequences,
  `--lift-steps` 200000 interactions; its baseline single-task SQIL on lift, the same budget;
* LfGP on stack (the thesis' comparison): main task stack, auxiliary tasks open, close, lift, reach
  and move-object (`0_stack-open,1_close,2_stack,3_lift,4_reach,5_move`), the thesis' handcrafted
  Panda sequences (`--handcrafted panda-lfgp`, thesis 6.6.2), `--stack-steps` 500000 (the thesis' 2M at
  20 Hz in robot time); its baseline single-task DAC on the stack trajectories alone
  (`train lfgp --no-multitask`, which sees expert trajectories as LfGP does). LfGP and DAC keep the
  trainer's `lfgp` preset, thesis Table A.2 (docs/vpace.md);
* `--lfgp-task lift` runs LfGP against DAC on lift instead, with VPACE's lift tasks and budget: a
  shorter multitask comparison (LfGP on lift), for machines where stack does not fit.
`--methods` picks which of vpace, sqil, lfgp, dac run.

Data, each made once with shiftkit's own commands (docs/vpace.md, docs/success_examples.md):
* success examples for VPACE: `shiftkit collect --task T --control-hz 5 --only-successful` of
  `--example-episodes` (default 240) scripted-expert episodes for each of lift, open, close and reach,
  then `shiftkit run docs/pipelines/vpace_lift_examples.toml` (the `success_examples` stage, a seeded
  200 final states per task): one example dataset, as bench/vpace_reach.py's `--examples scene`;
* expert trajectories for LfGP and DAC: `--demos` (default 10) successful scripted episodes per task
  (LeRobot datasets, each frame labelled with its task).

Every run evaluates its main intention (mean action) every `--eval-every` interactions on
`--eval-episodes` episodes (metrics.jsonl, `split == "eval"`: the success curve; the reference: 50
episodes every 10k on lift), and its last checkpoint is evaluated at the end on `--final-episodes`
held-out episodes (`shiftkit eval`, seeds 600000 onwards, which no training reset, curve evaluation or
recording uses). Runs write a checkpoint every `--checkpoint-every` interactions: a rerun with the same
`--workdir` reuses the data, finished runs (their card.json) and evaluations, and resumes an
unfinished run from its newest checkpoint (one without any checkpoint starts again). Once the data
exists, further processes with the same `--workdir` and their own `--seeds`/`--methods` can run side
by side. The quick run prints each training's CPU time as `train_cpu_s`; docs/vpace.md has the
measured costs per interaction.

Reported: per method the success curve over seeds, interquartile mean with stratified-bootstrap 95%
CIs (`_study.iqm_ci`, rliable's convention, scipy's bootstrap, seed 0), over the evaluation steps
every seed reached; and the final success pooled over seeds with its Wilson 95% interval
(`_study.pool`). `shiftkit plot curves VPACE=RUN,RUN,... SQIL=... --out lift.png` draws the same
curves. Last line: the JSON result, VPACE's final success minus SQIL's on lift (or, without them,
LfGP's minus DAC's), both gaps where they ran, the curves and every run. `--quick`: one seed, 200
interactions per run (100 random before the first update, curve points at 100 and 200), 3 scripted
episodes per example set and trajectory set, 1-episode evaluations: every command of the full run,
its numbers mean nothing.
"""

from __future__ import annotations

import os
from pathlib import Path

from _study import (
    arguments,
    choices_of,
    docs_pipeline,
    evaluate,
    iqm_ci,
    pool,
    report,
    resumable,
    seeds_of,
    shiftkit,
    workspace,
)

from shiftkit.policies.curves import read_success

HZ = ["--control-hz", "5"]
# The reference's task sets, main task first (utiasSTARS/vpace env_default_configs.py).
EXAMPLE_TASKS = ("lift", "open", "close", "reach")
LFGP_TASKS = {
    "stack": ("stack", "open", "close", "lift", "reach", "move-object"),
    "lift": EXAMPLE_TASKS,
}
HANDCRAFTED = {"stack": ["--handcrafted", "panda-lfgp"], "lift": []}  # the reference's lift: WRS alone
LIFT_STEPS, STACK_STEPS = 200_000, 500_000  # the reference at 5 Hz; stack: the thesis' 2M at 20 Hz in robot time
METHODS = ("vpace", "sqil", "lfgp", "dac")
EXAMPLE_SEED, DEMO_SEED, FINAL_SEED = 100_000, 300_000, 600_000  # + 10000 per task; training uses seed * 1e6 + ep
DEMO_ORDER = ("stack", "reach", "lift", "move-object", "open", "close")  # demo seeds by position, stable


def collect(task: str, episodes: int, seed: int, root: Path, env: dict[str, str]) -> None:
    """Successful scripted-expert episodes of `task` at 5 Hz, a LeRobot dataset at `root` (kept for reruns)."""
    if not root.exists():
        shiftkit(
            "collect", "--env", "panda-play", "--task", task, "--episodes", str(episodes), "--seed", str(seed),
            *HZ, "--only-successful", "--lerobot", f"local/{root.name}", "--root", str(root), "--no-progress",
            env=env,
        )  # fmt: skip


def curve(runs: list[Path]) -> dict:
    """IQM success and its 95% CI at each evaluation step every run reached."""
    points = [read_success(run)[1] for run in runs]
    steps = sorted(set.intersection(*(set(p) for p in points)))
    stats = [iqm_ci([p[step] for p in points]) for step in steps]
    return {
        "steps": steps,
        "iqm": [round(m, 4) for m, _, _ in stats],
        "ci95": [[round(lo, 4), round(hi, 4)] for _, lo, hi in stats],
        "runs": len(runs),
    }


def main() -> None:
    parser = arguments(__doc__)
    parser.add_argument("--methods", default=",".join(METHODS), help="methods to run (default: all four)")
    parser.add_argument(
        "--lfgp-task", choices=tuple(LFGP_TASKS), default="stack", help="LfGP vs DAC main task (default: stack)"
    )
    parser.add_argument("--lift-steps", type=int, default=LIFT_STEPS, help="interactions per lift run (200000)")
    parser.add_argument("--stack-steps", type=int, default=STACK_STEPS, help="interactions per stack run (500000)")
    parser.add_argument("--eval-every", type=int, default=10_000, help="interactions between curve points (10000)")
    parser.add_argument("--eval-episodes", type=int, default=50, help="episodes per curve point (default: 50)")
    parser.add_argument("--final-episodes", type=int, default=50, help="held-out episodes per run (default: 50)")
    parser.add_argument("--checkpoint-every", type=int, default=20_000, help="interactions between checkpoints")
    parser.add_argument(
        "--example-episodes", type=int, default=240, help="scripted episodes per example task (default: 240)"
    )
    parser.add_argument("--demos", type=int, default=10, help="expert trajectories per LfGP task (default: 10)")
    args = parser.parse_args()
    seeds = seeds_of(args)
    methods = choices_of(parser, "--methods", args.methods, METHODS)
    lfgp_task = "lift" if args.quick else args.lfgp_task  # quick: the shorter task set, fewer collections
    plan = {  # name: (main task, trainer, its own options)
        "vpace": ("lift", "vpace", ["--aux-tasks", *EXAMPLE_TASKS[1:]]),
        "sqil": ("lift", "vpace", ["--variant", "sqil"]),
        "lfgp": (lfgp_task, "lfgp", ["--aux-tasks", *LFGP_TASKS[lfgp_task][1:], *HANDCRAFTED[lfgp_task]]),
        "dac": (lfgp_task, "lfgp", ["--no-multitask"]),
    }
    if args.quick:
        steps = {"lift": 200, "stack": 200}
        every, episodes, final, example_episodes, demos, checkpoints = 100, 1, 1, 3, 3, 200
        startup = ["--buffer-warmup", "100", "--random-steps", "100", "--log-every", "100"]
    else:
        steps = {"lift": args.lift_steps, "stack": args.stack_steps}
        every, episodes, final = args.eval_every, args.eval_episodes, args.final_episodes
        example_episodes, demos, checkpoints = args.example_episodes, args.demos, args.checkpoint_every
        startup = []

    finals: dict[str, list[dict]] = {}
    runs_of: dict[str, list[Path]] = {}
    cpu_s: dict[str, list[float]] = {}
    with workspace(args.workdir) as (work, env):
        data = work / "lerobot" / "local"
        examples = data / "vpace-lift-examples"  # the destination of the committed pipeline
        if {"vpace", "sqil"} & set(methods):
            for i, task in enumerate(EXAMPLE_TASKS):  # the sources of docs/pipelines/vpace_lift_examples.toml
                collect(task, example_episodes, EXAMPLE_SEED + 10_000 * i, data / f"example-src-{task}", env)
            if not examples.exists():
                shiftkit("run", str(docs_pipeline("vpace_lift_examples", work)), "--no-progress", env=env)
        trajectories = {task: data / f"demos-{task}" for task in LFGP_TASKS[lfgp_task]}
        if {"lfgp", "dac"} & set(methods):
            for task, root in trajectories.items():
                collect(task, demos, DEMO_SEED + 10_000 * DEMO_ORDER.index(task), root, env)

        for name in methods:
            task, trainer, own = plan[name]
            if trainer == "vpace":
                data_args = ["--examples", str(examples)]
            else:  # LfGP: every task's trajectories; single-task DAC: the main task's only
                tasks = LFGP_TASKS[lfgp_task] if name == "lfgp" else (task,)
                data_args = ["--examples", *(str(trajectories[t]) for t in tasks)]
            for seed in seeds:
                run = work / "runs" / f"{name}-{task}-s{seed}"
                if not (run / "card.json").exists():  # the card is written when training ends
                    before = os.times()
                    shiftkit(
                        "train", trainer, *data_args, "--env", "panda-play", "--main-task", task, *own,
                        "--env-kwarg", "control_hz=5", "--total-steps", str(steps[task]),
                        "--eval-every", str(every), "--eval-episodes", str(episodes),
                        "--checkpoint-every", str(min(steps[task], checkpoints)), *startup,
                        "--threads", "1", "--device", "cpu", "--seed", str(seed), "--output", str(run),
                        *resumable(run), env=env,
                    )  # fmt: skip
                    after = os.times()
                    cpu = after.children_user + after.children_system - before.children_user - before.children_system
                    cpu_s.setdefault(name, []).append(round(cpu, 1))
                result = evaluate(
                    run, run / "eval" / "final-held-out.json", "--env", "panda-play", "--task", task, *HZ,
                    "--episodes", str(final), "--seed", str(FINAL_SEED), env=env,
                )  # fmt: skip
                finals.setdefault(name, []).append(
                    {"seed": seed, "successes": result["successes"], "episodes": result["episodes"]}
                )
                runs_of.setdefault(name, []).append(run)
        curves = {name: {"task": plan[name][0], **curve(runs)} for name, runs in runs_of.items()}

    pooled = {name: pool(runs) for name, runs in finals.items()}
    gaps = {
        f"{a}_minus_{b}_final_success": round(pooled[a]["success"] - pooled[b]["success"], 4)
        for a, b in (("vpace", "sqil"), ("lfgp", "dac"))
        if a in pooled and b in pooled
    }
    for name, c in curves.items():
        triples = zip(c["steps"], c["iqm"], c["ci95"], strict=True)
        points = ", ".join(f"{s}: {m:.0%} [{lo:.0%}, {hi:.0%}]" for s, m, (lo, hi) in triples)
        print(f"{name} ({c['task']}, {c['runs']} runs) IQM curve: {points}")
    metric, value = next(iter(gaps.items()), ("final_success", next(iter(pooled.values()))["success"]))
    report(
        "vpace_lfgp", metric, value, args.quick, pooled, **gaps, lfgp_task=lfgp_task, curves=curves, seeds=seeds,
        interactions=steps, eval_every=every, eval_episodes=episodes, final_episodes=final,
        final_seeds=[FINAL_SEED, FINAL_SEED + final - 1], example_episodes=example_episodes,
        demos_per_task=demos, train_cpu_s=cpu_s,
    )  # fmt: skip


if __name__ == "__main__":
    main()
