"""`shiftkit view DATASET [--episode N] [--save FILE.rrd]`: the dataset in the Rerun viewer
(`app/dataset_view.py`); the Rerun SDK is the optional `viz` extra."""

from __future__ import annotations

import argparse

HELP = "look at a dataset in the Rerun viewer: cameras, depth, every numeric column, flags, segments, views"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `view`."""
    from shiftkit.datasets.option_values import option_type

    parser.add_argument("dataset", help="dataset directory or dataset ID")
    parser.add_argument("--revision", help="hub revision when the ID is pulled")
    parser.add_argument(
        "--episode",
        type=option_type("non_negative_int"),
        metavar="N",
        help="only episode N (with the views re-rendered from the same source episode); default: all",
    )
    parser.add_argument(
        "--save", metavar="FILE.rrd", help="write a Rerun recording file instead of spawning the viewer"
    )
    parser.add_argument(
        "--progress", action=argparse.BooleanOptionalAction, default=True, help="show a progress bar (default: on)"
    )


def run(args: argparse.Namespace) -> int:
    """Send the dataset to the viewer (or the file) and print what was sent; return the exit code."""
    from shiftkit import datasets
    from shiftkit.app.dataset_view import entity_summary, import_rerun, view_dataset

    import_rerun()  # the missing extra is said before any dataset is read
    dataset = datasets.open(args.dataset, revision=args.revision)
    summary = view_dataset(dataset, episode=args.episode, save=args.save, progress=args.progress)
    for line in entity_summary(summary):
        print(line)
    print(f"wrote {args.save} (open it with `rerun {args.save}`)" if args.save else "sent to the Rerun viewer")
    return 0
