"""pi_m against pi_f in the fixed view and under base-pose shift (thesis Fig. 3.6), over seeds.

As in docs/multiview.md ("Science: pi_m vs pi_f"), per task (mv-lift, mv-door): 200 fixed-view
expert demonstrations (seeds 0-199), the fixed-view dataset (docs/pipelines/multiview_fixed.toml)
and the multiview one (docs/pipelines/multiview_matched.toml: the same demonstrations, each
re-rendered once from a sampled base pose); then per training seed BC with the CNN encoder on RGB +
depth + state (3000 steps lift, 4000 door), pi_f on the fixed-view and pi_m on the multiview
dataset, each evaluated on 50 held-out episodes (seeds 1000-1049) in T_f (`view=fixed`) and T_m
(`view=multiview`), plus a yaw sweep (5 episodes per bin, seeds 2000 onwards). Each step is a
printed `shiftkit` command.

Last line: the JSON result, pi_m minus pi_f in T_m on door pooled over seeds (the thesis claim:
pi_m beats pi_f under base-pose shift and matches it in T_f), per-seed successes and the pooled
Wilson intervals per task, policy and view. `--quick`: one seed, mv-lift only, 2 demonstrations,
20 steps, episodes cut to 1 s, pi_m's yaw sweep only (its numbers mean nothing).
"""

from __future__ import annotations

import json

from _study import arguments, docs_pipeline, evaluate, pool, report, seeds_of, shiftkit, workspace

STEPS = {"lift": 3000, "door": 4000}
INPUTS = "observation.images.base,observation.depth.base,observation.state"


def main() -> None:
    parser = arguments(__doc__)
    parser.add_argument("--demos", type=int, default=200, help="demonstrations per task (default: 200)")
    parser.add_argument("--eval-episodes", type=int, default=50, help="episodes per policy and view (default: 50)")
    parser.add_argument("--sweep-episodes", type=int, default=5, help="yaw-sweep episodes per bin (default: 5)")
    args = parser.parse_args()
    seeds = seeds_of(args)
    tasks = ["lift"] if args.quick else ["lift", "door"]
    demos, episodes, sweep = (2, 1, 1) if args.quick else (args.demos, args.eval_episodes, args.sweep_episodes)
    short = ["--env-kwarg", "max_episode_seconds=1"] if args.quick else []  # quick: 10-step episodes

    policies: dict[str, dict] = {}
    sweeps: dict[str, dict] = {}
    with workspace(args.workdir) as (work, env):
        for task in tasks:
            folder, name = work / task, f"mv-{task}"
            if not (folder / "data" / "mv_demos").exists():
                shiftkit(
                    "collect", "--env", name, "--task", task, "--episodes", str(demos), "--seed", "0",
                    "--env-kwarg", "view=fixed", "--cameras", "base", "--depth",
                    "--out", str(folder / "data" / "mv_demos"), "--no-progress", env=env,
                )  # fmt: skip
            for kind, pipeline in (("f", "multiview_fixed"), ("m", "multiview_matched")):
                dataset = folder / "out" / pipeline.replace("multiview", "mv")
                if not dataset.exists():  # a dataset appears at its destination only once finished
                    shiftkit("run", str(docs_pipeline(pipeline, folder)), "--no-progress", env=env)
                for seed in seeds:
                    run = folder / f"pi_{kind}-s{seed}"
                    if not (run / "card.json").exists():  # the card is written when training ends
                        shiftkit(
                            "train", "bc", "--dataset", str(dataset), "--output", str(run), "--regime", "fixed",
                            "--steps", str(20 if args.quick else STEPS[task]), "--ensemble", "1",
                            "--batch-size", "32", "--inputs", INPUTS, "--hidden", "256,256", "--threads", "1",
                            "--device", "cpu", "--seed", str(seed), "--no-progress", env=env,
                        )  # fmt: skip
                    for view, label in (("fixed", "T_f"), ("multiview", "T_m")):
                        result = evaluate(
                            run, run / f"eval-{view}.json", "--env", name, "--task", task,
                            "--episodes", str(episodes), "--seed", "1000", "--env-kwarg", f"view={view}", *short,
                            env=env,
                        )  # fmt: skip
                        policies.setdefault(f"{name} pi_{kind} {label}", []).append(
                            {"seed": seed, "successes": result["successes"], "episodes": result["episodes"]}
                        )
                    out = run / "eval-yawsweep.json"
                    if args.quick and kind == "f":
                        continue  # quick: one sweep (pi_m's) tries the command; each costs a process start
                    if not out.exists():
                        shiftkit(
                            "eval", "--policy", str(run), "--env", name, "--task", task, "--episodes", str(sweep),
                            "--seed", "2000", "--yaw-sweep", *short, "--out", str(out), env=env,
                        )  # fmt: skip
                    sweeps[f"{name} pi_{kind} s{seed}"] = json.loads(out.read_text())

    pooled = {name: pool(runs) for name, runs in policies.items()}
    task = tasks[-1]
    gap = pooled[f"mv-{task} pi_m T_m"]["success"] - pooled[f"mv-{task} pi_f T_m"]["success"]
    report(
        "multiview_pi", f"mv_{task}_pi_m_minus_pi_f_T_m", gap, args.quick, pooled,
        seeds=seeds, demos=demos, eval_episodes=episodes, eval_seeds=[1000, 1000 + episodes - 1],
        sweep_episodes_per_bin=sweep, yaw_sweeps=sweeps,
    )  # fmt: skip


if __name__ == "__main__":
    main()
