"""`shiftkit validate DATASET`: read everything and check it; non-zero exit with the reason."""

from __future__ import annotations

import argparse

HELP = "check a dataset end to end; exits non-zero naming the first problem"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", help="dataset directory or dataset ID")
    parser.add_argument("--revision", help="hub revision when the ID is pulled")


def run(args: argparse.Namespace) -> int:
    from shiftkit.pipelines.dataset_check import validate_dataset
    from shiftkit.pipelines.lerobot_io import resolve_dataset

    resolved = resolve_dataset(args.dataset, revision=args.revision)
    counts = validate_dataset(resolved.root)
    for warning in counts["warnings"]:
        print(f"warning: {warning}")
    print(f"ok: {resolved.root} ({counts['episodes']} episodes, {counts['frames']} frames)")
    return 0
