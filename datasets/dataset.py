"""The one handle on a LeRobot v3.0 dataset: `open(ref)` -> `Dataset` (`shiftkit.datasets.open`).

A dataset is named by a local path or a dataset ID (`$HF_LEROBOT_HOME/<id>`, then the hub). The
handle carries what every user of a dataset asks first (its ID, folder, revision and content
fingerprint), parses `meta/info.json` and the provenance once, on first use, and streams episodes
through one reader (`reader.py`). It is what a pipeline reads as a LeRobot source, what the trainers
and `eval` open, and what `info` and `validate` describe; code above the dataset layer does not read
a dataset's files itself.
"""

from __future__ import annotations

import functools
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from shiftkit.datasets import loaders
from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import DatasetError
from shiftkit.datasets.features import Features
from shiftkit.datasets.ids import find_local_dataset, fingerprint, lerobot_home, not_a_dataset
from shiftkit.datasets.provenance import PROVENANCE_PATH

if TYPE_CHECKING:
    from shiftkit.datasets.reader import LeRobotDatasetReader


class Dataset:
    """A local LeRobot v3.0 dataset, by the ID it was opened as (see the module docstring)."""

    def __init__(self, repo_id: str, root: Path, revision: str | None = None) -> None:
        self.repo_id = repo_id
        """The dataset ID (for a dataset opened by path: the folder's name)."""
        self.root = Path(root)
        """The dataset's folder."""
        self.revision = revision
        """The hub revision it was pulled at, if any."""
        self.fingerprint = fingerprint(self.root)
        """Content fingerprint of its metadata (`ids.fingerprint`), fixed when opened."""

    def __repr__(self) -> str:
        return f"Dataset({self.repo_id!r}, root={str(self.root)!r})"

    @functools.cached_property
    def info(self) -> dict[str, Any]:
        """`meta/info.json`, checked (`loaders.load_info`), read once."""
        return loaders.load_info(self.root / "meta" / "info.json")

    @functools.cached_property
    def provenance(self) -> dict[str, Any]:
        """shiftkit's provenance of the dataset (`meta/shiftkit_provenance.json`, checked), read once;
        {} for a dataset shiftkit did not write."""
        path = self.root / PROVENANCE_PATH
        return loaders.load_provenance(path) if path.is_file() else {}

    @functools.cached_property
    def reader(self) -> LeRobotDatasetReader:
        """The episode reader (opened once: info, episodes table, tasks, camera metadata)."""
        from shiftkit.datasets.reader import open_lerobot_dataset

        return open_lerobot_dataset(self.root)

    @property
    def features(self) -> Features:
        """The features without the writer-derived columns (timestamp, frame_index, ...)."""
        return self.reader.features

    @property
    def fps(self) -> int:
        """Frames per second."""
        return self.reader.fps

    @property
    def robot_type(self) -> str | None:
        """The `robot_type` of info.json, if any."""
        return self.reader.robot_type

    @property
    def num_episodes(self) -> int:
        """Number of episodes."""
        return self.reader.num_episodes

    def episode_groups(self) -> list[list[int]]:
        """Episode indices grouped by data file (read together)."""
        return self.reader.episode_groups()

    def iter_episodes(
        self, indices: list[int] | None = None, video_refs: frozenset[str] = frozenset()
    ) -> Iterator[Episode]:
        """The episodes at `indices` (default: all), streamed in that order; the video features in
        `video_refs` not decoded (`video_copy.VideoRef`)."""
        return self.reader.iter_episodes(indices, video_refs)

    def video_copy_signature(self, key: str) -> tuple | None:
        """What must match for video feature `key`'s packets to be copied into one stream with
        another's; None when they cannot be copied (`video_copy.copy_signature`)."""
        return self.reader.video_copy_signature(key)

    def video_cuttable(self, key: str) -> bool:
        """Whether video feature `key`'s episodes can be cut between keyframes (`video_copy.cuttable`)."""
        return self.reader.video_cuttable(key)

    def describe(self) -> dict[str, Any]:
        """The dataset as a pipeline's provenance records its source (ID, path, revision, fingerprint,
        episodes)."""
        return {
            "kind": "lerobot",
            "repo_id": self.repo_id,
            "path": str(self.root),
            "revision": self.revision,
            "fingerprint": self.fingerprint,
            "num_episodes": self.num_episodes,
        }

    @functools.cached_property
    def lerobot(self) -> Any:
        """lerobot's `LeRobotDataset` over the same folder (its Arrow table and metadata, for the
        trainers' batches), opened once: depth in metres, as shiftkit's trainers take it, and the video
        backend chosen by `video.decoder_backend` (lerobot logs a long traceback where torchcodec fails)."""
        from lerobot.datasets.lerobot_dataset import LeRobotDataset

        from shiftkit.datasets.video import decoder_backend

        try:
            return LeRobotDataset(self.repo_id, root=self.root, depth_output_unit="m", video_backend=decoder_backend())
        except Exception as exc:  # lerobot raises many types for a bad folder
            raise DatasetError(f"cannot open LeRobot dataset {self.repo_id!r} at {self.root}: {exc}") from exc


def open(ref: str | Path, root: str | Path | None = None, revision: str | None = None) -> Dataset:
    """The dataset `ref` names: `root` (its folder) if given, else `ref` itself
    if it is a dataset folder, else `$HF_LEROBOT_HOME/<ref>`, else the hub (`HF_ENDPOINT`), pulled into
    the cache at `revision`. A one-line `DatasetError` says why anything else is no dataset."""
    ref = str(ref)
    if root is not None:
        if not (Path(root) / "meta" / "info.json").is_file():
            raise DatasetError(not_a_dataset(Path(root)))
        return Dataset(ref, Path(root), revision)
    path = find_local_dataset(ref)
    if path is not None:
        return Dataset(Path(ref).name if Path(ref).exists() else ref, path, revision)
    if Path(ref).exists() or ref.startswith((".", "/")) or ref.count("/") != 1:
        raise DatasetError(not_a_dataset(Path(ref)))
    from shiftkit.datasets import hub

    return Dataset(ref, hub.pull_dataset(ref, revision=revision, root=lerobot_home() / ref), revision)


def as_dataset(dataset: Dataset | str | Path) -> Dataset:
    """`dataset` itself, or the dataset folder it names opened as a handle (by the folder's name)."""
    return dataset if isinstance(dataset, Dataset) else open(Path(dataset).name, root=dataset)
