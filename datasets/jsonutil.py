"""Deterministic JSON for the files shiftkit writes (metadata, provenance, raw-episode indexes)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np


def json_default(obj: Any) -> Any:
    """`json.dumps(default=...)` for numpy scalars/arrays and paths."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON-serialisable: {type(obj).__name__}")


def dumps(obj: Any, indent: int | None = None) -> str:
    """Sorted keys, so equal content gives equal bytes."""
    return json.dumps(obj, indent=indent, sort_keys=True, default=json_default)


def read_json_file(path: Path, missing: str) -> Any:
    """Parse a metadata file; a missing or malformed file is a one-line DatasetError. The value is
    unchecked: a file with a known layout is read through its loader in `datasets/loaders.py`."""
    from shiftkit.datasets.loaders import load_json

    return load_json(path, missing)
