"""`shiftkit import FORMAT INPUT... --repo-id ID --root DIR`: third-party data -> LeRobot dataset.

The formats are the importer modules under `shiftkit.pipelines.sources` and `shiftkit.app.importers`
(see `importers()`).
"""

from __future__ import annotations

import argparse

HELP = "import third-party data as a LeRobot dataset (`shiftkit import FORMAT --help` per format)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """One subcommand per registered importer, each with the importer's own options."""
    from shiftkit.app import importers as app_importers
    from shiftkit.pipelines.sources import importers

    sub = parser.add_subparsers(dest="format", metavar="FORMAT", required=True)
    for name, importer in importers(app_importers).items():
        p = sub.add_parser(name, help=importer.help, description=importer.help)
        importer.add_arguments(p)
        p.add_argument("--repo-id", required=True, help="dataset ID of the new dataset, e.g. me/vpace_lift")
        p.add_argument("--root", required=True, help="directory of the new dataset (must not exist)")
        # the format's positional arguments are its inputs (files or folders it reads)
        p.set_defaults(_importer=importer, _inputs=[a.dest for a in p._actions if not a.option_strings])


def run(args: argparse.Namespace) -> int:
    """Run the chosen importer and print what it wrote and the quality verdict on it; return the exit code."""
    from shiftkit.pipelines.provenance import recorded_verdict_lines
    from shiftkit.pipelines.staging import check_inputs_and_outputs

    importer = args._importer
    inputs = [(dest, value) for dest in args._inputs for value in _values(getattr(args, dest))]
    check_inputs_and_outputs(inputs, [("--root", args.root)])
    summary = importer.run(args)
    for line in importer.report(summary):
        print(line)
    print(
        f"wrote {summary.episodes} episodes, {summary.frames} frames at {summary.fps} fps ({summary.kind}) to {summary.root}"
    )
    for line in recorded_verdict_lines(summary.root):
        print(line)
    return 0


def _values(value: object) -> list[str]:
    return [str(v) for v in value] if isinstance(value, list | tuple) else [] if value is None else [str(value)]
