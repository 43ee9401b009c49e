"""`shiftkit pull`: download a LeRobot dataset (or a policy checkpoint) from a Hugging Face-compatible hub."""

from __future__ import annotations

import argparse

HELP = "Pull a LeRobot dataset (or, with --checkpoint, a policy checkpoint) from the hub at HF_ENDPOINT."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `pull`."""
    parser.add_argument("repo_id", metavar="ORG/NAME", help="hub repository to pull")
    parser.add_argument(
        "--revision",
        metavar="REV",
        default=None,
        help="version tag, branch or commit (default: the codebase version lerobot reads, v3.0; main for checkpoints)",
    )
    parser.add_argument(
        "--root",
        metavar="DIR",
        default=None,
        help="folder to write to (default: $HF_LEROBOT_HOME/ORG/NAME, "
        "$HF_LEROBOT_HOME/checkpoints/ORG/NAME for checkpoints)",
    )
    parser.add_argument("--force", action="store_true", help="replace an existing folder at the destination")
    parser.add_argument("--checkpoint", action="store_true", help="pull a policy checkpoint (model repository)")


def run(args: argparse.Namespace) -> int:
    """Pull the dataset (or checkpoint with `--checkpoint`) and print where it went; return the exit code."""
    from shiftkit.datasets import hub

    if args.checkpoint:
        from shiftkit.policies.run_dir import check_checkpoint_files

        root = hub.pull_checkpoint(
            args.repo_id, args.revision, args.root, force=args.force, check=check_checkpoint_files
        )
    else:
        root = hub.pull_dataset(args.repo_id, args.revision, args.root, force=args.force)
    print(f"pulled {args.repo_id} into {root}")
    return 0
