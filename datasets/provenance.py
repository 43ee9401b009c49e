"""Machine-readable provenance of a dataset: enough to audit and re-run the pipeline that made it.

Stored as `meta/shiftkit_provenance.json` and rendered into the dataset card. No wall-clock time
is recorded, so the same pipeline and seed give the same bytes.
"""

from __future__ import annotations

import functools
import hashlib
import subprocess
from importlib import metadata
from pathlib import Path
from typing import Any

from shiftkit.datasets.jsonutil import dumps

PROVENANCE_VERSION = 1
PROVENANCE_PATH = "meta/shiftkit_provenance.json"


def versions(packages: tuple[str, ...] = ("shiftkit", "lerobot")) -> dict[str, Any]:
    """Installed versions of `packages` ("unknown" when not installed) and, when shiftkit runs from a
    git checkout, the commit it runs (`shiftkit_commit`) and whether the checkout had changes
    (`shiftkit_dirty`): the package version alone does not say which code made an output."""
    out: dict[str, Any] = {}
    for dist in packages:
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "unknown"
    return {**out, **source_revision()}


# What makes a checkout's code differ from its commit: Python files, the packaging and the package data
# (not the datasets, runs and configs a user keeps in a clone).
CODE_PATHS = ("*.py", "pyproject.toml", "cards/templates/*", "envs/*/assets/*")


@functools.cache
def source_revision() -> dict[str, Any]:
    """`{"shiftkit_commit": SHA, "shiftkit_dirty": bool}` of the checkout this code is imported from,
    or {} for an installed (non-editable) copy or without git; a dirty checkout adds
    `shiftkit_changes`, a hash of its changes to the code (the diff from the commit and the new
    files): two dirty checkouts of one commit run different code, so a run's work folder made by one
    is not resumed by the other (`pipelines.work.run_key`)."""
    root = Path(__file__).resolve().parents[1]
    if not ((root / ".git").exists() and (root / "pyproject.toml").exists()):
        return {}
    try:
        git = lambda *args: subprocess.run(  # noqa: E731
            ["git", "-C", str(root), *args], capture_output=True, text=True, check=True, timeout=30
        ).stdout.strip()
        out: dict[str, Any] = {
            "shiftkit_commit": git("rev-parse", "HEAD"),
            "shiftkit_dirty": bool(git("status", "--porcelain", "--", *CODE_PATHS)),
        }
        if out["shiftkit_dirty"]:
            changes = hashlib.sha256(git("diff", "HEAD", "--", *CODE_PATHS).encode())
            for name in sorted(git("ls-files", "--others", "--exclude-standard", "--", *CODE_PATHS).splitlines()):
                changes.update(name.encode() + b"\0" + (root / name).read_bytes())
            out["shiftkit_changes"] = changes.hexdigest()[:16]
        return out
    except (OSError, subprocess.SubprocessError):
        return {}


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


def format_report(counts: dict[str, int]) -> str:
    """A stage's event counts on one line: `views_dropped_ik 3, views_kept 12`."""
    return ", ".join(f"{event} {n}" for event, n in counts.items())


def report_lines(provenance: dict[str, Any]) -> list[str]:
    """The run summary's counts: one line per stage that counted events (a source's own stages
    first, named by their source)."""
    own = [
        f"sources[{s}] stage {k} {stage['name']}: {format_report(stage['report'])}"
        for s, source in enumerate(provenance.get("sources", []))
        for k, stage in enumerate(source.get("stages", []), start=1)
        if stage.get("report")
    ]
    return own + [
        f"stage {k} {stage['name']}: {format_report(stage['report'])}"
        for k, stage in enumerate(provenance.get("stages", []), start=1)
        if stage.get("report")
    ]


def recorded_envs(root: Any) -> set[str]:
    """The envs a LeRobot dataset's episodes were recorded in, as its provenance names them (its
    raw and simulator sources); empty when it has no provenance or the provenance does not say."""
    from pathlib import Path

    from shiftkit.datasets.loaders import load_provenance

    path = Path(root) / PROVENANCE_PATH
    provenance = load_provenance(path) if path.is_file() else {}
    return {s["env"] for s in provenance.get("sources", []) if s.get("env")}


def recorded_verdict_lines(provenance: dict[str, Any]) -> list[str]:
    """The quality verdict a dataset's provenance records (the writer's, on what it wrote;
    `quality.py`), as the lines `run`, `merge` and `import` print after writing; none when there is
    no provenance."""
    from shiftkit.datasets.quality import verdict_lines

    verdict = provenance.get("quality")
    return verdict_lines(verdict) if verdict else []


def write_provenance(root: Path, provenance: dict[str, Any]) -> None:
    """The machine-readable provenance, with the quality verdict on what was written
    (`quality.py`), and the dataset card rendered from it (after info/stats)."""
    from shiftkit.cards import render_dataset_card
    from shiftkit.datasets.quality import quality_verdict

    provenance = {**provenance, "quality": quality_verdict(root)}
    (root / PROVENANCE_PATH).write_text(dumps(provenance, indent=2))
    # errors=: a source path that is not UTF-8 is shown escaped rather than failing the write.
    (root / "README.md").write_text(render_dataset_card(root, provenance), errors="backslashreplace")
