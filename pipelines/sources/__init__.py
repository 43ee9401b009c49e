"""Where episodes come from, in one place and behind one small interface.

* Pipeline inputs (`Source`): raw-episode directories (`raw`) and LeRobot datasets, local or by
  dataset ID (`lerobot`); `open_source` picks the reader. A source streams episodes grouped by the
  file they live in.
* Recorders and importers that make a LeRobot or raw dataset from outside one: episodes from a
  simulator and its scripted expert (`simulator`, `shiftkit collect`) and third-party formats
  (`vpace`, ...). An importer module defines `IMPORTER = Importer(...)`; `shiftkit import FORMAT`
  finds every module here that does, so a new format is one module (plus its test file). They
  write through one path, `write_imported`.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any, Protocol

from shiftkit.pipelines.config import SourceConfig
from shiftkit.pipelines.episode import Episode
from shiftkit.pipelines.errors import ConfigError
from shiftkit.pipelines.features import Features

# `SourceConfig` (a `[[sources]]` entry) lives with the config file's schema; `open_source` reads it.
__all__ = [
    "ImportSummary",
    "Importer",
    "Source",
    "SourceConfig",
    "importers",
    "open_source",
    "write_imported",
]


class Source(Protocol):
    """A pipeline input: its schema and episodes, streamed by group (the episodes of one file)."""

    features: Features
    fps: int
    robot_type: str | None
    num_episodes: int

    def episode_groups(self) -> list[list[int]]:
        """Episode indices in groups read together (one file's episodes)."""

    def iter_episodes(self, indices: list[int]) -> Iterator[Episode]:
        """The episodes at `indices`, in that order."""

    def describe(self) -> dict[str, Any]:
        """The source fields of the provenance (kind, path, episodes, ...)."""


def open_source(config: SourceConfig, base_dir: Path | None = None) -> Source:
    """The reader for a pipeline's `[[sources]]` entry (paths relative to `base_dir`)."""
    from shiftkit.pipelines.lerobot_io import resolve_dataset
    from shiftkit.pipelines.sources.lerobot import LeRobotSource
    from shiftkit.pipelines.sources.raw import RawSource, is_raw_dataset

    if config.path is not None:
        path = Path(config.path)
        if not path.is_absolute() and base_dir is not None:
            path = base_dir / path
        if is_raw_dataset(path):
            return RawSource(path)
        resolved = resolve_dataset(str(path), root=path) if path.exists() else None
        if resolved is None:
            raise ConfigError(f"source path not found: {path}")
        return LeRobotSource(resolved.root, path.name, None, resolved.fingerprint)
    resolved = resolve_dataset(config.repo_id, revision=config.revision)
    return LeRobotSource(resolved.root, config.repo_id, config.revision, resolved.fingerprint)


@dataclass
class ImportSummary:
    """What an importer wrote."""

    root: Path
    kind: str
    fps: int
    episodes: int
    frames: int
    per_file: list[dict[str, Any]] = field(default_factory=list)
    """Per source file: what it held and how it was split (importer-specific keys)."""


@dataclass(frozen=True)
class Importer:
    """A third-party format that `shiftkit import FORMAT ... --repo-id ID --root DIR` imports."""

    name: str
    """FORMAT on the command line."""
    help: str
    """One line for `shiftkit import --help`."""
    add_arguments: Callable[[argparse.ArgumentParser], None]
    """Adds the format's inputs and options (`--repo-id` and `--root` are common)."""
    run: Callable[[argparse.Namespace], ImportSummary]
    """Imports from the parsed arguments; raises `ShiftkitError` subclasses for bad input."""
    report: Callable[[ImportSummary], list[str]] = lambda summary: []
    """Lines printed before the closing summary line (per-file details)."""


def importers(*packages: ModuleType) -> dict[str, Importer]:
    """Every importer module under `shiftkit.pipelines.sources` and the given `packages` (importers
    above the core, e.g. `shiftkit.app.importers`), by format name."""
    found: dict[str, Importer] = {}
    for package in (sys.modules[__name__], *packages):
        for module in pkgutil.iter_modules(package.__path__):
            importer = getattr(importlib.import_module(f"{package.__name__}.{module.name}"), "IMPORTER", None)
            if isinstance(importer, Importer):
                found[importer.name] = importer
    return found


def write_imported(
    repo_id: str,
    root: str | Path,
    fps: int,
    features: Features,
    episodes: Iterable[Episode],
    *,
    robot_type: str | None,
    sources: list[dict[str, Any]],
    importer: dict[str, Any],
    seed: int | None = None,
) -> tuple[int, int]:
    """The one path from imported episodes to a LeRobot dataset at `root`: repo id checked before
    anything is read, written atomically, provenance naming the inputs (with fingerprints) and the
    importer's settings. Returns (episodes, frames)."""
    from shiftkit.pipelines.hub import validate_repo_id
    from shiftkit.pipelines.lerobot_io import DatasetWriter
    from shiftkit.pipelines.provenance import make_provenance

    validate_repo_id(repo_id)
    with DatasetWriter(repo_id, root, fps, features, robot_type=robot_type) as writer:
        for episode in episodes:
            writer.add_episode(episode)
        writer.close(
            provenance=make_provenance(
                repo_id=repo_id,
                fps=fps,
                num_episodes=writer.num_episodes,
                num_frames=writer.num_frames,
                sources=sources,
                seed=seed,
                importer=importer,
            )
        )
    return writer.num_episodes, writer.num_frames
