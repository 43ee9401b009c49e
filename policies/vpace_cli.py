"""CLI glue for `shiftkit train vpace|lfgp` and the success-curve plot; the logic lives in vpace.py/curves.py.

Every hyperparameter of `VPACEArgs` is a flag (`--total-steps`, `--main-rate`, ...) whose help is the
field's docstring; flags left out keep the chosen `--variant`'s preset and the thesis defaults.
"""

from __future__ import annotations

import argparse
import dataclasses
import typing

from shiftkit.pipelines.dataclass_config import add_env_kwarg, csv_list

# Fields with a hand-made flag (lists, dicts, renamed or preset-only ones); the rest are generated.
_SPECIAL = {
    "examples",
    "aux_tasks",
    "handcrafted",
    "hidden",
    "env_kwargs",
    "multitask",
    "full_trajectories",
    "variant",
    "output_dir",
    "torch_threads",
    "resume",
    "frames_as_examples",
}


def _scalar_type(tp: object) -> type:
    """int / float / str behind `X` or `X | None` annotations."""
    args = [a for a in typing.get_args(tp) if a is not type(None)]
    return args[0] if args else tp  # type: ignore[return-value]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Flags of `train vpace` and `train lfgp` (the subcommand name sets the default variant)."""
    from shiftkit.pipelines.dataclass_config import field_docs
    from shiftkit.policies.vpace import VARIANTS, VPACEArgs

    docs = field_docs(VPACEArgs)
    hints = typing.get_type_hints(VPACEArgs)
    p = parser
    p.add_argument(
        "--examples",
        type=csv_list,
        required=True,
        help="example dataset ID(s) or local folder(s), comma-separated; frames' `task` names the task",
    )
    p.add_argument("--env", default=None, help=f"{docs['env']} (default: panda-play)")
    p.add_argument("--main-task", required=True, help=docs["main_task"])
    p.add_argument("--aux-tasks", type=csv_list, default=None, help=docs["aux_tasks"] + " Comma-separated.")
    p.add_argument("--output", required=True, help=docs["output_dir"])
    p.add_argument(
        "--variant",
        choices=list(VARIANTS),
        default=None,
        help="vpace | ace | vp-sqil | sqil | dac | rce | lfgp (default: the subcommand's name)",
    )
    p.add_argument(
        "--single-task",
        dest="multitask",
        action="store_false",
        default=None,
        help="main intention only (no scheduler), overriding the variant",
    )
    p.add_argument(
        "--handcrafted",
        action="append",
        default=None,
        metavar="T1,T2,...",
        help=docs["handcrafted"] + " Repeatable, e.g. --handcrafted panda or "
        "--handcrafted reach,lift,main,open,reach,lift,main,open",
    )
    p.add_argument(
        "--hidden",
        type=lambda s: tuple(int(x) for x in csv_list(s)),
        default=None,
        help="hidden widths, comma-separated (default: 256,256)",
    )
    add_env_kwarg(p, "control_hz=5", dest="env_kwargs", default=None)
    p.add_argument("--threads", dest="torch_threads", type=int, default=None, help=docs["torch_threads"])
    p.add_argument("--resume", action="store_true", help=docs["resume"])
    p.add_argument("--frames-as-examples", action="store_true", default=None, help=docs["frames_as_examples"])
    for f in dataclasses.fields(VPACEArgs):
        if f.name in _SPECIAL or f.name in ("env", "main_task"):
            continue
        default = f.default if f.default is not dataclasses.MISSING else None
        p.add_argument(
            f"--{f.name.replace('_', '-')}",
            type=_scalar_type(hints[f.name]),
            default=None,
            help=f"{docs.get(f.name, '')} (default: {default})",
        )


def build_args(args: argparse.Namespace):
    """`VPACEArgs` from parsed flags: the variant preset, then every flag that was given."""
    from shiftkit.policies.vpace import VPACEArgs

    variant = args.variant or getattr(args, "trainer", None) or "vpace"
    overrides = {}
    for f in dataclasses.fields(VPACEArgs):
        key = "output" if f.name == "output_dir" else f.name
        value = getattr(args, key, None)
        if value is not None and f.name not in ("variant", "resume"):
            overrides[f.name] = dict(value) if f.name == "env_kwargs" else value
    return VPACEArgs.for_variant(variant, resume=bool(args.resume), **overrides)


def run(args: argparse.Namespace) -> int:
    from shiftkit.policies.vpace import train

    config = build_args(args)
    metrics = train(config)
    shown = ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in metrics.items())
    print(f"trained {config.variant} ({config.main_task}) in {config.output_dir}" + (f": {shown}" if shown else ""))
    return 0


def add_plot_arguments(parser: argparse.ArgumentParser) -> None:
    """Flags of the success-curve plot command."""
    parser.add_argument(
        "groups",
        nargs="+",
        metavar="LABEL=RUN[,RUN...]",
        help="a method's label and its run folders (one per seed; several tasks allowed)",
    )
    parser.add_argument("--out", required=True, help="PNG file to write")
    parser.add_argument("--title", default="", help="plot title")
    parser.add_argument("--reps", type=int, default=2000, help="bootstrap resamples (default: 2000)")
    parser.add_argument("--seed", type=int, default=0, help="bootstrap seed (default: 0)")


def run_plot(args: argparse.Namespace) -> int:
    from pathlib import Path

    from shiftkit.pipelines.errors import ConfigError
    from shiftkit.policies.curves import aggregate, plot_curves

    curves = []
    for group in args.groups:
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
