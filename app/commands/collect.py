"""`shiftkit collect`: record scripted-expert episodes (raw format or LeRobot).

The options are generated from `CollectConfig` (`option_values.DataclassOptions`): help, defaults and
types come from the dataclass; `--kinesthetic` and `--progress` are the command's own.
"""

from __future__ import annotations

import argparse

from shiftkit.datasets.option_values import DataclassOptions

HELP = "record scripted-expert episodes from a simulated env (raw episodes or a LeRobot dataset)"


def _options() -> DataclassOptions:
    from shiftkit.app.collect import CollectConfig

    return DataclassOptions(
        CollectConfig,
        flags={"env_kwargs": "env-kwarg"},
        metavars={"lerobot": "REPO_ID", "out": "DIR", "root": "DIR"},
        required=("task",),
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `collect`."""
    _options().add_to(parser)
    parser.add_argument("--kinesthetic", action="store_true", help="shorthand for --expert kinesthetic")
    parser.add_argument(
        "--progress", action=argparse.BooleanOptionalAction, default=True, help="show a progress bar (default: on)"
    )


def run(args: argparse.Namespace) -> int:
    """Record the episodes and print where they went; return the exit code."""
    from shiftkit.app.collect import collect
    from shiftkit.app.env_kwargs import check_env_kwargs

    config = _options().build(args, **({"expert": "kinesthetic"} if args.kinesthetic else {}))
    check_env_kwargs(config.env, config.env_kwargs)
    path, counts = collect(config, progress=args.progress)
    print(f"wrote {counts['episodes']} episodes ({counts['successes']} successful) to {path}")
    return 0
