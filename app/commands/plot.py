"""`shiftkit plot roc|fire|curves RUN...`: figures of runs (PNG): FIRE's failure prediction and
success, and the success curves of RL runs (VPACE, LfGP, SQIL, ...) across seeds."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field

from shiftkit.datasets.dataclass_config import field_help, option
from shiftkit.datasets.option_values import DataclassOptions

HELP = (
    "plot runs: ROC curves of FIRE's failure predictors (roc), FIRE's success vs expert samples and time (fire), "
    "success curves of RL runs across seeds (curves)"
)

PREDICTOR_LABELS = {"beta": "beta rule", "gda": "GDA", "doubt": "ensemble doubt", "gda+doubt": "GDA or doubt"}


@dataclass(frozen=True)
class RocFigure:
    """`plot roc`: ROC curves of every failure predictor, pooled over the runs' episodes after D started."""

    out: str
    """PNG file to write"""
    runs: tuple[str, ...] = ()
    """FIRE run folders or aggregated datasets (`fire aggregate`) (positional)"""
    title: str = ""
    """plot title (default: the runs, n episodes and n failed)"""


@dataclass(frozen=True)
class FireFigure:
    """`plot fire`: policy success against expert samples and against execution time, one line per
    method over its seeds, BC as points or a curve over its number of demonstrations (thesis Figs. 5.3
    and 5.9)."""

    out: str
    """PNG path; -expert and -time are added before .png"""
    runs: tuple[str, ...] = ()
    """FIRE run folders, each as [LABEL=]RUN (positional); runs given the same LABEL (e.g. seeds) are one
    line: the IQM of their success curves with a 95% bootstrap band over the runs"""
    window: int = option(10, rule="positive_int")
    """episodes per success estimate"""
    bc: dict[str, str] = field(default_factory=dict)
    """LABEL=RUN[,RUN...]: BC runs (each with its one eval/*.json): runs on the same training data (e.g.
    seeds) pooled into one point, x = its frames (/ fps on the time panel), y = the pooled evaluation
    episodes' success with the Wilson 95% CI; runs on several datasets (e.g. 10, 20, ... 60
    demonstrations) a curve through those points; repeatable, one LABEL each"""
    title: str = ""
    """plot title (default: the curves and points)"""


@dataclass(frozen=True)
class CurvesFigure:
    """`plot curves`: evaluation success curves of RL runs across seeds, the interquartile mean with
    stratified bootstrap 95% CIs, one curve per method."""

    out: str
    """PNG file to write"""
    runs: tuple[str, ...] = ()
    """a method's label and its run folders, LABEL=RUN[,RUN...] (one per seed; several tasks allowed) (positional)"""
    title: str = ""
    """plot title"""
    reps: int = option(2000, rule="positive_int")
    """bootstrap resamples"""
    seed: int = option(0, rule="non_negative_int")
    """bootstrap seed"""


ROC_OPTIONS = DataclassOptions(RocFigure, skip=("runs",))
CURVES_OPTIONS = DataclassOptions(CurvesFigure, skip=("runs",))
FIRE_OPTIONS = DataclassOptions(FireFigure, skip=("runs",))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """One subcommand per figure (`roc`, `fire`), its options generated from its dataclass."""
    sub = parser.add_subparsers(dest="figure", metavar="FIGURE", required=True)
    roc = sub.add_parser(
        "roc",
        help="ROC of every failure predictor over the runs' episodes (AUC in the legend)",
        description="ROC curves of beta rule, GDA, ensemble doubt and GDA-or-doubt, pooled over the runs' "
        "episodes after D started; label: whether the policy's uninterrupted run failed.",
    )
    roc.add_argument("runs", nargs="+", metavar="RUN", help=field_help(RocFigure, "runs"))
    ROC_OPTIONS.add_to(roc)
    roc.set_defaults(_plot=_run_roc, _options=ROC_OPTIONS)
    fire = sub.add_parser(
        "fire",
        help="policy success vs expert samples and vs execution time",
        description="Success of each run's policy (moving window of episodes, Wilson 95% CI) against the "
        "expert samples and against the total execution time, with BC runs as points at their training "
        "frames; writes OUT-expert.png and OUT-time.png.",
    )
    fire.add_argument("runs", nargs="+", metavar="[LABEL=]RUN", help=field_help(FireFigure, "runs"))
    FIRE_OPTIONS.add_to(fire)
    fire.set_defaults(_plot=_run_fire, _options=FIRE_OPTIONS)
    curves = sub.add_parser(
        "curves",
        help="success curves across seeds: IQM with stratified bootstrap 95%% CIs",
        description="Plot evaluation success curves of runs: LABEL=RUN[,RUN...] per method.",
    )
    curves.add_argument("runs", nargs="+", metavar="LABEL=RUN[,RUN...]", help=field_help(CurvesFigure, "runs"))
    CURVES_OPTIONS.add_to(curves)
    curves.set_defaults(_plot=_run_curves, _options=CURVES_OPTIONS)


def check_figure_path(out: str, flag: str = "--out") -> None:
    """`out` (given as `flag`) must name a format matplotlib writes, checked before any work."""
    from pathlib import Path

    from matplotlib.figure import Figure

    from shiftkit.datasets.errors import ConfigError

    formats = Figure().canvas.get_supported_filetypes()
    suffix = Path(out).suffix.lower().lstrip(".")
    if suffix and suffix not in formats:
        raise ConfigError(
            f"{flag} {out}: format {suffix!r} is not one matplotlib writes ({', '.join(sorted(formats))})"
        )


def _run_roc(args: RocFigure) -> int:
    from pathlib import Path

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from shiftkit.datasets.errors import ConfigError
    from shiftkit.policies.fire.aggregate import ROC_FILE, read_roc
    from shiftkit.policies.fire.failure_predictors import roc_curve
    from shiftkit.policies.fire.runs import read_episode_lines, roc_scores

    check_figure_path(args.out)
    pooled: dict[str, list] = {}
    labels = []
    for run in args.runs:
        # an aggregated dataset scores policy stretches against the recorded interventions
        scores, failed = read_roc(run) if (Path(run) / ROC_FILE).is_file() else roc_scores(read_episode_lines(run))
        for name, values in scores.items():
            pooled.setdefault(name, []).append(values)
        labels.append(failed)
    pooled = {name: parts for name, parts in pooled.items() if len(parts) == len(args.runs)}
    failed = np.concatenate(labels)
    if failed.all() or not failed.any():
        raise ConfigError(
            f"ROC needs episodes after D started with both outcomes; got {int(failed.sum())} failed of {len(failed)}"
        )
    fig, ax = plt.subplots(figsize=(5, 5), dpi=120)
    ax.plot([0, 1], [0, 1], color="grey", linestyle="--", linewidth=1)
    for name, parts in pooled.items():
        fpr, tpr, auc = roc_curve(np.concatenate(parts), failed)
        ax.plot(fpr, tpr, label=f"{PREDICTOR_LABELS[name]} (AUC {auc:.2f})")
        print(f"{name}: AUC {auc:.3f}")
    ax.set_xlabel("false positive rate")
    ax.set_ylabel("true positive rate")
    names = ", ".join(Path(run).name for run in args.runs)
    if len(names) > 50:  # what fits above a 5-inch figure
        names = f"{len(args.runs)} runs ({Path(args.runs[0]).name}, ...)"
    ax.set_title(
        args.title or f"failure prediction, {names}\n(n = {len(failed)} episodes, {int(failed.sum())} failed)",
        fontsize=9,
    )
    ax.legend(loc="lower right")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    print(f"wrote {out}")
    return 0


def _run_fire(args: FireFigure) -> int:
    from pathlib import Path

    import numpy as np

    from shiftkit.datasets.dataclass_config import csv_list
    from shiftkit.policies.curves import Curve, Point, plot_curves
    from shiftkit.policies.fire.runs import bc_curve, read_episode_lines, seed_curve, success_curve

    check_figure_path(args.out)
    methods: dict[str, list[list[dict]]] = {}  # label -> its runs' episode lines
    for item in args.runs:
        label, sep, path = item.partition("=")
        label, path = (label, path) if sep else (Path(item).name, item)
        methods.setdefault(label, []).append(read_episode_lines(path))
    bc = {label: bc_curve(csv_list(str(paths))) for label, paths in args.bc.items()}
    out = Path(args.out)
    written = []
    for suffix, key, xlabel in (
        ("expert", "expert_samples", "expert samples (demonstrations + corrections)"),
        ("time", "execution_time_s", "total execution time (s)"),
    ):
        curves, points = [], []
        for label, runs in methods.items():
            x, rate, low, high = seed_curve(runs, key, args.window)
            what = "IQM, 95% bootstrap CI" if len(runs) > 1 else f"{len(runs[0])} episodes"
            curves.append(Curve(f"{label} ({what})", x, rate, low, high, len(runs)))
        for label, refs in bc.items():
            runs = sum(r["runs"] for r in refs)
            if len(refs) == 1:
                p = refs[0]
                points.append(Point(f"{label}, {runs} run{'s' if runs != 1 else ''} pooled", p[key], p["success"],
                                    *p["ci95"], p["episodes"]))  # fmt: skip
            else:
                xs, ys = np.array([r[key] for r in refs]), np.array([r["success"] for r in refs])
                lows, highs = (np.array([r["ci95"][i] for r in refs]) for i in (0, 1))
                curves.append(Curve(f"{label} (seeds pooled per size, Wilson 95%)", xs, ys, lows, highs, runs))
        path = out.with_name(f"{out.stem}-{suffix}{out.suffix or '.png'}")
        ylabel = f"policy success ({args.window}-episode window for FIRE)"
        try:
            written.append(plot_curves(curves, path, args.title, xlabel, ylabel, tuple(points)))
        except BaseException:  # both figures or neither
            for done in written:
                done.unlink(missing_ok=True)
            raise
    for label, runs in methods.items():
        finals = [success_curve(lines, "expert_samples", args.window)[1][-1] for lines in runs]
        last = [lines[-1] for lines in runs]
        print(
            f"{label}: {len(runs)} run(s), {np.mean([len(lines) for lines in runs]):.0f} episodes, "
            f"{np.mean([x['expert_samples'] for x in last]):.0f} expert samples, "
            f"{np.mean([x['execution_time_s'] for x in last]):.0f} s executed (means); policy success over "
            f"the last {args.window}: {', '.join(f'{f:.0%}' for f in finals)}"
        )
    for label, refs in bc.items():
        for p in refs:
            print(
                f"{label}: {p['runs']} BC run(s), {p['expert_samples']:.0f} expert samples, "
                f"{p['execution_time_s']:.0f} s; success {p['successes']}/{p['episodes']} = {p['success']:.0%} "
                f"[{p['ci95'][0]:.0%}, {p['ci95'][1]:.0%}]"
            )
    print("wrote " + ", ".join(str(p) for p in written))
    return 0


def _run_curves(args: CurvesFigure) -> int:
    from pathlib import Path

    from shiftkit.datasets.dataclass_config import csv_list
    from shiftkit.datasets.errors import ConfigError
    from shiftkit.policies.curves import aggregate, plot_curves

    check_figure_path(args.out)
    curves = []
    for group in args.runs:
        label, sep, runs = group.partition("=")
        if not sep or not label or not csv_list(runs):
            raise ConfigError(f"expected LABEL=RUN[,RUN...], got {group!r}")
        curves.append(aggregate(label, [Path(r) for r in csv_list(runs)], args.reps, args.seed))
    out = plot_curves(curves, Path(args.out), args.title)
    for c in curves:
        print(
            f"{c.label}: final IQM {c.iqm[-1]:.3f} [{c.low[-1]:.3f}, {c.high[-1]:.3f}] at step {c.steps[-1]} "
            f"over {c.runs} runs"
        )
    print(f"wrote {out}")
    return 0


def run(args: argparse.Namespace) -> int:
    """Draw the chosen figure from its options; return the exit code."""
    return args._plot(args._options.build(args, runs=tuple(args.runs)))
