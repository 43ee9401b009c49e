"""`shiftkit train NAME`: train a policy from dataset IDs into a run folder.

The subcommands are the registered trainers (`policies/trainers/`): each brings its options
(generated from its args dataclass) and its run; `train --help` lists them without importing any.
"""

from __future__ import annotations

import argparse

HELP = "train a policy (bc, vpace, lfgp, ...) from LeRobot dataset IDs"


def add_arguments(parser: argparse.ArgumentParser, argv: list[str] | None = None) -> None:
    """One subcommand per trainer; only the one chosen in `argv` (the words after `train`; None:
    all) gets its options, so the others are not imported."""
    from shiftkit.policies.trainers import TRAINERS

    sub = parser.add_subparsers(dest="trainer", metavar="TRAINER", required=True)
    chosen = None if argv is None else next((a for a in argv if not a.startswith("-")), "")
    for name, trainer in TRAINERS.items():
        p = sub.add_parser(name, help=trainer.help, description=trainer.help)
        if chosen is None or chosen == name:
            cli = trainer.cli_module()
            cli.add_arguments(p, trainer)
            p.set_defaults(_train_run=cli.run)


def run(args: argparse.Namespace) -> int:
    """Train with the chosen trainer, holding its run folder against a second run; return the exit code."""
    from pathlib import Path

    from shiftkit.app.env_kwargs import check_env_kwargs
    from shiftkit.datasets.staging import DestinationLock

    if isinstance(getattr(args, "env", None), str) and isinstance(getattr(args, "env_kwargs", None), dict):
        check_env_kwargs(args.env, args.env_kwargs)  # a trainer that runs an env (VPACE, LfGP)
    with DestinationLock(Path(args.output_dir)):  # a second run on the same --output is told who holds it
        return args._train_run(args)
