"""LeRobot datasets (a local root or a dataset ID resolved locally, then on the hub) as a pipeline source."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

from shiftkit.pipelines.episode import Episode
from shiftkit.pipelines.lerobot_io import open_lerobot_dataset


class LeRobotSource:
    """A LeRobot dataset as a pipeline source."""

    def __init__(self, root: Path, repo_id: str, revision: str | None, fp: str) -> None:
        self._reader = open_lerobot_dataset(root)
        self.root, self.repo_id, self.revision, self.fingerprint = root, repo_id, revision, fp
        self.features = self._reader.features
        self.fps = self._reader.fps
        self.robot_type = self._reader.robot_type
        self.num_episodes = self._reader.num_episodes

    def episode_groups(self) -> list[list[int]]:
        """Episode indices grouped by data file."""
        return self._reader.episode_groups()

    def iter_episodes(self, indices: list[int]) -> Iterator[Episode]:
        """The episodes at `indices`, read in that order."""
        return self._reader.iter_episodes(indices)

    def describe(self) -> dict[str, Any]:
        """The source fields of the provenance (repo id, path, revision, fingerprint, episodes)."""
        return {
            "kind": "lerobot",
            "repo_id": self.repo_id,
            "path": str(self.root),
            "revision": self.revision,
            "fingerprint": self.fingerprint,
            "num_episodes": self.num_episodes,
        }
