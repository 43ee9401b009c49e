"""`shiftkit demo`: the end-to-end demo pipeline on embedded defaults."""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "record demo episodes, re-render them from new base poses (multiview), validate the LeRobot dataset"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `demo`."""
    parser.add_argument("--out", default="outputs/demo", help="output directory (default outputs/demo)")
    parser.add_argument("--episodes", type=int, default=4, help="episodes to record (default 4)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--overwrite", action="store_true", help="replace an earlier demo output")


def run(args: argparse.Namespace) -> int:
    """Run the demo and print the dataset's summary and where its files are; return the exit code."""
    from shiftkit.app.demo import run_demo
    from shiftkit.pipelines.dataset_check import format_summary

    result = run_demo(Path(args.out), args.episodes, args.seed, args.overwrite)
    print(format_summary(result["summary"]))
    print(f"\nvalid LeRobot dataset: {result['dataset']} ({result['episodes']} episodes, {result['frames']} frames)")
    print(f"pipeline config: {result['config']} (try `shiftkit plan {result['config']}`)")
    print(f"recorded vs re-rendered views: {result['figure']}")
    return 0
