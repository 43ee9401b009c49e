"""BC on force-matched against position-replay data, and mode switching against fixed STS modes
(thesis Figs. 4.10, 4.11, 4.13), per door task, encoder and seed.

As in docs/force_matching.md ("BC on force-matched vs position-replay data"): per task of
door-tactile (flat-handle-open, flat-handle-close, knob-open, knob-close), 20 kinesthetic
demonstrations (seeds 0-19, wrist camera, 64x64), the force-matched dataset
(docs/pipelines/force_matched.toml: the policy drives the STS mode) and the position-replay one
(docs/pipelines/position_replay.toml), both from the same demonstrations; then per training seed BC
on wrist + STS images and `observation.state` (one member, `--steps`, default 4000) with the small
CNN (`--encoder cnn`) and with a ResNet-18 trunk (`--encoder resnet18`, random init: no pretrained
weights offline) on each dataset, each evaluated on 50 held-out episodes (seeds 1000-1049, 40 s
limit). On flat-handle-open only, mode switching (force_matched.toml) against the fixed tactile and
visual modes (docs/pipelines/force_matched_tactile.toml, force_matched_visual.toml, evaluated with
`--env-kwarg sensor_mode=tactile|visual`), over the seeds, CNN encoder. The thesis trains 20k steps
from an ImageNet-pretrained ResNet-18; the default 4000 is what the CPU allows. Each step is a
printed `shiftkit` command; a rerun with the same --workdir reuses the demonstrations, datasets,
finished trainings (their `card.json`) and evaluations, and resumes an interrupted training from
its last checkpoint.

    python bench/science/force_matched_bc.py --workdir /tmp/fmbc  # --steps 20000 for the thesis' length

Last line: the JSON result, force-matched minus position-replay success in points with the first of
`--encoders` (the CNN by default; the others' gaps beside it),
pooled over tasks and seeds (thesis: +62.5 on average over its four tasks), with the per-seed
successes and the pooled Wilson intervals per task, dataset and encoder, and pooled over the tasks.
`--tasks` and `--encoders` run a part of the study (e.g. the CNN on one task over 3 seeds). `--quick`:
one seed, flat-handle-open only, 2 demonstrations, 20 steps, both encoders on the
position-replay and force-matched datasets and the CNN on the two fixed modes, one eval episode cut
to 1 s (its numbers mean nothing).
"""

from __future__ import annotations

from _study import (
    arguments,
    choices_of,
    docs_pipeline,
    evaluate,
    pool,
    report,
    resumable,
    seeds_of,
    shiftkit,
    workspace,
)

TASKS = ("flat-handle-open", "flat-handle-close", "knob-open", "knob-close")
ENCODERS = ("cnn", "resnet18")
INPUTS = "observation.images.wrist,observation.images.sts,observation.state"
# pipeline -> (label, STS mode of the eval env: None where the policy drives it)
DATASETS = {
    "force_matched": ("force-matched", None),
    "position_replay": ("position replay", None),
    "force_matched_tactile": ("force-matched tactile only", "tactile"),
    "force_matched_visual": ("force-matched visual only", "visual"),
}
FIXED_MODES_TASK = "flat-handle-open"  # Fig. 4.13's comparison runs on this task only


def main() -> None:
    parser = arguments(__doc__)
    parser.add_argument("--demos", type=int, default=20, help="kinesthetic demonstrations per task (default: 20)")
    parser.add_argument("--steps", type=int, default=4000, help="BC gradient steps (default: 4000; thesis: 20000)")
    parser.add_argument("--eval-episodes", type=int, default=50, help="episodes per policy (default: 50)")
    parser.add_argument("--tasks", default=",".join(TASKS), help="door tasks, comma-separated (default: all four)")
    parser.add_argument("--encoders", default=",".join(ENCODERS), help="BC encoders, comma-separated (default: both)")
    args = parser.parse_args()
    seeds = seeds_of(args)
    tasks = [FIXED_MODES_TASK] if args.quick else choices_of(parser, "--tasks", args.tasks, TASKS)
    encoders = choices_of(parser, "--encoders", args.encoders, ENCODERS)
    demos, steps, episodes = (2, 20, 1) if args.quick else (args.demos, args.steps, args.eval_episodes)
    limit = 1 if args.quick else 40  # seconds per eval episode; the half-speed replays last up to 26.2 s

    policies: dict[str, list[dict]] = {}
    over_tasks: dict[str, list[dict]] = {}  # the headline comparison: each task's runs of a dataset and encoder
    with workspace(args.workdir) as (work, env):
        for task in tasks:
            folder = work / task
            if not (folder / "data" / "door_kinesthetic").exists():
                shiftkit(
                    "collect", "--env", "door-tactile", "--task", task, "--expert", "kinesthetic",
                    "--episodes", str(demos), "--seed", "0", "--cameras", "wrist", "--width", "64", "--height", "64",
                    "--out", str(folder / "data" / "door_kinesthetic"), "--no-progress", env=env,
                )  # fmt: skip
            pipelines = list(DATASETS) if task == FIXED_MODES_TASK else ["force_matched", "position_replay"]
            for pipeline in pipelines:
                label, mode = DATASETS[pipeline]
                dataset = folder / "out" / f"door_{pipeline}"
                if not dataset.exists():  # `shiftkit run` publishes the finished dataset in one rename
                    shiftkit("run", str(docs_pipeline(pipeline, folder)), "--no-progress", env=env)
                # the fixed modes: CNN only
                for encoder in encoders if mode is None else [e for e in encoders if e == "cnn"]:
                    for seed in seeds:
                        run = folder / f"{pipeline}-{encoder}-s{seed}"
                        if not (run / "card.json").exists():  # the card is written when training ends
                            shiftkit(
                                "train", "bc", "--dataset", str(dataset), "--output", str(run), "--regime", "fixed",
                                "--steps", str(steps), "--ensemble", "1", "--batch-size", "32", "--inputs", INPUTS,
                                "--encoder", encoder, "--hidden", "256,256", "--threads", "1", "--device", "cpu",
                                "--seed", str(seed), "--no-progress", *resumable(run), env=env,
                            )  # fmt: skip
                        sensor = [] if mode is None else ["--env-kwarg", f"sensor_mode={mode}"]
                        result = evaluate(
                            run, run / "eval.json", "--env", "door-tactile", "--task", task,
                            "--episodes", str(episodes), "--seed", "1000",
                            "--env-kwarg", f"max_episode_seconds={limit}", *sensor, env=env,
                        )  # fmt: skip
                        entry = {"task": task, "seed": seed, "successes": result["successes"]}
                        entry["episodes"] = result["episodes"]
                        policies.setdefault(f"{task} {label} {encoder}", []).append(entry)
                        if mode is None:
                            over_tasks.setdefault(f"all tasks {label} {encoder}", []).append(entry)

    pooled = {name: pool(runs) for name, runs in {**policies, **over_tasks}.items()}
    gaps = {
        f"force_matched_minus_position_{encoder}_points": 100 * (
            pooled[f"all tasks force-matched {encoder}"]["success"]
            - pooled[f"all tasks position replay {encoder}"]["success"])
        for encoder in encoders
    }  # fmt: skip
    headline, *others = gaps  # the first encoder's (the CNN's by default)
    report(
        "force_matched_bc", headline, gaps[headline], args.quick, pooled,
        **{k: round(gaps[k], 4) for k in others}, tasks=tasks, encoders=encoders, seeds=seeds,
        demos=demos, steps=steps, eval_episodes=episodes, eval_seeds=[1000, 1000 + episodes - 1],
        max_episode_seconds=limit,
    )  # fmt: skip


if __name__ == "__main__":
    main()
