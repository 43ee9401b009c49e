"""Success curves across seeds: interquartile mean (IQM) with stratified bootstrap 95% CIs (rliable-style).

Each run contributes its evaluation success rates (`split == "eval"` lines of metrics.jsonl) at the
evaluation steps it shares with the other runs of its method. At each step the IQM is the mean of the
middle 50% of all run scores (the lowest and highest 25% cut, as scipy's trim_mean); its confidence
interval comes from bootstrap resamples that draw runs with replacement separately within each task
(stratum), so every task keeps its number of runs (Agarwal et al. 2021).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shiftkit.datasets.errors import ShiftkitError


def iqm(scores: np.ndarray, axis: int = -1) -> np.ndarray:
    """Interquartile mean along `axis`: cut floor(25%) of the values from each end, average the rest."""
    scores = np.sort(np.asarray(scores, float), axis=axis)
    n = scores.shape[axis]
    cut = int(0.25 * n)
    return np.take(scores, np.arange(cut, n - cut), axis=axis).mean(axis=axis)


def stratified_bootstrap_ci(
    scores: np.ndarray, strata: np.ndarray, reps: int = 2000, level: float = 0.95, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Percentile CI of the IQM of `scores` (runs, steps); runs are resampled within each stratum."""
    rng = np.random.default_rng(seed)
    groups = [np.flatnonzero(strata == s) for s in np.unique(strata)]
    picks = np.concatenate([g[rng.integers(0, len(g), (reps, len(g)))] for g in groups], axis=1)  # (reps, runs)
    boot = iqm(scores[picks], axis=1)  # (reps, steps)
    tail = (1.0 - level) / 2.0 * 100.0
    return np.percentile(boot, tail, axis=0), np.percentile(boot, 100.0 - tail, axis=0)


@dataclass
class Curve:
    """One method's aggregate curve."""

    label: str
    steps: np.ndarray
    iqm: np.ndarray
    low: np.ndarray
    high: np.ndarray
    runs: int
    tasks: tuple[str, ...] = ()
    """The tasks its runs trained on (named in the default title)."""


def read_success(run_dir: Path, metric: str = "success_rate") -> tuple[str, dict[int, float]]:
    """(task, {step: success}) from a run directory's config.json and metrics.jsonl."""
    from shiftkit.datasets import loaders

    config = loaders.load_run_config(run_dir / "config.json")
    lines = loaders.load_metrics(run_dir / "metrics.jsonl", split="eval")
    evals = [x for x in lines if metric in x]
    points = {
        x["step"]: loaders.check_value(
            x, loaders.obj(**{metric: loaders.number()}), f"{run_dir}/metrics.jsonl step {x['step']}"
        )[metric]
        for x in evals
    }
    if not points:
        raise ShiftkitError(f"run {run_dir} has no evaluation lines with {metric!r}")
    return str(config["args"].get("main_task", "")), points


def aggregate(label: str, run_dirs: list[Path], reps: int = 2000, seed: int = 0) -> Curve:
    """IQM curve and CI of `run_dirs` over the evaluation steps all of them reached."""
    runs = [read_success(Path(d)) for d in run_dirs]
    steps = sorted(set.intersection(*(set(points) for _, points in runs)))
    if not steps:
        raise ShiftkitError(f"runs of {label!r} share no evaluation step")
    scores = np.array([[points[s] for s in steps] for _, points in runs])
    strata = np.array([task for task, _ in runs])
    low, high = stratified_bootstrap_ci(scores, strata, reps, seed=seed)
    tasks = tuple(sorted({task for task, _ in runs if task}))
    return Curve(label, np.array(steps), iqm(scores, axis=0), low, high, len(runs), tasks)


@dataclass
class Point:
    """A single policy's result drawn as a point with a vertical 95% CI (e.g. BC on FIRE's figures)."""

    label: str
    x: float
    rate: float
    low: float
    high: float
    episodes: int


def draw_curves(
    curves: list[Curve],
    title: str = "",
    xlabel: str = "environment steps",
    ylabel: str = "success rate (IQM, 95% CI)",
    points: tuple[Point, ...] = (),
):
    """A matplotlib Figure of IQM lines with shaded CIs and `points` with error bars; without
    `title`, the title names the curves, points and tasks (each legend entry gives its n)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
    for c in curves:
        (line,) = ax.plot(c.steps, c.iqm, label=f"{c.label} (n = {c.runs} run{'s' if c.runs != 1 else ''})")
        ax.fill_between(c.steps, c.low, c.high, color=line.get_color(), alpha=0.25, linewidth=0)
    for p in points:
        ax.errorbar(
            [p.x], [p.rate], yerr=[[p.rate - p.low], [p.high - p.rate]], fmt="D", capsize=4,
            label=f"{p.label} (n = {p.episodes} episodes)",
        )  # fmt: skip
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    # beside the axes, where it hides no curve or band (curves spanning the whole axes leave no "best" spot)
    fig.set_size_inches(9.5, 4)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    names = [c.label for c in curves] + [p.label for p in points]
    tasks = sorted({t for c in curves for t in c.tasks})
    on = f" on {', '.join(tasks)}" if tasks else ""
    ax.set_title(title or f"{' vs '.join(names)}{on}: {ylabel}", fontsize=9)
    fig.tight_layout()
    return fig


def plot_curves(
    curves: list[Curve],
    out: Path,
    title: str = "",
    xlabel: str = "environment steps",
    ylabel: str = "success rate (IQM, 95% CI)",
    points: tuple[Point, ...] = (),
) -> Path:
    """Draw `draw_curves`' figure into a PNG."""
    import matplotlib.pyplot as plt

    fig = draw_curves(curves, title, xlabel, ylabel, points)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out
