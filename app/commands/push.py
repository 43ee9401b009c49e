"""`shiftkit push`: upload a LeRobot dataset (or a policy checkpoint) to a Hugging Face-compatible hub."""

from __future__ import annotations

import argparse

HELP = "Push a LeRobot dataset (or, with --checkpoint, a policy checkpoint) to the hub at HF_ENDPOINT."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `push`."""
    parser.add_argument(
        "source",
        metavar="DATASET",
        help="dataset root folder or local dataset ID (under $HF_LEROBOT_HOME); a checkpoint folder with --checkpoint",
    )
    parser.add_argument("--repo-id", required=True, metavar="ORG/NAME", help="hub repository to push to")
    parser.add_argument("--private", action="store_true", help="create the repository as private")
    parser.add_argument(
        "--revision",
        metavar="BRANCH",
        default=None,
        help="branch to push to, created from main when missing (default: main)",
    )
    parser.add_argument(
        "--checkpoint", action="store_true", help="push a policy checkpoint folder to a model repository"
    )


def run(args: argparse.Namespace) -> int:
    """Push the dataset (or checkpoint with `--checkpoint`) and print the commit; return the exit code."""
    from shiftkit.datasets import hub

    push = hub.push_checkpoint if args.checkpoint else hub.push_dataset
    result = push(args.source, args.repo_id, revision=args.revision, private=args.private)
    tag = f", tagged {result.tag}" if result.tag else ""
    print(
        f"pushed {result.repo_type} {result.repo_id}@{result.branch} (commit {result.commit[:12]}{tag}): {result.url}"
    )
    return 0
