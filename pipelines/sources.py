"""Pipeline inputs: raw-episode directories and LeRobot datasets (local root or dataset ID),
behind one small interface that streams episodes grouped by the file they live in."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from shiftkit.pipelines.episode import Episode
from shiftkit.pipelines.errors import ConfigError
from shiftkit.pipelines.features import Features
from shiftkit.pipelines.lerobot_io import open_lerobot_dataset, resolve_dataset
from shiftkit.pipelines.raw_format import is_raw_dataset, open_raw_dataset


@dataclass
class SourceConfig:
    path: str | None = None
    """A raw-episode directory or a LeRobot dataset directory (relative to the config file)."""
    repo_id: str | None = None
    """A LeRobot dataset ID: looked up in $HF_LEROBOT_HOME first, then on the hub."""
    revision: str | None = None
    """Hub revision (branch, tag or commit) when `repo_id` is pulled."""

    def __post_init__(self) -> None:
        if (self.path is None) == (self.repo_id is None):
            raise ValueError("give exactly one of 'path' and 'repo_id'")


class Source(Protocol):
    features: Features
    fps: int
    robot_type: str | None
    num_episodes: int

    def episode_groups(self) -> list[list[int]]: ...
    def iter_episodes(self, indices: list[int]) -> Iterator[Episode]: ...
    def describe(self) -> dict[str, Any]: ...


class RawSource:
    def __init__(self, root: Path) -> None:
        self._raw = open_raw_dataset(root)
        self.root = root
        self.features = self._raw.features()
        self.fps = self._raw.fps
        self.robot_type = self._raw.index.get("robot") or None
        self.num_episodes = self._raw.num_episodes

    def episode_groups(self) -> list[list[int]]:
        return [[i] for i in range(self.num_episodes)]  # one directory per episode

    def iter_episodes(self, indices: list[int]) -> Iterator[Episode]:
        return self._raw.iter_episodes(indices)

    def describe(self) -> dict[str, Any]:
        return {"kind": "raw", "path": str(self.root), "num_episodes": self.num_episodes,
                "env": self._raw.index.get("env", ""), "format_version": self._raw.index.get("version")}


class LeRobotSource:
    def __init__(self, root: Path, repo_id: str, revision: str | None, fp: str) -> None:
        self._reader = open_lerobot_dataset(root)
        self.root, self.repo_id, self.revision, self.fingerprint = root, repo_id, revision, fp
        self.features = self._reader.features
        self.fps = self._reader.fps
        self.robot_type = self._reader.robot_type
        self.num_episodes = self._reader.num_episodes

    def episode_groups(self) -> list[list[int]]:
        return self._reader.episode_groups()

    def iter_episodes(self, indices: list[int]) -> Iterator[Episode]:
        return self._reader.iter_episodes(indices)

    def describe(self) -> dict[str, Any]:
        return {"kind": "lerobot", "repo_id": self.repo_id, "path": str(self.root), "revision": self.revision,
                "fingerprint": self.fingerprint, "num_episodes": self.num_episodes}


def open_source(config: SourceConfig, base_dir: Path | None = None) -> Source:
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
