"""`force_match` stage: throughput with 2 workers vs 1, and replay success force-matched vs position.

Default (benchmark): records simulated kinesthetic door demonstrations, then runs the same
`force_match` (position mode, both STS images) -> `mode_label` pipeline with 1 and with 2 workers;
reports episodes/s and the speed-up (goal >= 1.6x; it needs two free cores). As in
bench/executors.py, the pipeline is stamped (`bench/_timing.py`) when each episode's transform
started and ended, so that the start-up (spawning and importing in the workers, the stages'
set-up), the processing span and the rest (the dataset write) are reported apart, with what keeps
the 2-worker span above half the 1-worker one; the headline speed-up is the processing span's, the
whole run's is beside it.
Each worker renders with one llvmpipe thread (`LP_NUM_THREADS=1`), so that workers, not a
renderer's threads, are the unit of parallelism.

`--replay-success N` (the thesis' replay study, §4.4.3): N kinesthetic demonstrations per door task,
each replayed by position and force-matched through the impedance controller with the stage's own
code; prints a success table and, as the last line, the JSON result (goal: force-matched >= 90%,
position <= 40%). The calibration comes from `--calibration` (default: docs').

`--label-timing ROOT...` prints, for datasets written with a `mode_label` stage, the table of
mode-switch step minus true first-contact step per task (thesis Fig. 4.15); `--png` draws it.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("LP_NUM_THREADS", "1")

import _timing  # noqa: E402  (bench/, beside this file; registers the bench-stamp stage)
import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
TASKS = ("flat-handle-open", "flat-handle-close", "knob-open", "knob-close")


def record(out: Path, task: str, episodes: int, seed: int = 0, cameras: tuple[str, ...] = ()) -> Path:
    from shiftkit.app.collect import CollectConfig, collect

    config = CollectConfig(
        env="door-tactile", task=task, episodes=episodes, seed=seed, expert="kinesthetic", cameras=cameras
    )
    config.out = str(out)
    collect(config)
    return out


def run_pipeline_timed(raw: Path, dest: Path, workers: int) -> dict[str, float]:
    """The run's time split (`_timing.breakdown`: start-up, processing span, write, ...)."""
    from shiftkit.datasets.sources import SourceConfig
    from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, StageSpec

    stages = [
        StageSpec(name="force_match", params={"mode": "position", "hold_steps": 5}),
        StageSpec(
            name="mode_label",
            params={"visual_image": "observation.images.sts_visual", "tactile_image": "observation.images.sts_tactile"},
        ),
    ]
    config = PipelineConfig(
        sources=[SourceConfig(path=str(raw))],
        destination=DestinationConfig(root=str(dest)),
        stages=_timing.stamped(stages),
    )
    return _timing.timed_run(config, workers)


def throughput(quick: bool, episodes: int | None = None) -> dict:
    episodes = episodes or (4 if quick else 8)
    loads = [os.getloadavg()[0]]
    # the dataset writer's one-time import of lerobot (and torch) is not part of either run
    import lerobot.datasets.lerobot_dataset  # noqa: F401

    with tempfile.TemporaryDirectory() as tmp:
        raw = record(Path(tmp) / "raw", "knob-open", episodes, cameras=("wrist",))
        times = {}
        for workers in (1, 2):
            times[workers] = t = run_pipeline_timed(raw, Path(tmp) / f"w{workers}", workers)
            loads.append(os.getloadavg()[0])
            print(_timing.describe(f"{workers} worker(s)", t, episodes))
    speedup = times[1]["span"] / times[2]["span"]
    print(f"speed-up {speedup:.2f}x over the processing span (cores: {os.cpu_count()}, load {loads})")
    return {
        "bench": "force_match",
        "metric": "speedup_2_workers_vs_1_excluding_startup",
        "value": round(speedup, 3),
        "goal": 1.6,
        "higher_is_better": True,
        "speedup_whole_run": round(times[1]["total"] / times[2]["total"], 3),
        "episodes": episodes,
        "seconds": {w: {k: round(v, 2) for k, v in t.items()} for w, t in times.items()},
        "episodes_per_s_1_worker": round(episodes / times[1]["span"], 4),
        "episodes_per_s_2_workers": round(episodes / times[2]["span"], 4),
        "cpu_count": os.cpu_count(),
        "load_average": loads,
        "quick": quick,
    }


def replay_success(
    n: int,
    calibration: str,
    slowdown: int,
    extra_steps: int,
    tasks: tuple[str, ...],
    damping_time: float = 0.0,
    first_seed: int = 0,
) -> dict:
    """Replay each demonstration with the stage's code (no images) by position and force-matched."""
    from tqdm import tqdm

    from shiftkit.datasets.episode import Episode
    from shiftkit.envs import env_family, make
    from shiftkit.pipelines.stage import StageContext, build_stage

    family = env_family("door-tactile")
    features = {
        "observation.ee_pose": {"dtype": "float64", "shape": (7,), "names": None},
        "observation.wrench": {"dtype": "float64", "shape": (4,), "names": None},
        "action": {"dtype": "float32", "shape": (7,), "names": list(family.action_names)},
        "next.success": {"dtype": "bool", "shape": (1,), "names": None},
    }
    stages = {}
    for mode in ("position", "force_matched"):
        params = {"mode": mode, "slowdown": slowdown}
        if mode == "force_matched":
            params.update(calibration=calibration, damping_time=damping_time)
        s = build_stage("force_match", params, StageContext(fps=10), "bench")
        s.transform_features(features)
        s.setup()
        stages[mode] = s
    rows = {}
    for task in tasks:
        env = make("door-tactile", task)
        counts = {"demonstrations": 0, "demo_success": 0, "position": 0, "force_matched": 0}
        for seed in tqdm(range(first_seed, first_seed + n), desc=task, leave=False):
            r = family.experts["kinesthetic"](env, seed, extra_steps=extra_steps)
            t = len(r.actions)
            episode = Episode(
                {
                    "observation.ee_pose": r.arrays["ee_pose"],
                    "observation.wrench": r.arrays["wrench_raw"],
                    "action": r.actions,
                    "next.success": r.success,
                    "timestamp": np.arange(t) / 10.0,
                    "task": np.array([task] * t),
                },
                {**r.meta, "task": task, "seed": seed, "sim_model": family.sim_model_id},
            )
            counts["demonstrations"] += 1
            counts["demo_success"] += int(r.succeeded)
            for mode, s in stages.items():
                out = next(iter(s.process(episode, np.random.default_rng(0))))
                counts[mode] += int(out.meta["replay_success"])
        env.close()
        rows[task] = counts
        print(task, counts, flush=True)
    total = {k: sum(r[k] for r in rows.values()) for k in next(iter(rows.values()))}
    print("| task | demonstrations | teacher success | position replay | force-matched replay |")
    print("|---|---|---|---|---|")
    for task, r in {**rows, "all": total}.items():
        d = r["demonstrations"]
        print(
            f"| {task} | {d} | {r['demo_success'] / d:.0%} | {r['position'] / d:.0%} | {r['force_matched'] / d:.0%} |"
        )
    fm, pos = total["force_matched"] / total["demonstrations"], total["position"] / total["demonstrations"]
    return {
        "bench": "force_match_replay_success",
        "metric": "force_matched_minus_position_points",
        "value": round(100 * (fm - pos), 1),
        "goal": 62.5,
        "higher_is_better": True,
        "force_matched_success": round(fm, 3),
        "position_success": round(pos, 3),
        "goal_force_matched": 0.9,
        "goal_position_max": 0.4,
        "per_task": rows,
        "slowdown": slowdown,
        "damping_time": damping_time,
        "seeds": [first_seed, first_seed + n - 1],
        "extra_steps": extra_steps,
        "calibration": calibration,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="short run (4 episodes)")
    parser.add_argument("--episodes", type=int, help="throughput: recorded demonstrations (default 8, quick 4)")
    parser.add_argument("--replay-success", type=int, metavar="N", help="replay study with N demonstrations per task")
    parser.add_argument("--calibration", default=str(REPO / "docs" / "force_matching_calibration.json"))
    parser.add_argument("--slowdown", type=int, default=2, help="force_match slowdown (default: 2)")
    parser.add_argument("--extra-steps", type=int, default=0, help="demonstration frames kept after success")
    parser.add_argument("--damping-time", type=float, default=0.0, help="force_match damping_time (default: 0)")
    parser.add_argument("--seed", type=int, default=0, help="demonstration seeds SEED..SEED+N-1 (default: 0)")
    parser.add_argument("--tasks", default=",".join(TASKS), help="comma-separated door tasks")
    parser.add_argument("--label-timing", nargs="+", metavar="ROOT", help="mode-label timing table of datasets")
    parser.add_argument("--png", help="with --label-timing: the histogram PNG (of the first dataset)")
    args = parser.parse_args()
    if args.label_timing:
        from shiftkit.transforms.mode_labels import dataset_timing_report

        for i, root in enumerate(args.label_timing):
            print(f"{root}:\n{dataset_timing_report(root, args.png if i == 0 else None)}")
        return
    if args.replay_success:
        tasks = tuple(t for t in args.tasks.split(",") if t)
        result = replay_success(
            args.replay_success, args.calibration, args.slowdown, args.extra_steps, tasks, args.damping_time, args.seed
        )
    else:
        result = throughput(args.quick, args.episodes)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
