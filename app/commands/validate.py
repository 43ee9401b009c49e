"""`shiftkit validate DATASET`: read everything and check it; non-zero exit with the reason.
`--quality` adds the verdict on the content (`datasets/quality.py`)."""

from __future__ import annotations

import argparse

HELP = "check a dataset end to end; exits non-zero naming the first problem (--quality: a verdict on its content)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `validate`."""
    from shiftkit.datasets.option_values import positive_int

    parser.add_argument("dataset", help="dataset directory or dataset ID")
    parser.add_argument("--revision", help="hub revision when the ID is pulled")
    parser.add_argument(
        "--deep",
        action="store_true",
        help="also recompute every numeric feature's statistics and compare with stats.json",
    )
    parser.add_argument(
        "--quality",
        action="store_true",
        help="also give a verdict on the content (ok / warn / fail): constant dims, NaN/inf, timestamp gaps, "
        "short, still, jerky and duplicated episodes, depth range, flags, segments",
    )
    parser.add_argument(
        "--chunk-size",
        type=positive_int,
        metavar="N",
        help="--quality: the action chunk episodes should cover (default 16, lerobot's diffusion horizon; ACT: 100)",
    )
    parser.add_argument(
        "--strict", action="store_true", help="implies --quality; exit 1 unless the verdict is ok (for CI)"
    )
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object")


def run(args: argparse.Namespace) -> int:
    """Validate the dataset (recompute its statistics with `--deep`, judge its content with
    `--quality`) and print the result; return the exit code."""
    import json

    from shiftkit import datasets
    from shiftkit.datasets.check import validate_dataset
    from shiftkit.datasets.errors import DatasetError
    from shiftkit.datasets.quality import CHUNK_SIZE, quality_verdict, verdict_lines

    dataset = datasets.open(args.dataset, revision=args.revision)
    judge = args.quality or args.strict or args.chunk_size is not None
    try:
        counts = validate_dataset(dataset)
    except DatasetError as exc:
        if not judge:
            raise
        # A content problem the form check refuses (a timestamp gap, NaN statistics) is what the
        # verdict is for: give it, then the form error (exit 2).
        counts, error = None, exc
    else:
        error = None
    if args.deep and counts is not None:
        from shiftkit.datasets.check import recompute_stats

        counts["stats"] = recompute_stats(dataset)
    verdict = quality_verdict(dataset.root, args.chunk_size or CHUNK_SIZE) if judge else None
    if args.json:
        failed = {"error": str(error)} if error else {}
        print(json.dumps({"dataset": str(dataset.root), **(counts or failed), "quality": verdict}))
    elif counts is not None:
        for warning in counts["warnings"]:
            print(f"warning: {warning}")
        deep = (
            f", statistics of {counts['stats']} features recomputed"
            if args.deep
            else "; statistics not recomputed from the data (--deep does)"
        )
        print(f"ok: {dataset.root} ({counts['episodes']} episodes, {counts['frames']} frames{deep})")
    if verdict is not None and not args.json:
        for line in verdict_lines(verdict, limit=None):
            print(line)
    if error is not None:
        raise error
    return 1 if args.strict and verdict["verdict"] != "ok" else 0
