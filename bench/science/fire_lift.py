"""FIRE against BC at matched expert samples and matched execution time (thesis Figs 5.3 and 5.9), for
a perfect and a suboptimal expert, over seeds.

panda-play lift at 5 Hz, per expert (`scripted`, and `suboptimal`: the scripted expert with a person's
variance, docs/fire.md), demonstrations recorded once (`collect --expert E --only-successful`, seeds
0 onwards, the first N episodes for N demonstrations). Per training seed s:

* BC's reference curve: BC from 10, 20, ... 60 demonstrations;
* FIRE (gda and beta predictors) from 20 demonstrations, as Algorithm 2 runs it (thesis 5.4.2):
  the policy on its own until 10k policy samples, then D, predictions, corrections handed back as
  soon as the policy can finish, with the same expert correcting; until 500 corrections (env seeds
  10000 + 1000 s onwards);
* BC at FIRE's expert samples and BC at FIRE's execution time (demonstrations + every executed step),
  both from FIRE gda's mean over the seeds.

BC and FIRE use the same network (one 2x256 MLP, tanh output, thesis 5.4.2), named explicitly, so
neither follows `train bc`'s defaults. Every policy is evaluated on the same held-out episodes (seeds
100000 onwards, used by no demonstration or FIRE episode). Each step is a `shiftkit` command, printed
before it runs; a rerun with the same `--workdir` reuses every finished step (resumable).

Each FIRE run's entry in the JSON result holds `protocol`: its warm-up and hand-backs as its metrics
and its DAgger-layout recording show them (`policies.fire.runs.protocol_check`).

Prints a table and, last, the JSON result: FIRE gda's success pooled over seeds minus BC's at matched
expert samples, with the suboptimal expert (the thesis' claim: FIRE beats BC at equal expert data,
with human demonstrations). `--quick` is a smoke test of every command (one seed, tiny sizes; its
numbers mean nothing).
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _study import arguments, choices_of, evaluate, pool, seeds_of, shiftkit, workspace  # noqa: E402

from shiftkit.policies.fire.runs import bc_reference, protocol_check, read_episode_lines  # noqa: E402

NETWORK = ["--ensemble", "1", "--hidden", "256,256", "--output-activation", "tanh"]
FIRE_NETWORK = [f"--bc.{a[2:]}" if a.startswith("--") else a for a in NETWORK]  # FIRE nests BC's options
EXPERTS = ("scripted", "suboptimal")


def main() -> None:
    parser = arguments(__doc__)
    parser.add_argument("--eval-episodes", type=int, default=30, help="held-out episodes per policy (default: 30)")
    parser.add_argument("--experts", help="experts to run, comma-separated (default: both; --quick: suboptimal)")
    parser.add_argument("--figure", help="PNG prefix of `plot fire` (-EXPERT-expert/-time added; default: workdir)")
    args = parser.parse_args()
    seeds = seeds_of(args)
    experts = choices_of(
        parser, "--experts", args.experts or ("suboptimal" if args.quick else ",".join(EXPERTS)), EXPERTS
    )
    quick = args.quick
    sizes = [3, 5] if quick else [10, 20, 30, 40, 50, 60]
    start = 3 if quick else 20
    episodes = 2 if quick else args.eval_episodes
    fire_opts = (
        ["--budget-expert-samples", "20", "--max-episodes", "3", "--d-start", "40"]
        if quick
        else ["--budget-expert-samples", "500", "--d-start", "10000"]
    )
    rows: dict[str, list[dict]] = {}
    with workspace(args.workdir) as (work, env):
        home = work / "lerobot" / "local"

        def demos(expert: str, n: int) -> str:
            repo = f"lift5-{expert}-{n}"
            if not (home / repo).exists():
                shiftkit(
                    "collect", "--task", "lift", "--episodes", str(n), "--control-hz", "5", "--seed", "0",
                    "--expert", expert, "--only-successful", "--lerobot", f"local/{repo}", "--root", str(home / repo),
                    "--no-progress", env=env,
                )  # fmt: skip
            return f"local/{repo}"

        def bc(expert: str, n: int, seed: int) -> Path:
            run = work / f"bc-{expert}-{n}-s{seed}"
            if not (run / "eval" / "lift-held-out.json").exists():
                if not (run / "checkpoints" / "last.txt").exists():
                    shiftkit("train", "bc", "--dataset", demos(expert, n), "--output", str(run), *NETWORK,
                             "--seed", str(seed), "--threads", "1", "--device", "cpu", "--no-progress",
                             *(["--resume"] if (run / "config.json").exists() else []), env=env)  # fmt: skip
                held_out(run)
            return run

        def held_out(policy: Path) -> dict:
            return evaluate(
                policy, policy / "eval" / "lift-held-out.json", "--task", "lift", "--control-hz", "5",
                "--episodes", str(episodes), "--seed", "100000", env=env,
            )  # fmt: skip

        def bc_row(name: str, run: Path, seed: int) -> None:
            ref = bc_reference([run])
            rows.setdefault(name, []).append(
                {"seed": seed, "successes": ref["successes"], "episodes": ref["episodes"],
                 "expert_samples": int(ref["expert_samples"]), "execution_s": round(ref["execution_time_s"], 1)}
            )  # fmt: skip

        # seed by seed, both experts each (one finished seed shows the whole study's cost per seed)
        curves: dict[str, list[str]] = {expert: [] for expert in experts}
        fire_runs: dict[str, list[str]] = {expert: [] for expert in experts}
        for seed in seeds:
            for expert in experts:
                for n in sizes:
                    run = bc(expert, n, seed)
                    curves[expert].append(str(run))
                    bc_row(f"{expert}: BC, {n} demos", run, seed)
                for predictor in ("gda", "beta"):
                    run = work / f"fire-{expert}-{predictor}-s{seed}"
                    if not (run / "policy" / "eval" / "lift-held-out.json").exists():
                        shiftkit(
                            "fire", "--dataset", demos(expert, start), "--env", "panda-play", "--task", "lift",
                            "--expert-policy", expert, "--predictor", predictor, *fire_opts, *FIRE_NETWORK,
                            "--env-seed", str(10000 + 1000 * seed), "--output", str(run),
                            "--repo-id", f"local/fire-{expert}-{predictor}-s{seed}", "--seed", str(seed),
                            "--threads", "1", "--device", "cpu", "--no-progress",
                            *(["--resume"] if (run / "config.json").exists() else []), env=env,
                        )  # fmt: skip
                    result = held_out(run / "policy")
                    lines = read_episode_lines(run)
                    fire_runs[expert].append(f"FIRE {predictor}={run}")
                    rows.setdefault(f"{expert}: FIRE {predictor}, from {start} demos", []).append(
                        {"seed": seed, "successes": result["successes"], "episodes": result["episodes"],
                         "expert_samples": lines[-1]["expert_samples"],
                         "execution_s": round(lines[-1]["execution_time_s"], 1), "fire_episodes": len(lines),
                         "warm_up_episodes": sum(not x["d_ready"] for x in lines), "protocol": protocol_check(run)}
                    )  # fmt: skip
        figures = {}
        for expert in experts:
            # BC at FIRE gda's expert samples and execution time: the demonstrations that reach them
            fire = rows[f"{expert}: FIRE gda, from {start} demos"]
            per_demo = bc_reference([bc(expert, sizes[-1], seeds[0])])["expert_samples"] / sizes[-1]
            for what, target in (
                ("expert samples", sum(r["expert_samples"] for r in fire) / len(fire)),
                ("execution time", sum(r["execution_s"] for r in fire) / len(fire) * 5),
            ):
                n = max(1, math.ceil(target / per_demo))
                for seed in seeds:
                    bc_row(f"{expert}: BC at FIRE's {what} ({n} demos)", bc(expert, n, seed), seed)
            figure = Path(f"{args.figure}-{expert}") if args.figure else work / f"fire-lift-{expert}"
            shiftkit(
                "plot", "fire", *fire_runs[expert],
                "--bc", f"BC, {sizes[0]}-{sizes[-1]} demos={','.join(curves[expert])}",
                "--out", f"{figure}.png", "--title",
                f"lift at 5 Hz, {expert} expert: FIRE (from {start} demos) vs BC, {len(seeds)} seed(s)", env=env,
            )  # fmt: skip
            figures[expert] = str(figure)

    rows = {name: rows[name] for expert in experts for name in rows if name.startswith(f"{expert}:")}
    policies = {name: pool(runs) for name, runs in rows.items()}
    print(
        "\n| policy | seeds | expert samples (mean) | execution time s (mean) | success per seed | pooled (Wilson 95%) |"
    )
    print("|---|---|---|---|---|---|")
    for name, runs in rows.items():
        p = policies[name]
        samples = sum(r["expert_samples"] for r in runs) / len(runs)
        exec_s = sum(r["execution_s"] for r in runs) / len(runs)
        per_seed = ", ".join(f"{r['successes']}/{r['episodes']}" for r in runs)
        lo, hi = p["ci95"]
        print(
            f"| {name} | {len(runs)} | {samples:.0f} | {exec_s:.0f} | {per_seed} | "
            f"{p['success']:.1%} [{lo:.1%}, {hi:.1%}] |"
        )
    expert = "suboptimal" if "suboptimal" in experts else experts[0]
    fire = policies[f"{expert}: FIRE gda, from {start} demos"]
    matched = next(v for k, v in policies.items() if k.startswith(f"{expert}: BC at FIRE's expert samples"))
    print(
        json.dumps(
            {
                "bench": "science_fire_lift",
                "metric": f"fire_gda_success_minus_bc_at_matched_expert_samples_{expert}",
                "value": round(fire["success"] - matched["success"], 4),
                "goal": 0.0,
                "higher_is_better": True,
                "seeds": seeds,
                "eval_episodes": episodes,
                "figures": figures,
                "quick": quick,
                "policies": policies,
            }
        )
    )


if __name__ == "__main__":
    main()
