"""FIRE against BC at equal expert samples and execution time (thesis Figs 5.3 and 5.9), over seeds.

panda-play lift at 5 Hz, as in docs/fire.md: demonstrations recorded once (seeds 0-39), then per
training seed s: BC from 20 and from 40 demonstrations, and FIRE (gda and beta predictors) started
from the 20 demonstrations with D after 300 policy samples and a budget of 500 corrections (env
seeds 10000 + 1000 s onwards). Every policy is evaluated on the same held-out episodes (seeds
100000 onwards, used by no demonstration or FIRE episode). Each step is a `shiftkit` command,
printed before it runs, so a row of docs/results.md can be re-made by hand.

Prints a table and, last, the JSON result: FIRE gda's success pooled over seeds against BC from 40
demonstrations (the thesis claim: FIRE reaches BC's success with fewer expert samples). `--quick`
is a smoke test of the whole path (one seed, a few episodes; its numbers mean nothing).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from shiftkit.policies.evaluation import wilson_interval
from shiftkit.policies.fire_runs import bc_reference, read_episode_lines
from shiftkit.policies.run_dir import EVAL

SHIFTKIT = [sys.executable, "-m", "shiftkit.app.cli"]


def shiftkit(*args: str, env: dict[str, str]) -> None:
    print("+ shiftkit " + " ".join(args), flush=True)
    subprocess.run([*SHIFTKIT, *args], env=env, check=True, stdout=subprocess.DEVNULL)


def evaluate(policy: Path, episodes: int, env: dict[str, str]) -> dict:
    out = policy / EVAL / "lift-held-out.json"  # in the run, so `plot fire --bc` and the card find it
    shiftkit(
        "eval", "--policy", str(policy), "--task", "lift", "--control-hz", "5",
        "--episodes", str(episodes), "--seed", "100000", "--out", str(out), env=env,
    )  # fmt: skip
    return json.loads(out.read_text())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke test: one seed, a few episodes (< 5 min)")
    parser.add_argument("--seeds", default="0,1,2", help="training seeds (default: 0,1,2)")
    parser.add_argument("--eval-episodes", type=int, default=30, help="held-out episodes per policy (default: 30)")
    parser.add_argument("--figure", help="PNG of `plot fire` (-expert/-time added; default: in the workdir)")
    parser.add_argument("--workdir", help="keep the datasets and runs here (default: a temporary folder)")
    args = parser.parse_args()
    seeds = [0] if args.quick else [int(s) for s in args.seeds.split(",")]
    demos = {"small": 3, "large": 6} if args.quick else {"small": 20, "large": 40}
    episodes = 2 if args.quick else args.eval_episodes
    budget, max_episodes = ("30", "2") if args.quick else ("500", "60")

    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.workdir or tmp)
        work.mkdir(parents=True, exist_ok=True)
        env = {**os.environ, "HF_LEROBOT_HOME": str(work / "lerobot"), "HF_HUB_OFFLINE": "1"}
        for n in demos.values():
            if not (work / "lerobot" / "local" / f"lift5-{n}").exists():
                shiftkit(
                    "collect", "--task", "lift", "--episodes", str(n), "--control-hz", "5", "--seed", "0",
                    "--lerobot", f"local/lift5-{n}", "--root", str(work / "lerobot" / "local" / f"lift5-{n}"),
                    "--no-progress", env=env,
                )  # fmt: skip
        rows: dict[str, list[dict]] = {}
        bc_runs: dict[str, list[str]] = {}  # `plot fire --bc LABEL=RUN,RUN...`: one point per label
        fire_runs: list[str] = []
        for seed in seeds:
            common = ["--threads", "1", "--device", "cpu", "--seed", str(seed), "--no-progress"]
            for n in demos.values():
                run = work / f"bc{n}-s{seed}"
                shiftkit("train", "bc", "--dataset", f"local/lift5-{n}", "--output", str(run),
                         "--hidden", "256,256", *common, env=env)  # fmt: skip
                evaluate(run, episodes, env)
                ref = bc_reference([run])
                rows.setdefault(f"BC, {n} demos", []).append(
                    {"seed": seed, "successes": ref["successes"], "episodes": ref["episodes"],
                     "expert_samples": int(ref["expert_samples"]), "execution_s": ref["execution_time_s"]}
                )  # fmt: skip
                bc_runs.setdefault(f"BC, {n} demos", []).append(str(run))
            for predictor in ("gda", "beta"):
                run = work / f"fire-{predictor}-s{seed}"
                shiftkit(
                    "fire", "--dataset", f"local/lift5-{demos['small']}", "--env", "panda-play", "--task", "lift",
                    "--predictor", predictor, "--budget-expert-samples", budget, "--max-episodes", max_episodes,
                    "--d-start", "300", "--env-seed", str(10000 + 1000 * seed), "--output", str(run),
                    "--repo-id", f"local/fire-{predictor}-s{seed}", *common, env=env,
                )  # fmt: skip
                fire_runs.append(f"FIRE {predictor} s{seed}={run}")
                last = read_episode_lines(run)[-1]
                result = evaluate(run / "policy", episodes, env)
                rows.setdefault(f"FIRE {predictor}, from {demos['small']} demos", []).append(
                    {"seed": seed, "successes": result["successes"], "episodes": result["episodes"],
                     "expert_samples": last["expert_samples"], "execution_s": last["execution_time_s"],
                     "fire_episodes": last["episode"] + 1}
                )  # fmt: skip
        # thesis Figs 5.3 / 5.9: FIRE's success curves with BC's points at its training frames
        figure = Path(args.figure) if args.figure else work / "fire-lift.png"
        shiftkit("plot", "fire", *fire_runs, *(x for label, runs in bc_runs.items() for x in ("--bc", f"{label}={','.join(runs)}")), "--out", str(figure),
                 "--title", f"lift at 5 Hz: FIRE from {demos['small']} demos vs BC ({len(seeds)} seeds, BC on {episodes} held-out episodes each)", env=env)  # fmt: skip

    summary = {}
    print(
        "\n| policy | seeds | expert samples (mean) | execution time s (mean) | success per seed | pooled (Wilson 95%) |"
    )
    print("|---|---|---|---|---|---|")
    for name, runs in rows.items():
        k, n = sum(r["successes"] for r in runs), sum(r["episodes"] for r in runs)
        samples = sum(r["expert_samples"] for r in runs) / len(runs)
        exec_s = sum(r["execution_s"] for r in runs) / len(runs)
        summary[name] = {"success": round(k / n, 4), "ci95": [round(c, 4) for c in wilson_interval(k, n)], "runs": runs}
        per_seed = ", ".join(f"{r['successes']}/{r['episodes']}" for r in runs)
        ci = summary[name]["ci95"]
        print(
            f"| {name} | {len(runs)} | {samples:.0f} | {exec_s:.0f} | {per_seed} | {k / n:.1%} [{ci[0]:.1%}, {ci[1]:.1%}] |"
        )
    fire, bc = summary[f"FIRE gda, from {demos['small']} demos"], summary[f"BC, {demos['large']} demos"]
    print(
        json.dumps(
            {
                "bench": "science_fire_lift",
                "metric": "fire_gda_success_minus_bc_large_success",
                "value": round(fire["success"] - bc["success"], 4),
                "goal": 0.0,
                "higher_is_better": True,
                "seeds": seeds,
                "eval_episodes": episodes,
                "quick": args.quick,
                "policies": summary,
            }
        )
    )


if __name__ == "__main__":
    main()
