"""`shiftkit import` as a function: third-party data into a new LeRobot dataset.

An import is an ordinary pipeline whose source is the format's importer (`[[sources]] format = ...`)
and which has no stages, run by the engine and written by the one writer with its provenance (the
provenance's `pipeline` re-runs it with `shiftkit run`); a format lerobot converts itself is
converted into the writer's staging folder and finished like every dataset.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Any

from shiftkit import datasets


def import_dataset(
    format: str, options: dict[str, Any], repo_id: str, root: str | Path, progress: bool = False
) -> datasets.Dataset:
    """Import with the importer of `format` (`options`: its `Options` as plain values, input paths
    relative to the working directory) into a new dataset `repo_id` at `root`; returns the dataset."""
    from shiftkit.datasets.importers import IMPORTERS, convert_import

    importer = IMPORTERS.get(format)
    # input paths made absolute, so that the provenance's pipeline re-runs from anywhere
    checked = importer.options(options, f"import {format}", base_dir=Path.cwd())
    if importer.convert is not None:
        written = convert_import(importer, checked, repo_id, root)
    else:
        from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, PipelineSource
        from shiftkit.pipelines.runner import run_pipeline

        source = PipelineSource(format=format, options=asdict(checked))
        destination = DestinationConfig(root=str(Path(root).resolve()), repo_id=repo_id)
        written = run_pipeline(PipelineConfig(sources=[source], destination=destination), progress=progress)
    return datasets.open(repo_id, root=written)
