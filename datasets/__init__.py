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

if __name__ == "datasets":
    # This folder was found as the top-level `datasets`: Python runs in the clone's root with the root
    # first on sys.path (`python -m`, `python -c`, pytest's rootdir). That name is the installed Hugging
    # Face `datasets` (lerobot imports it): load that one in this module's place (the import system hands
    # out what sys.modules holds once this module has run).
    import importlib.machinery
    import importlib.util
    import sys

    _root = Path(__file__).resolve().parents[1]
    _spec = importlib.machinery.PathFinder.find_spec(
        "datasets", [p for p in sys.path if Path(p or ".").resolve() != _root]
    )
    if _spec is None or _spec.loader is None:
        raise ImportError(f"{Path(__file__).parent} is shiftkit.datasets; the Hugging Face `datasets` is not installed")
    _installed = importlib.util.module_from_spec(_spec)
    sys.modules["datasets"] = _installed
    _spec.loader.exec_module(_installed)


def __getattr__(name: str) -> Any:
    if name in ("open", "Dataset"):
        from shiftkit.datasets import dataset

        return getattr(dataset, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["Dataset", "open"]
