"""Trainers `vpace` and `lfgp`: scheduled auxiliary control from success examples or expert
trajectories (`training.py`) and their `shiftkit train vpace|lfgp` glue (`shiftkit plot curves` draws
their runs' success curves, `policies/curves.py`).

Every hyperparameter of `VPACEArgs` is an option generated from the dataclass
(`option_values.DataclassOptions`: `--total-steps`, `--main-rate`, ..., help from the field's
docstring); options left out keep the chosen `--variant`'s preset and the thesis defaults.
"""

from __future__ import annotations

import argparse

from shiftkit.datasets.option_values import DataclassOptions
from shiftkit.policies.trainers import Trainer, register

for _name, _help, _citation in (
    (
        "vpace",
        "VPACE / ACE / SQIL / DAC / RCE from success examples",
        "Ablett et al., *Efficient imitation without demonstrations via value-penalized auxiliary control "
        "from examples*, ICRA 2025.",
    ),
    (
        "lfgp",
        "Learning from Guided Play (expert trajectories, multitask DAC, thesis Table A.2)",
        "Ablett et al., *Learning from guided play: improving exploration for adversarial imitation learning "
        "with simple auxiliary tasks*, RA-L 2023.",
    ),
):
    register(
        Trainer(
            name=_name,
            help=_help,
            args=f"{__name__}.args:VPACEArgs",
            cli=__name__,
            load_policy=f"{__name__}.training:load_policy",
            citation=_citation,
        )
    )


def options() -> DataclassOptions:
    """`VPACEArgs` as options (each field's rule and choices are the field's own); `variant` and
    `handcrafted` are made by `add_arguments`, the preset-only `full_trajectories` has none."""
    from shiftkit.policies.trainers.vpace.args import VPACEArgs

    return DataclassOptions(
        VPACEArgs,
        skip=("variant", "handcrafted", "full_trajectories"),
        flags={"output_dir": "output", "torch_threads": "threads", "env_kwargs": "env-kwarg"},
        required=("examples", "main_task", "output_dir"),
    )


def add_arguments(parser: argparse.ArgumentParser, trainer: Trainer) -> None:
    """Options of `train vpace` and `train lfgp` (the subcommand's name is the default variant)."""
    from shiftkit.datasets.dataclass_config import field_help
    from shiftkit.policies.trainers.vpace.args import VARIANTS, VPACEArgs

    options().add_to(parser)
    parser.add_argument(
        "--variant",
        choices=list(VARIANTS),
        default=trainer.name,
        help=f"{field_help(VPACEArgs, 'variant')} (default: {trainer.name})",
    )
    parser.add_argument(
        "--handcrafted",
        action="append",
        default=argparse.SUPPRESS,
        metavar="T1,T2,...",
        help=field_help(VPACEArgs, "handcrafted") + " Repeatable, e.g. --handcrafted panda or "
        "--handcrafted reach,lift,main,open,reach,lift,main,open",
    )


def build_args(args: argparse.Namespace):
    """`VPACEArgs` from parsed options: the variant preset, then every option that was given."""
    from shiftkit.policies.trainers.vpace.args import VPACEArgs

    given = options().values(args)
    if hasattr(args, "handcrafted"):
        given["handcrafted"] = list(args.handcrafted)
    return VPACEArgs.for_variant(args.variant, **given)


def run(args: argparse.Namespace) -> int:
    """Trains VPACE / LfGP from the parsed options; returns the exit code."""
    from shiftkit.policies.trainers.vpace.training import train

    config = build_args(args)
    metrics = train(config)
    shown = ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in metrics.items())
    print(f"trained {config.variant} ({config.main_task}) in {config.output_dir}" + (f": {shown}" if shown else ""))
    return 0
