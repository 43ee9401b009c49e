"""`shiftkit import FORMAT FILE... --repo-id ID --root DIR`: third-party data -> LeRobot dataset."""

from __future__ import annotations

import argparse

HELP = "import third-party data as a LeRobot dataset (vpace: the VPACE/LfGP authors' expert buffers)"
FORMATS = ("vpace",)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("format", choices=FORMATS, help="input format")
    parser.add_argument("files", nargs="+", metavar="FILE", help="input files (all go into one dataset)")
    parser.add_argument("--repo-id", required=True, help="dataset ID of the new dataset, e.g. me/vpace_lift")
    parser.add_argument("--root", required=True, help="directory of the new dataset (must not exist)")
    parser.add_argument("--kind", default="auto", choices=("auto", "examples", "trajectories"),
                        help="vpace: success-example sets or expert trajectories (default: detected)")
    parser.add_argument("--task", help="vpace: task name for every file (default: from the file name, 3_lift -> lift)")
    parser.add_argument("--fps", type=int, help="vpace: frame rate (default: 20 for 60-column files, 5 for 54)")


def run(args: argparse.Namespace) -> int:
    from shiftkit.pipelines.import_vpace import import_vpace

    summary = import_vpace(args.files, args.repo_id, args.root, kind=args.kind, task=args.task, fps=args.fps)
    for f in summary.per_file:
        detail = f"{f['rows']} examples" if summary.kind == "examples" else (
            f"{f['rows']} transitions in {f['episodes']} episodes (lengths {f['lengths']})")
        print(f"{f['file']}: task {f['task']!r}, {detail}")
    print(f"wrote {summary.episodes} episodes, {summary.frames} frames at {summary.fps} fps ({summary.kind}) to {summary.root}")
    return 0
