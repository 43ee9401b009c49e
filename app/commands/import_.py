"""`shiftkit import FORMAT INPUT... --repo-id ID --root DIR`: third-party data -> LeRobot dataset
(`app/importing.py`: a pipeline whose source is the importer).

The formats are the registered importers (`shiftkit.datasets.importers.IMPORTERS`: the dataset
layer's and the application's, `shiftkit.app.importers`); each subcommand's options are generated
from the importer's `Options` dataclass, its first input positional.
"""

from __future__ import annotations

import argparse

HELP = "import third-party data as a LeRobot dataset (`shiftkit import FORMAT --help` per format)"


def _options(importer):  # noqa: ANN001, ANN202 - an Importer; its DataclassOptions
    from shiftkit.datasets.option_values import DataclassOptions

    return DataclassOptions(importer.Options, positional=importer.inputs[:1])


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """One subcommand per registered importer, each with the importer's own options."""
    from shiftkit.datasets.importers import IMPORTERS

    sub = parser.add_subparsers(dest="format", metavar="FORMAT", required=True)
    for name, importer in IMPORTERS.items():
        p = sub.add_parser(name, help=importer.help, description=importer.help)
        _options(importer).add_to(p)
        p.add_argument("--repo-id", required=True, help="dataset ID of the new dataset, e.g. me/vpace_lift")
        p.add_argument("--root", required=True, help="directory of the new dataset (must not exist)")
        p.set_defaults(_importer=importer)


def run(args: argparse.Namespace) -> int:
    """Run the chosen importer (`importing.import_dataset`) and print what it read, what it wrote and
    the quality verdict on it; return the exit code."""
    from dataclasses import asdict

    from shiftkit.app.importing import import_dataset
    from shiftkit.datasets.provenance import recorded_verdict_lines

    importer = args._importer
    options = asdict(_options(importer).build(args))
    dataset = import_dataset(importer.name, options, args.repo_id, args.root)
    for line in importer.report(dataset.provenance["sources"][0]):
        print(line)
    output = dataset.provenance["output"]
    print(f"wrote {output['episodes']} episodes, {output['frames']} frames at {output['fps']} fps to {dataset.root}")
    for line in recorded_verdict_lines(dataset.provenance):
        print(line)
    return 0
