"""What the science scripts in bench/science/ share: running each step as a printed `shiftkit` (or
bench) command, a work folder whose datasets a rerun reuses, the committed pipeline files run as
they are, and the pooled summary (Wilson 95% interval over every seed's episodes) printed last as
one JSON line. Not a script itself (tests/test_science_scripts.py runs every other file here)."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

from shiftkit.policies.evaluation import wilson_interval

REPO = Path(__file__).resolve().parents[2]
SHIFTKIT = [sys.executable, "-m", "shiftkit.app.cli"]


def arguments(doc: str, seeds: str = "0,1,2") -> argparse.ArgumentParser:
    """The options every science script takes: --quick, --seeds, --workdir."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke test of every command: one seed, tiny sizes")
    parser.add_argument("--seeds", default=seeds, help=f"training seeds, comma-separated (default: {seeds})")
    parser.add_argument("--workdir", help="keep the datasets and runs here (default: a temporary folder)")
    return parser


def seeds_of(args: argparse.Namespace) -> list[int]:
    return [0] if args.quick else [int(s) for s in args.seeds.split(",")]


def choices_of(parser: argparse.ArgumentParser, option: str, value: str, known: tuple[str, ...]) -> list[str]:
    """The comma-separated names of `value`, in `known`'s order; a usage error names any unknown one."""
    names = [n for n in value.split(",") if n]
    unknown = sorted(set(names) - set(known))
    if unknown or not names:
        problem = f"unknown {', '.join(unknown)}" if unknown else "no name given"
        parser.error(f"{option}: {problem} (choose from {', '.join(known)})")
    return [k for k in known if k in names]


@contextlib.contextmanager
def workspace(workdir: str | None) -> Iterator[tuple[Path, dict[str, str]]]:
    """(folder, environment of the commands): `workdir` if given, else a temporary folder."""
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(workdir or tmp).resolve()
        work.mkdir(parents=True, exist_ok=True)
        env = {
            **os.environ,
            "HF_LEROBOT_HOME": str(work / "lerobot"),
            "HF_HUB_OFFLINE": "1",
            "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
        }
        yield work, env


def shiftkit(*args: str, env: dict[str, str]) -> None:
    """One `shiftkit` command, printed first; run from the repository root, where the committed
    pipelines' calibration paths are relative to."""
    print("+ shiftkit " + " ".join(args), flush=True)
    subprocess.run([*SHIFTKIT, *args], env=env, cwd=REPO, check=True, stdout=subprocess.DEVNULL)


def resumable(run: Path) -> list[str]:
    """`--resume` for a run that stopped after a checkpoint; a run that stopped before its first
    checkpoint is removed (it starts again: its metric lines would otherwise stay)."""
    if (run / "checkpoints" / "last.txt").exists():
        return ["--resume"]
    if run.exists():
        shutil.rmtree(run)
    return []


def bench(script: str, *args: str, env: dict[str, str]) -> dict:
    """`python bench/SCRIPT ARGS`, printed first; its last output line, the bench's JSON result."""
    print(f"+ python bench/{script} " + " ".join(args), flush=True)
    done = subprocess.run(
        [sys.executable, str(REPO / "bench" / script), *args],
        env=env,
        cwd=REPO,
        check=True,
        stdout=subprocess.PIPE,
        text=True,
    )
    return json.loads(done.stdout.strip().splitlines()[-1])


def docs_pipeline(name: str, folder: Path) -> Path:
    """docs/pipelines/NAME.toml copied unchanged to FOLDER/docs/pipelines/, so that its paths (relative
    to the file: ../../data/..., ../../out/...) resolve inside FOLDER."""
    copy = folder / "docs" / "pipelines" / f"{name}.toml"
    copy.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(REPO / "docs" / "pipelines" / f"{name}.toml", copy)
    return copy


def evaluate(policy: Path, out: Path, *args: str, env: dict[str, str]) -> dict:
    """`shiftkit eval --policy POLICY ARGS --out OUT` (reused when OUT exists); its per-episode JSON."""
    if not out.exists():
        shiftkit("eval", "--policy", str(policy), *args, "--out", str(out), env=env)
    return json.loads(out.read_text())


def pool(runs: list[dict]) -> dict:
    """Success over every run's episodes with its Wilson 95% interval; each run holds successes, episodes."""
    k, n = sum(r["successes"] for r in runs), sum(r["episodes"] for r in runs)
    return {"success": round(k / n, 4), "ci95": [round(c, 4) for c in wilson_interval(k, n)], "runs": runs}


def print_table(policies: dict[str, dict]) -> None:
    print("\n| policy | runs | success per run | pooled (Wilson 95%) |")
    print("|---|---|---|---|")
    for name, p in policies.items():
        per_run = ", ".join(f"{r['successes']}/{r['episodes']}" for r in p["runs"])
        lo, hi = p["ci95"]
        print(f"| {name} | {len(p['runs'])} | {per_run} | {p['success']:.1%} [{lo:.1%}, {hi:.1%}] |")


def report(bench_name: str, metric: str, value: float, quick: bool, policies: dict[str, dict], **extra) -> None:
    """The table, then the JSON result as the last line (what tests/test_science_scripts.py reads)."""
    print_table(policies)
    result = {"bench": f"science_{bench_name}", "metric": metric, "value": round(value, 4)}
    print(json.dumps({**result, **extra, "quick": quick, "policies": policies}))


def iqm_ci(
    scores: dict[str, list[float]] | list[float], reps: int = 2000, level: float = 0.95, seed: int = 0
) -> tuple[float, float, float]:
    """(IQM, low, high): the interquartile mean of every run's score and its stratified-bootstrap CI.

    rliable's convention (Agarwal et al. 2021): the IQM is the mean of the middle 50% of all runs'
    scores (scipy's `trim_mean(x, 0.25)`: floor(25%) of the values cut from each end, so 3 runs keep
    all three); the interval is the percentile interval of `reps` bootstrap IQMs in which runs are
    drawn with replacement separately within each task (`scores` = {task: [score per run]}; a plain
    list is one task), so every task keeps its number of runs. The resampling is
    `scipy.stats.bootstrap` with one sample per task (unpaired, so each is resampled on its own),
    seeded with `np.random.default_rng(seed)`: the same scores and seed give the same interval. A
    task with a single run has nothing to resample (scipy refuses such samples) and enters every
    bootstrap IQM as it is; with no task of 2 or more runs the interval is the IQM itself."""
    import numpy as np
    from scipy.stats import bootstrap, trim_mean

    strata = [np.asarray(s, float).reshape(-1) for s in (scores.values() if isinstance(scores, dict) else [scores])]
    if not strata or any(len(s) == 0 for s in strata):
        raise ValueError("iqm_ci needs at least one score per task")
    point = float(trim_mean(np.concatenate(strata), 0.25))
    varied = [s for s in strata if len(s) >= 2]
    fixed = np.concatenate([s for s in strata if len(s) < 2] or [np.empty(0)])
    if not varied:
        return point, point, point

    def statistic(*samples: np.ndarray, axis: int = -1) -> np.ndarray:
        batch = samples[0].shape[:-1]  # scipy's resample batch; the runs are on the last axis
        runs = np.concatenate([*samples, np.broadcast_to(fixed, (*batch, len(fixed)))], axis=-1)
        return trim_mean(runs, 0.25, axis=-1)

    ci = bootstrap(
        varied, statistic, n_resamples=reps, vectorized=True, axis=-1, confidence_level=level,
        method="percentile", rng=np.random.default_rng(seed),
    ).confidence_interval  # fmt: skip
    return point, float(ci.low), float(ci.high)
