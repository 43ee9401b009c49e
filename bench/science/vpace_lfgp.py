"""VPACE learns lift from success examples alone (thesis ch. 7) and LfGP beats single-task DAC on stack
(thesis ch. 6), in the panda-play env at 5 Hz (90-step episodes), over seeds.

Data, each made once with shiftkit's own commands (docs/vpace.md, docs/success_examples.md):
* success examples for VPACE: `shiftkit collect --task T --control-hz 5 --only-successful` of
  `--example-episodes` (default 240) scripted-expert episodes for each of lift, reach and open, then
  `shiftkit run docs/pipelines/vpace_lift_examples.toml` (the `success_examples` stage, a seeded 200
  final states per task): one example dataset, as bench/vpace_reach.py's `--examples scene`;
* expert trajectories for LfGP and DAC: `--demos` (default 10) successful scripted episodes for each of
  stack, reach, lift, move-object and open (LeRobot datasets, each frame labelled with its task).

Per training seed (default 0,1,2), `shiftkit train` with the thesis hyperparameters otherwise:
* `vpace`: `train vpace`, main task lift, auxiliary tasks reach and open (the env's release), weighted
  random scheduler; its baseline `sqil`: `train vpace --variant sqil`, lift alone, same examples;
* `lfgp`: `train lfgp`, main task stack, auxiliary tasks reach, lift, move-object and open, with the
  thesis' handcrafted Panda sequences (`--handcrafted panda-lfgp`, thesis 6.6.2); its baseline
  `dac`: `train lfgp --no-multitask`, DAC on (s, a) from the stack trajectories alone (the thesis'
  single-task DAC baseline, which sees expert trajectories as LfGP does, not final states).
Every run evaluates its main intention (mean action) every `--eval-every` interactions on
`--eval-episodes` episodes (metrics.jsonl, `split == "eval"`: the success curve), and its last
checkpoint is evaluated at the end on `--final-episodes` held-out episodes (`shiftkit eval`, seeds
600000 onwards, which no training reset, curve evaluation or recording uses).

Interaction budgets: `--lift-steps` (default 300000, the trainer's default) and `--stack-steps`
(default 1000000). CPU time is the limit, not the
method. Measured on the 2-core development machine under load (one torch thread, CPU time per
interaction once updates run): vpace about 27 ms (3 intentions), sqil 14 ms, lfgp 65-70 ms (5
intentions, a discriminator each), dac 20 ms; so one lift run takes about 2.3 h (vpace) and 1.2 h
(sqil) of CPU, one stack run about 19 h (lfgp) and 5.5 h (dac), some 85 CPU hours for 3 seeds of
all four (the quick run prints each training's CPU time as `train_cpu_s`). Once the data exists,
further processes with the same `--workdir` and their own `--seeds` reuse it, so seeds can run side
by side; finished runs (with their card.json) and evaluations are reused by a rerun.

Reported: per method the success curve over seeds, interquartile mean with stratified-bootstrap 95%
CIs (`_study.iqm_ci`, rliable's convention, scipy's bootstrap, seed 0), over the evaluation steps
every seed reached; and the final success pooled over seeds with its Wilson 95% interval
(`_study.pool`). `shiftkit plot curves VPACE=RUN,RUN,... SQIL=... --out lift.png` draws the same
curves. Last line: the JSON result, LfGP's final success minus DAC's (the thesis claim: > 0), with
VPACE minus SQIL on lift, the curves and every run. `--quick`: one seed, 200 interactions per run
(100 random before the first update, curve points at 100 and 200), 3 scripted episodes per example
set and trajectory set, 1-episode evaluations: every command of the full run, its numbers mean
nothing.
"""

from __future__ import annotations

import os
from pathlib import Path

from _study import arguments, docs_pipeline, evaluate, iqm_ci, pool, report, seeds_of, shiftkit, workspace

from shiftkit.policies.curves import read_success

HZ = ["--control-hz", "5"]
EXAMPLE_TASKS = ("lift", "reach", "open")  # VPACE's main task and its auxiliary tasks
DEMO_TASKS = ("stack", "reach", "lift", "move-object", "open")  # LfGP's main task and its auxiliary tasks
EXAMPLE_SEED, DEMO_SEED, FINAL_SEED = 100_000, 300_000, 600_000  # + 10000 per task; training uses seed * 1e6 + ep
METHODS = {  # name: (main task, trainer, its own options)
    "vpace": ("lift", "vpace", ["--aux-tasks", "reach", "open"]),
    "sqil": ("lift", "vpace", ["--variant", "sqil"]),
    "lfgp": ("stack", "lfgp", ["--aux-tasks", "reach", "lift", "move-object", "open", "--handcrafted", "panda-lfgp"]),
    "dac": ("stack", "lfgp", ["--no-multitask"]),
}


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
    parser.add_argument("--lift-steps", type=int, default=300_000, help="interactions per lift run (default: 300000)")
    parser.add_argument(
        "--stack-steps", type=int, default=1_000_000, help="interactions per stack run (default: 1000000)"
    )
    parser.add_argument("--eval-every", type=int, default=10_000, help="interactions between curve points (10000)")
    parser.add_argument("--eval-episodes", type=int, default=20, help="episodes per curve point (default: 20)")
    parser.add_argument("--final-episodes", type=int, default=50, help="held-out episodes per run (default: 50)")
    parser.add_argument(
        "--example-episodes", type=int, default=240, help="scripted episodes per example task (default: 240)"
    )
    parser.add_argument("--demos", type=int, default=10, help="expert trajectories per LfGP task (default: 10)")
    args = parser.parse_args()
    seeds = seeds_of(args)
    if args.quick:
        steps = {"lift": 200, "stack": 200}
        every, episodes, final, example_episodes, demos = 100, 1, 1, 3, 3
        startup = ["--buffer-warmup", "100", "--random-steps", "100", "--log-every", "100"]
    else:
        steps = {"lift": args.lift_steps, "stack": args.stack_steps}
        every, episodes, final = args.eval_every, args.eval_episodes, args.final_episodes
        example_episodes, demos = args.example_episodes, args.demos
        startup = []

    finals: dict[str, list[dict]] = {}
    runs_of: dict[str, list[Path]] = {}
    cpu_s: dict[str, list[float]] = {}
    with workspace(args.workdir) as (work, env):
        data = work / "lerobot" / "local"
        for i, task in enumerate(EXAMPLE_TASKS):  # the sources of docs/pipelines/vpace_lift_examples.toml
            collect(task, example_episodes, EXAMPLE_SEED + 10_000 * i, data / f"example-src-{task}", env)
        examples = data / "vpace-lift-examples"  # the destination of the committed pipeline
        if not examples.exists():
            shiftkit("run", str(docs_pipeline("vpace_lift_examples", work)), "--no-progress", env=env)
        trajectories = {task: data / f"demos-{task}" for task in DEMO_TASKS}
        for i, (task, root) in enumerate(trajectories.items()):
            collect(task, demos, DEMO_SEED + 10_000 * i, root, env)

        for name, (task, trainer, own) in METHODS.items():
            if trainer == "vpace":
                data_args = ["--examples", str(examples)]
            else:  # LfGP: every task's trajectories; single-task DAC: the main task's only
                tasks = DEMO_TASKS if "--no-multitask" not in own else (task,)
                data_args = ["--examples", *(str(trajectories[t]) for t in tasks)]
            for seed in seeds:
                run = work / "runs" / f"{name}-s{seed}"
                if not (run / "card.json").exists():  # the card is written when training ends
                    before = os.times()
                    shiftkit(
                        "train", trainer, *data_args, "--env", "panda-play", "--main-task", task, *own,
                        "--env-kwarg", "control_hz=5", "--total-steps", str(steps[task]),
                        "--eval-every", str(every), "--eval-episodes", str(episodes),
                        "--checkpoint-every", str(min(steps[task], 50_000)), *startup,
                        "--threads", "1", "--device", "cpu", "--seed", str(seed), "--output", str(run),
                        env=env,
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
        curves = {name: {"task": METHODS[name][0], **curve(runs)} for name, runs in runs_of.items()}

    pooled = {name: pool(runs) for name, runs in finals.items()}
    gap = pooled["lfgp"]["success"] - pooled["dac"]["success"]
    for name, c in curves.items():
        triples = zip(c["steps"], c["iqm"], c["ci95"], strict=True)
        points = ", ".join(f"{s}: {m:.0%} [{lo:.0%}, {hi:.0%}]" for s, m, (lo, hi) in triples)
        print(f"{name} ({c['task']}, {c['runs']} runs) IQM curve: {points}")
    report(
        "vpace_lfgp", "lfgp_minus_dac_final_success", gap, args.quick, pooled,
        vpace_minus_sqil_final_success=round(pooled["vpace"]["success"] - pooled["sqil"]["success"], 4),
        curves=curves, seeds=seeds, interactions=steps, eval_every=every, eval_episodes=episodes,
        final_episodes=final, final_seeds=[FINAL_SEED, FINAL_SEED + final - 1], example_episodes=example_episodes,
        demos_per_task=demos, train_cpu_s=cpu_s,
    )  # fmt: skip


if __name__ == "__main__":
    main()
