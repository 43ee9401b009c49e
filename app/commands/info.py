"""`shiftkit info DATASET`: features, episodes, tasks, stats summary and provenance."""

from __future__ import annotations

import argparse
import json

HELP = "describe a dataset (path or dataset ID): features, episodes, tasks, stats, provenance"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `info`."""
    parser.add_argument("dataset", help="dataset directory or dataset ID")
    parser.add_argument("--revision", help="hub revision when the ID is pulled")
    parser.add_argument("--json", action="store_true", help="print machine-readable JSON")


def run(args: argparse.Namespace) -> int:
    """Print the dataset's summary (as JSON with `--json`); return the exit code."""
    from shiftkit import datasets
    from shiftkit.datasets.check import format_summary, summarize

    summary = summarize(datasets.open(args.dataset, revision=args.revision))
    print(json.dumps(summary, indent=2) if args.json else format_summary(summary))
    return 0
