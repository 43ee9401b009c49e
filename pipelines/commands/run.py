"""`shiftkit run FILE`: run a pipeline (resumable, atomic)."""

from __future__ import annotations

import argparse
import dataclasses

HELP = "run a pipeline config; re-running after an interruption resumes it"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("config", help="pipeline config (.toml, .yaml or .json)")
    parser.add_argument("--workers", type=int, default=1, help="worker processes (default 1)")
    parser.add_argument("--executor", default="local", help="executor: local (default)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--push", metavar="ORG/NAME", help="push the result to the hub under this dataset ID")
    parser.add_argument("--push-revision", metavar="BRANCH", help="hub branch for --push (default main)")
    parser.add_argument("--private", action="store_true", help="create the hub repository as private")


def run(args: argparse.Namespace) -> int:
    from shiftkit.pipelines.config import load_pipeline_config
    from shiftkit.pipelines.runner import run_pipeline

    config = load_pipeline_config(args.config)
    if args.push:
        from shiftkit.pipelines.hub import validate_repo_id

        validate_repo_id(args.push)  # fail before any work, not after it
        config.destination = dataclasses.replace(
            config.destination, repo_id=args.push, push=True, revision=args.push_revision,
            private=args.private or config.destination.private,
        )
    path = run_pipeline(config, workers=args.workers, executor=args.executor, progress=not args.no_progress)
    print(f"wrote {path}")
    return 0
