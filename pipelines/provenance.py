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


def make_provenance(
    *,
    repo_id: str,
    fps: int,
    num_episodes: int,
    num_frames: int,
    sources: list[dict[str, Any]],
    stages: list[dict[str, Any]] | None = None,
    seed: int | None = None,
    **extra: Any,
) -> dict[str, Any]:
    """The provenance record every shiftkit dataset carries (pipelines, importers, FIRE): tool and
    versions, the sources with their fingerprints, the stages with their parameters, the seed and
    what was written; `extra` adds the producer's own entries (`executor`, `pipeline`,
    `importer`, `fire`)."""
    return {
        "provenance_version": PROVENANCE_VERSION,
        "tool": "shiftkit",
        "versions": versions(),
        "sources": sources,
        "stages": stages or [],
        "seed": seed,
        **extra,
        "output": {"repo_id": repo_id, "fps": fps, "episodes": num_episodes, "frames": num_frames},
    }


def build_provenance(
    plan: Any, executor: dict[str, Any], num_episodes: int, num_frames: int, report: list[dict[str, int]]
) -> dict[str, Any]:
    """A pipeline run's provenance. `report`: per stage, the run's totals of the events it counted
    (`Stage.report`), stored as the stage entry's "report" when it counted any."""
    return make_provenance(
        repo_id=plan.repo_id,
        fps=plan.fps,
        num_episodes=num_episodes,
        num_frames=num_frames,
        sources=[s.describe() for s in plan.sources],
        stages=[
            {**s.describe(), "report": counts} if counts else s.describe()
            for s, counts in zip(plan.stages, report, strict=True)
        ],
        seed=plan.config.seed,
        executor=executor,
        # The pipeline config itself: `shiftkit run` accepts this object saved as a .json file.
        pipeline=asdict(plan.config),
    )


def format_report(counts: dict[str, int]) -> str:
    """A stage's event counts on one line: `views_dropped_ik 3, views_kept 12`."""
    return ", ".join(f"{event} {n}" for event, n in counts.items())


def report_lines(provenance: dict[str, Any]) -> list[str]:
    """The run summary's counts: one line per stage that counted events."""
    return [
        f"stage {k} {stage['name']}: {format_report(stage['report'])}"
        for k, stage in enumerate(provenance.get("stages", []), start=1)
        if stage.get("report")
    ]
