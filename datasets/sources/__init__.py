"""Where a pipeline's episodes come from, behind one small interface (`Source`).

A `[[sources]]` entry (`SourceConfig`) names a raw-episode folder (`raw.py`), a LeRobot dataset by
path or dataset ID (the `Dataset` handle, `shiftkit.datasets.open`) or a third-party format by its
importer (`format` and `options`, `shiftkit.datasets.importers`): an import is a pipeline whose
source is the importer, with or without stages. `open_source` picks the reader. A source knows its
features, fps and episode groups and streams episodes; nothing is loaded whole.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import ConfigError
from shiftkit.datasets.features import Features


class Source(Protocol):
    """A pipeline input: its schema and episodes, streamed by group (the episodes of one file)."""

    features: Features
    fps: int
    robot_type: str | None
    num_episodes: int

    def episode_groups(self) -> list[list[int]]:
        """Episode indices in groups read together (one file's episodes)."""

    def iter_episodes(self, indices: list[int]) -> Iterator[Episode]:
        """The episodes at `indices`, in that order, each with `meta["source_episode_index"]`."""

    def describe(self) -> dict[str, Any]:
        """The source fields of the provenance (kind, path, episodes, ...)."""


@dataclass
class SourceConfig:
    """One pipeline input: a local path, a dataset ID, or a third-party format read by its importer
    (`open_source` opens it)."""

    path: str | None = None
    """A raw-episode directory or a LeRobot dataset directory (relative to the config file)."""
    repo_id: str | None = None
    """A LeRobot dataset ID: looked up in $HF_LEROBOT_HOME first, then on the hub."""
    revision: str | None = None
    """Hub revision (branch, tag or commit) when `repo_id` is pulled."""
    format: str | None = None
    """A third-party format (`shiftkit import --help` lists them): its importer reads the inputs and
    settings given in `options`."""
    options: dict[str, Any] = field(default_factory=dict)
    """The importer's options (`shiftkit import FORMAT --help`: its inputs and settings, by field name;
    relative input paths are relative to the config file)."""

    def __post_init__(self) -> None:
        if self.format is not None:
            if self.path is not None or self.repo_id is not None:
                raise ValueError(f"a {self.format!r} source takes its inputs in 'options', not 'path' or 'repo_id'")
        elif (self.path is None) == (self.repo_id is None):
            raise ValueError("give exactly one of 'path' and 'repo_id'")
        elif self.options:
            raise ValueError("'options' are an importer's: give them with its 'format'")


def open_source(config: SourceConfig, base_dir: Path | None = None) -> Source:
    """The reader for a pipeline's `[[sources]]` entry (paths relative to `base_dir`)."""
    from shiftkit.datasets.dataset import open
    from shiftkit.datasets.sources.raw import RawSource, is_raw_dataset

    if config.format is not None:
        from shiftkit.datasets.importers import open_import

        return open_import(config.format, config.options, base_dir)
    if config.path is not None:
        path = Path(config.path)
        if not path.is_absolute() and base_dir is not None:
            path = base_dir / path
        if is_raw_dataset(path):
            return RawSource(path)
        if not path.exists():
            raise ConfigError(f"source path not found: {path}")
        return open(path.name, root=path)
    return open(config.repo_id, revision=config.revision)


def groups_by_file(files: list[int]) -> list[list[int]]:
    """Episode indices grouped by the file each episode is read from (`files[i]`: episode i's), in
    order: a source's `episode_groups` when one file holds several episodes."""
    groups: dict[int, list[int]] = {}
    for i, file in enumerate(files):
        groups.setdefault(file, []).append(i)
    return list(groups.values())


def input_paths(config: SourceConfig, source: Any) -> list[Path]:
    """The local files and folders a source reads (its folder, a resolved dataset ID's, an importer's
    inputs): what `staging.check_inputs_and_outputs` holds apart from the destination."""
    if config.format is not None:
        return list(source.inputs)
    root = getattr(source, "root", None) or config.path
    return [Path(root)] if root is not None else []
