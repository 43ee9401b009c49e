"""`shiftkit demo`: the end-to-end demo pipeline on embedded defaults."""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

from shiftkit.datasets.dataclass_config import option
from shiftkit.datasets.option_values import DataclassOptions

HELP = "record demo episodes, re-render them from new base poses (multiview), validate the LeRobot dataset"


@dataclass(frozen=True)
class DemoArgs:
    """Where `shiftkit demo` writes and how many episodes it records."""

    out: str = "outputs/demo"
    """Output directory."""
    episodes: int = option(4, rule="positive_int")
    """Episodes to record."""
    seed: int = option(0, rule="non_negative_int")
    """Episode i is recorded with seed `seed + i`."""
    overwrite: bool = False
    """Replace an earlier demo output."""


OPTIONS = DataclassOptions(DemoArgs, metavars={"out": "DIR"})


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `demo`."""
    OPTIONS.add_to(parser)


def run(args: argparse.Namespace) -> int:
    """Run the demo and print the dataset's summary and where its files are; return the exit code."""
    from shiftkit.app.demo import run_demo
    from shiftkit.datasets.check import format_summary

    config = OPTIONS.build(args)
    result = run_demo(Path(config.out), config.episodes, config.seed, config.overwrite)
    print(format_summary(result["summary"]))
    print(f"\nvalid LeRobot dataset: {result['dataset']} ({result['episodes']} episodes, {result['frames']} frames)")
    print(f"pipeline config: {result['config']} (try `shiftkit plan {result['config']}`)")
    print(f"recorded vs re-rendered views: {result['figure']}")
    return 0
