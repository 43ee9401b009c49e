"""Trainer `bc`: behavioural cloning, one network or an ensemble (`training.py`), and its `shiftkit train bc` glue."""

from __future__ import annotations

import argparse

from shiftkit.datasets.option_values import DataclassOptions
from shiftkit.policies.trainers import Trainer, register
from shiftkit.policies.trainers.bc.args import FLAGS

TRAINER = register(
    Trainer(
        name="bc",
        help="behavioural cloning (MSE; one network by default, --ensemble N; CNN + spatial soft-argmax for cameras)",
        args=f"{__name__}.args:BCArgs",
        cli=__name__,
        load_policy="shiftkit.policies.bc_policy:load_policy",
    )
)


def options() -> DataclassOptions:
    """`BCArgs` as options (each field's rule and choices are the field's own)."""
    return DataclassOptions(
        TRAINER.args_class(),
        flags={"datasets": "dataset", "output_dir": "output", **FLAGS},
    )


def add_arguments(parser: argparse.ArgumentParser, trainer: Trainer) -> None:
    """Adds the options of `shiftkit train bc` to `parser`."""
    options().add_to(parser)
    parser.add_argument(
        "--progress", action=argparse.BooleanOptionalAction, default=True, help="show a progress bar (default: on)"
    )


def run(args: argparse.Namespace) -> int:
    """Trains a BC policy from the parsed options; returns the exit code."""
    from shiftkit.policies.trainers.bc.training import train

    config = options().build(args)
    if config.regime == "early-stop":
        steps = f"{config.steps} steps or " if config.steps else ""
        print(
            f"early-stop: at most {steps}{config.max_epochs} epochs; ends sooner once every member has not "
            f"improved for {config.patience} epochs"
        )
    metrics = train(config, progress=args.progress)
    shown = ", ".join(
        f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in metrics.items() if not isinstance(v, list)
    )
    print(f"trained BC policy in {config.output_dir}: {shown}")
    return 0
