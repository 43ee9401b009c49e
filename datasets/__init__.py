"""shiftkit.datasets: the dataset layer, below the pipeline engine and the trainers.

One handle to a dataset by path or ID (`open(ref)` -> `Dataset`: ID, folder, fingerprint, features,
provenance, streamed episodes), one write path (`writer.DatasetWriter`: LeRobot v3.0 through
lerobot's own format code, provenance always), the episode sources a pipeline reads (`sources/`: raw
episodes, LeRobot datasets, and the importers' formats, `importers/`), statistics, video, depth,
camera metadata, the hub, staging, and the typed loaders of every file shiftkit reads back. It also
holds the engine-independent config helpers (`errors`, `dataclass_config`, `option_values`) every
layer above it uses (docs/architecture.md says why here). It knows no stage, engine, trainer or env.

Importing this package is cheap: `open` and `Dataset` load their module on first use.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

if __name__ == "datasets":  # this folder found as the top-level `datasets`: the clone's root is on sys.path first
    raise ImportError(
        f"{Path(__file__).parent} (shiftkit.datasets) shadows the installed Hugging Face `datasets` because "
        f"{Path(__file__).parents[1]} comes first on sys.path: run Python from another folder or with `python -P`"
    )


def __getattr__(name: str) -> Any:
    if name in ("open", "Dataset"):
        from shiftkit.datasets import dataset

        return getattr(dataset, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["Dataset", "open"]
