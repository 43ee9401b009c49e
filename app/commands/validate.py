"""`shiftkit validate DATASET`: read everything and check it; non-zero exit with the reason."""

from __future__ import annotations

import argparse

HELP = "check a dataset end to end; exits non-zero naming the first problem"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `validate`."""
    parser.add_argument("dataset", help="dataset directory or dataset ID")
    parser.add_argument("--revision", help="hub revision when the ID is pulled")
    parser.add_argument(
        "--deep",
        action="store_true",
        help="also recompute every numeric feature's statistics and compare with stats.json",
    )


def run(args: argparse.Namespace) -> int:
    """Validate the dataset (and recompute its statistics with `--deep`) and print the counts; return the exit code."""
    from shiftkit.pipelines.dataset_check import validate_dataset
    from shiftkit.pipelines.lerobot_io import resolve_dataset

    resolved = resolve_dataset(args.dataset, revision=args.revision)
    counts = validate_dataset(resolved.root)
    if args.deep:
        from shiftkit.pipelines.dataset_check import recompute_stats

        counts["stats"] = recompute_stats(resolved.root)
    for warning in counts["warnings"]:
        print(f"warning: {warning}")
    deep = (
        f", statistics of {counts['stats']} features recomputed"
        if args.deep
        else "; statistics not recomputed from the data (--deep does)"
    )
    print(f"ok: {resolved.root} ({counts['episodes']} episodes, {counts['frames']} frames{deep})")
    return 0
