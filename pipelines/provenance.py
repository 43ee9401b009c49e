"""Machine-readable provenance of a dataset: enough to audit and re-run the pipeline that made it.

Stored as `meta/shiftkit_provenance.json` and rendered into the dataset card. No wall-clock time
is recorded, so the same pipeline and seed give the same bytes.
"""

from __future__ import annotations

from dataclasses import asdict
from importlib import metadata
from typing import Any

PROVENANCE_VERSION = 1


def versions() -> dict[str, str]:
    out = {}
    for dist in ("shiftkit", "lerobot"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "unknown"
    return out


def build_provenance(plan: Any, executor: dict[str, Any], num_episodes: int, num_frames: int) -> dict[str, Any]:
    return {
        "provenance_version": PROVENANCE_VERSION,
        "tool": "shiftkit",
        "versions": versions(),
        "sources": [s.describe() for s in plan.sources],
        "stages": [s.describe() for s in plan.stages],
        "seed": plan.config.seed,
        "executor": executor,
        "output": {"repo_id": plan.repo_id, "fps": plan.fps, "episodes": num_episodes, "frames": num_frames},
        # The pipeline config itself: `shiftkit run` accepts this object saved as a .json file.
        "pipeline": asdict(plan.config),
    }
