"""Trainer `bc`: behavioural cloning, one network or an ensemble (`training.py`), and its `shiftkit train bc` glue."""

from __future__ import annotations

import argparse

from shiftkit.pipelines.option_values import DataclassOptions
from shiftkit.policies.trainers import Trainer, register

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
    """`BCArgs` as options: counts and widths positive, the seed >= 0, rates positive."""
    from shiftkit.policies.trainers.bc.args import OUTPUT_ACTIVATIONS, REGIMES

    positive = (
        "steps",
        "max_epochs",
        "patience",
        "batch_size",
        "ensemble_size",
        "num_keypoints",
        "hidden",
        "checkpoint_every",
        "log_every",
        "threads",
    )
    return DataclassOptions(
        TRAINER.args_class(),
        flags={
            "datasets": "dataset",
            "output_dir": "output",
            "ensemble_size": "ensemble",
            "num_keypoints": "keypoints",
        },
        rules={
            **dict.fromkeys(positive, "positive_int"),
            **dict.fromkeys(("lr", "norm_clip"), "positive_float"),
            **dict.fromkeys(("weight_decay", "val_fraction", "norm_std_floor"), "non_negative_float"),
            "seed": "non_negative_int",
        },
        choices={"regime": REGIMES, "encoder": ("cnn", "resnet18"), "output_activation": OUTPUT_ACTIVATIONS},
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
