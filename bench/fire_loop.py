"""FIRE loop throughput: environment steps per second of the FIRE episodes (policy + discriminator +
failure prediction + the oracle's simulator forks and look-aheads + expert takeovers + recording)
against a plain rollout of the same policy on the same seeds, in the same run. Goal: ratio >= 0.5.

Steps, through shiftkit's own entry points:
1. `shiftkit collect` scripted-expert demonstrations (panda-play lift at 5 Hz);
2. `shiftkit fire` (`policies.fire.loop.run`) with the gda+doubt predictor and D active early, so every
   step pays for D, the doubt, GDA and the oracle;
3. the run's final policy rolled out plainly (`evaluation.run_episodes`) on the FIRE episodes' seeds.

The headline ratio counts the episodes' execution time (what the loop adds to running the policy);
the learning between episodes (D, BC updates, retraining), which any online learner pays, is
reported separately as `with_learning_ratio`. `cpu_time_ratio` is the headline ratio in the
process's CPU time, which other processes on a shared machine stretch less than wall time. The
simulated oracle's look-ahead runs the policy to the end of the episode (its success, or a
standstill) from the first question, and during a correction at every step to decide whether the
policy can finish (the hand-back), so an early-failing policy costs several extra episodes per
executed one; `simulated_steps_ratio` counts the look-ahead steps too, i.e. the per-step overhead of
D, doubt, prediction, forks and recording.

    python bench/fire_loop.py [--quick] [--workdir DIR]

Last line: {"bench": "fire_loop", "metric": "fire_vs_plain_steps_per_s", "value": ..., "goal": 0.5, ...}
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="4 demonstrations, 6 FIRE episodes")
    parser.add_argument("--episodes", type=int, help="FIRE episodes (default 30, quick 6)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    parser.add_argument("--workdir", help="keep dataset and run here (default: a temporary folder)")
    args = parser.parse_args()
    episodes = args.episodes or (6 if args.quick else 30)
    demos = 4 if args.quick else 10
    tmp = None if args.workdir else tempfile.TemporaryDirectory(prefix="bench-fire-")
    work = Path(args.workdir or tmp.name)
    work.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("HF_DATASETS_CACHE", str(work / "hf-cache"))

    from shiftkit.app.collect import CollectConfig, collect
    from shiftkit.envs import make
    from shiftkit.policies.bc_policy import load_policy
    from shiftkit.policies.evaluation import run_episodes
    from shiftkit.policies.fire.config import FireArgs, FireBC
    from shiftkit.policies.fire.loop import run as run_fire
    from shiftkit.policies.fire.runs import read_episode_lines

    dataset, run = work / f"lift5-{demos}", work / f"fire-{episodes}"
    if not dataset.exists():
        collect(
            CollectConfig(
                task="lift", episodes=demos, seed=0, control_hz=5, lerobot=f"local/lift5-{demos}", root=str(dataset)
            )
        )
    fire_args = FireArgs(
        dataset=str(dataset),
        env="panda-play",
        task="lift",
        output_dir=str(run),
        predictor="gda+doubt",
        max_episodes=episodes,
        budget_expert_samples=10**9,
        dataset_root=str(work / f"aggregated-{episodes}"),
        bc=FireBC(regime="fixed", steps=500 if args.quick else 2000),
        d_start=50,
        threads=args.threads,
        device="cpu",
        resume=run.exists(),
    )
    summary = run_fire(fire_args)
    lines = read_episode_lines(run)
    fire_steps = sum(x["length"] for x in lines)
    fire_exec_s = sum(x["episode_exec_s"] for x in lines)
    fire_cpu_s = sum(x["episode_cpu_s"] for x in lines)
    fire_wall_s = lines[-1]["wall_time_s"]
    look_ahead = lines[-1]["look_ahead_steps"]

    policy = load_policy(run / "policy")
    env = make("panda-play", "lift", control_hz=5)
    t0, c0 = time.perf_counter(), time.process_time()
    plain = run_episodes(policy, env, episodes, seed=fire_args.env_seed)
    plain_s, plain_cpu_s = time.perf_counter() - t0, time.process_time() - c0
    env.close()
    plain_steps = sum(r.steps for r in plain)

    fire_rate, plain_rate = fire_steps / fire_exec_s, plain_steps / plain_s
    print(
        f"FIRE: {fire_steps} steps in {fire_exec_s:.1f} s of episodes ({fire_rate:.0f}/s), {fire_wall_s:.1f} s with "
        f"learning; {lines[-1]['forks']} forks, {lines[-1]['look_ahead_steps']} look-ahead steps; "
        f"plain rollout: {plain_steps} steps in {plain_s:.1f} s ({plain_rate:.0f}/s)"
    )
    print(
        json.dumps(
            {
                "bench": "fire_loop",
                "metric": "fire_vs_plain_steps_per_s",
                "value": round(fire_rate / plain_rate, 3),
                "goal": 0.5,
                "higher_is_better": True,
                "fire_steps_per_s": round(fire_rate, 1),
                "plain_steps_per_s": round(plain_rate, 1),
                # the same ratio in CPU time of this process: on a shared machine, other processes
                # stretch the two phases' wall times differently
                "cpu_time_ratio": round((fire_steps / fire_cpu_s) / (plain_steps / plain_cpu_s), 3),
                "with_learning_ratio": round(fire_steps / fire_wall_s / plain_rate, 3),
                # every simulated step (executed + the oracle's look-ahead): the cost of D, doubt,
                # prediction, forks and recording per step, apart from how far the oracle looks ahead
                "simulated_steps_ratio": round((fire_steps + look_ahead) / fire_exec_s / plain_rate, 3),
                "fire_steps": fire_steps,
                "plain_steps": plain_steps,
                "forks": lines[-1]["forks"],
                "look_ahead_steps": lines[-1]["look_ahead_steps"],
                "episodes": episodes,
                "corrections": summary["corrections"],
                "quick": args.quick,
            }
        )
    )


if __name__ == "__main__":
    main()
