"""Reading a FIRE run folder back: its per-episode lines, final summary, ROC scores and success curves
(`shiftkit plot fire`, the docs' figures).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from shiftkit.datasets import loaders
from shiftkit.policies.evaluation import wilson_interval
from shiftkit.policies.run_dir import RunDir


def summary(run_dir: RunDir, counters: dict) -> dict:
    """The final summary of a run: episodes (and how many were the warm-up), outcomes, the expert's
    answers, takeovers and hand-backs, and samples (expert samples: demonstrations + corrections)."""
    lines = [x for x in run_dir.read_metrics() if x["split"] == "episode"]
    feedback = [f for x in lines for f in x["feedback"]]
    return {
        "episodes": counters["episode"],
        "warm_up_episodes": sum(not x["d_ready"] for x in lines),
        "successes": sum(x["success"] for x in lines),
        "policy_successes": sum(x["policy_success"] for x in lines),
        "corrections": counters["corrections"],
        "interventions": counters["interventions"],
        "hand_backs": counters["hand_backs"],
        "expert_samples": counters["demo_frames"] + counters["corrections"],
        "env_steps": counters["env_steps"],
        "true_positives": feedback.count("tp"),
        "false_positives": feedback.count("fp"),
        "false_negatives": feedback.count("fn"),
        "retrains": counters["retrains"],
    }


def protocol_check(run_path: str | Path) -> dict:
    """Algorithm 2's warm-up and hand-backs as a finished run shows them, read twice: from its episode
    lines (metrics.jsonl) and from its DAgger-layout recording (rollouts/, `intervention` per frame).
    A hand-back is a correction after which the policy drives again in the same episode."""
    from shiftkit.datasets.reader import open_lerobot_dataset

    lines = [x for x in RunDir(Path(run_path), resume=True).read_metrics() if x["split"] == "episode"]
    warm = sum(not x["d_ready"] for x in lines)
    flags = [
        ep.frames["intervention"][:, 0] for ep in open_lerobot_dataset(Path(run_path) / "rollouts").iter_episodes()
    ]
    handed = [int((np.diff(f.astype(int)) == -1).sum()) for f in flags]
    return {
        "metrics": {
            "episodes": len(lines),
            "warm_up_episodes": warm,
            "interventions_before_d": sum(len(x["interventions"]) for x in lines[:warm]),
            "interventions": sum(len(x["interventions"]) for x in lines),
            "hand_backs": sum(i["end"] < x["length"] for x in lines for i in x["interventions"]),
        },
        "recording": {
            "episodes": len(flags),
            "intervention_frames_before_d": int(sum(f.sum() for f in flags[:warm])),
            "first_episode_with_intervention": next((i for i, f in enumerate(flags) if f.any()), None),
            "hand_backs": sum(handed),
            "episodes_with_hand_back": sum(h > 0 for h in handed),
        },
    }


# What the figures read from each per-episode line of a FIRE run's metrics.jsonl.
EPISODE_LINE = loaders.obj(
    d_ready=loaders.boolean,
    policy_success=loaders.boolean,
    expert_samples=loaders.number(0.0),
    execution_time_s=loaders.number(0.0),
    scores=loaders.map_of(loaders.number(finite=False)),  # a rule's score may be infinite
)


def read_episode_lines(run_path: str | Path) -> list[dict]:
    """The per-episode metric lines of a FIRE run, each with the numbers the figures read;
    ShiftkitError (one line) for anything else."""
    from shiftkit.datasets.errors import ShiftkitError

    run_dir = RunDir(Path(run_path), resume=True)
    config = run_dir.read_config() if (Path(run_path) / "config.json").is_file() else None
    if config is None or config["trainer"] != "fire":
        raise ShiftkitError(f"{run_path} is not a FIRE run folder (no config.json of trainer 'fire')")
    metrics = Path(run_path) / "metrics.jsonl"
    lines = loaders.load_metrics(metrics, EPISODE_LINE, split="episode") if metrics.is_file() else []
    if not lines:
        raise ShiftkitError(f"FIRE run {run_path} has no finished episode yet")
    return lines


def roc_scores(lines: list[dict]) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Per-predictor episode scores (beta, gda and, for an ensemble policy, doubt and the quantile OR
    of gda and doubt) and the labels (the policy's uninterrupted run failed) of the episodes after D
    started."""
    from shiftkit.datasets.errors import ShiftkitError
    from shiftkit.policies.fire.failure_predictors import quantile_or

    ready = [x for x in lines if x["d_ready"]]
    missing = {name for x in ready for name in ("beta", "gda") if name not in x["scores"]}
    if missing:
        raise ShiftkitError(f"a FIRE episode line has no {sorted(missing)[0]!r} score")
    names = [n for n in ("beta", "gda", "doubt") if all(n in x["scores"] for x in ready)]
    scores = {name: np.array([x["scores"][name] for x in ready], dtype=float) for name in names}
    if "doubt" in scores:
        scores["gda+doubt"] = quantile_or(scores["gda"], scores["doubt"])
    return scores, np.array([not x["policy_success"] for x in ready])


def success_curve(
    lines: list[dict], x_key: str, window: int = 10
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(x, success rate, 95% low, high) of the policy's own outcome over a moving window of episodes
    (each FIRE episode's label is an evaluation of the policy of that time, see `run_episode`)."""
    x = np.array([line[x_key] for line in lines], dtype=float)
    ok = np.array([line["policy_success"] for line in lines], dtype=float)
    rate, low, high = [], [], []
    for i in range(len(ok)):
        part = ok[max(0, i - window + 1) : i + 1]
        lo, hi = wilson_interval(int(part.sum()), len(part))
        rate.append(part.mean())
        low.append(lo)
        high.append(hi)
    return x, np.array(rate), np.array(low), np.array(high)


def seed_curve(
    runs: list[list[dict]], x_key: str, window: int = 10, reps: int = 2000
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One method over seeds: each run's `success_curve` as a step function of `x_key`, read on the
    x values where every run has data; (x, IQM over the runs, 95% low, high), the interval a
    bootstrap over runs (`curves.stratified_bootstrap_ci`; a single run's band is its line)."""
    from shiftkit.policies.curves import iqm, stratified_bootstrap_ci

    curves = [success_curve(lines, x_key, window)[:2] for lines in runs]
    first, last = max(x[0] for x, _ in curves), min(x[-1] for x, _ in curves)
    grid = np.unique(np.concatenate([x[(x >= first) & (x <= last)] for x, _ in curves]))
    values = np.array([[y[np.searchsorted(x, g, side="right") - 1] for g in grid] for x, y in curves])
    low, high = stratified_bootstrap_ci(values, np.zeros(len(runs)), reps)
    return grid, iqm(values, axis=0), low, high


def bc_curve(run_paths: list[str | Path]) -> list[dict]:
    """BC as a curve over its training data: the runs grouped by the datasets they trained on (e.g.
    seeds of BC from 10, 20, ... demonstrations), each group pooled as `bc_reference`, in order of
    expert samples."""
    from shiftkit.policies.run_dir import trained_datasets

    groups: dict[tuple, list[Path]] = {}
    for path in map(Path, run_paths):
        key = tuple(sorted(str(d.get("root", "")) for d in trained_datasets(path)))
        groups.setdefault(key, []).append(path)
    return sorted((bc_reference(paths) for paths in groups.values()), key=lambda r: r["expert_samples"])


def bc_reference(run_paths: list[str | Path]) -> dict:
    """The point a BC policy stands at on FIRE's figures, pooled over `run_paths` (e.g. one run per
    seed): expert samples = the frames of its training datasets (mean over the runs), execution time =
    those frames / fps, success = its evaluations' episodes (the one eval/*.json of each run) with the
    Wilson 95% interval."""
    from shiftkit.datasets.errors import ShiftkitError
    from shiftkit.policies.run_dir import EVAL, trained_datasets

    samples, seconds, successes, episodes = [], [], 0, 0
    for path in map(Path, run_paths):
        datasets = trained_datasets(path)
        if not datasets:
            raise ShiftkitError(f"{path} is not a run folder that names its training datasets (config.json)")
        frames = time_s = 0.0
        for record in datasets:
            info = loaders.load_info(Path(record.get("root") or "") / "meta" / "info.json")
            total = info.get("total_frames", 0)
            frames += total
            time_s += total / (record.get("fps") or info["fps"])
        evals = sorted((path / EVAL).glob("*.json"))
        if len(evals) != 1:
            found = ", ".join(e.name for e in evals) or "none"
            raise ShiftkitError(f"{path}: needs exactly one evaluation in {path / EVAL} (found {found})")
        result = loaders.load_evaluation(evals[0])
        samples.append(frames)
        seconds.append(time_s)
        successes += result.get("successes", round(result["success_rate"] * result["episodes"]))
        episodes += result["episodes"]
    low, high = wilson_interval(successes, episodes)
    return {
        "runs": len(samples),
        "expert_samples": float(np.mean(samples)),
        "execution_time_s": float(np.mean(seconds)),
        "successes": successes,
        "episodes": episodes,
        "success": successes / episodes if episodes else 0.0,
        "ci95": [low, high],
    }
