"""`shiftkit plan FILE`: validate a pipeline and print the output schema without running it."""

from __future__ import annotations

import argparse

HELP = "validate a pipeline config and print its output schema (runs nothing)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `plan`."""
    parser.add_argument("config", nargs="?", help="pipeline config (.toml, .yaml or .json)")
    parser.add_argument("--stages", action="store_true", help="list the registered stages and their parameters")


def run(args: argparse.Namespace) -> int:
    """Print the plan of a pipeline config (or the registered stages with `--stages`); return the exit code."""
    from shiftkit.datasets.errors import ConfigError
    from shiftkit.pipelines.config import load_pipeline_config
    from shiftkit.pipelines.planner import format_plan, plan_pipeline

    if args.stages:
        from shiftkit.pipelines.stage import describe_stages

        print(describe_stages())
        return 0
    if args.config is None:
        raise ConfigError("give a pipeline config file (or --stages)")
    print(format_plan(plan_pipeline(load_pipeline_config(args.config))))
    return 0
