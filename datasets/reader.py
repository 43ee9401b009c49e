"""The reader of LeRobot v3.0 datasets: streams a local dataset one episode at a time (one data file
open at a time, only the row groups an episode lives in), with frames decoded by `images.py`, the
episode meta from the episodes table and camera metadata from `meta/cameras.json`. One-line errors
for broken metadata or data files. `shiftkit.datasets.open` gives the dataset handle around it.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from shiftkit.datasets import camera_meta, loaders
from shiftkit.datasets.arrow_columns import column_to_numpy
from shiftkit.datasets.encoded_frames import EncodedFrames
from shiftkit.datasets.episode import META_COLUMN, Episode
from shiftkit.datasets.errors import DatasetError
from shiftkit.datasets.features import Features, object_column, user_features
from shiftkit.datasets.images import decode_image, decode_video, image_form
from shiftkit.datasets.video_copy import VideoRef, copy_signature, cuttable

_EPISODES_PER_READ = 64  # a reader holds at most this many episodes' rows of one data file


@dataclass
class LeRobotDatasetReader:
    """Streams a local LeRobot v3.0 dataset one episode at a time (one data file open at a time)."""

    root: Path
    info: dict[str, Any]
    episodes: Any  # pandas DataFrame of meta/episodes without stats columns
    tasks: list[str]
    cameras: dict[str, Any] = field(default_factory=dict)  # meta/cameras.json (camera_meta)

    def __post_init__(self) -> None:
        # Global index of each data file's first frame, to map episodes to the file's row groups.
        starts = self.episodes.groupby(["chunk", "file"])["dataset_from_index"].min()
        self._file_starts = {(int(c), int(f)): int(v) for (c, f), v in starts.items()}
        self._features = user_features(self.info["features"])  # `features` hands out copies
        self._rows = self.episodes.to_dict("records")  # a pandas row lookup costs ~1 ms
        self._footers: dict[tuple[int, int], Any] = {}  # parsed parquet metadata per data file
        self._stats: dict[str, list[dict[str, np.ndarray] | None]] = {}  # recorded statistics per feature

    @property
    def fps(self) -> int:
        """Frames per second."""
        return int(self.info["fps"])

    @property
    def features(self) -> Features:
        """The features without the writer-derived columns (timestamp, frame_index, episode_index, ...)."""
        return user_features(self.info["features"])

    @property
    def num_episodes(self) -> int:
        """Number of episodes."""
        return len(self.episodes)

    @property
    def robot_type(self) -> str | None:
        """The `robot_type` in info.json, if any."""
        return self.info.get("robot_type")

    def episode_groups(self) -> list[list[int]]:
        """Episode indices grouped by data file, so a worker opens each file once."""
        groups: dict[tuple[int, int], list[int]] = {}
        for i, row in enumerate(self.episodes.itertuples(index=False)):
            groups.setdefault((row.chunk, row.file), []).append(i)
        return list(groups.values())

    def iter_episodes(
        self, indices: list[int] | None = None, video_refs: frozenset[str] = frozenset()
    ) -> Iterator[Episode]:
        """The episodes at `indices`, in that order. Consecutive episodes of one data file (a work
        unit's) share one read of just the row groups that hold them. The video features in
        `video_refs` are not decoded: they come as `VideoRef`s (`video_copy.py`)."""
        indices = list(range(self.num_episodes)) if indices is None else list(indices)
        k = 0
        while k < len(indices):
            run = [(indices[k], self._row(indices[k]))]
            key = self._file_of(run[0][1])
            while k + len(run) < len(indices) and len(run) < _EPISODES_PER_READ:
                i = indices[k + len(run)]
                if self._file_of(row := self._row(i)) != key:
                    break
                run.append((i, row))
            table, table_start = self._read_rows(
                key,
                min(int(row["dataset_from_index"]) for _, row in run),
                max(int(row["dataset_to_index"]) for _, row in run),
            )
            for i, row in run:
                start, stop = int(row["dataset_from_index"]), int(row["dataset_to_index"])
                yield self._episode_from_table(i, table.slice(start - table_start, stop - start), row, video_refs)
            k += len(run)

    def _row(self, i: int) -> Any:
        if not 0 <= i < self.num_episodes:
            raise DatasetError(f"{self.root}: no episode {i} (dataset has {self.num_episodes})")
        return self._rows[i]

    @staticmethod
    def _file_of(row: Any) -> tuple[int, int]:
        return int(row["chunk"]), int(row["file"])

    def _read_rows(self, key: tuple[int, int], lo: int, hi: int) -> tuple[Any, int]:
        """The row groups of data file `key` that hold global frames [lo, hi), and the global index
        of their first row."""
        import pyarrow.parquet as pq

        path = self.root / self.info["data_path"].format(chunk_index=key[0], file_index=key[1])
        try:
            with pq.ParquetFile(path, metadata=self._footers.get(key)) as data:
                self._footers[key] = data.metadata
                groups, first, row = [], lo, int(self._file_starts[key])
                for g in range(data.metadata.num_row_groups):
                    n = data.metadata.row_group(g).num_rows
                    if row < hi and row + n > lo:
                        first = row if not groups else first
                        groups.append(g)
                    row += n
                return data.read_row_groups(groups), first
        except FileNotFoundError:
            raise DatasetError(f"{path}: data file is missing") from None
        except Exception as exc:  # pyarrow raises several types for corrupt files
            raise DatasetError(f"{path}: unreadable parquet file ({type(exc).__name__}: {exc})") from None

    def _episode_from_table(self, i: int, part: Any, row: Any, video_refs: frozenset[str] = frozenset()) -> Episode:
        where = f"{self.root} episode {i}"
        n = part.num_rows
        if n != int(row["length"]) or n == 0:
            raise DatasetError(f"{where}: {n} rows in the data file, metadata says {int(row['length'])}")
        ep_idx = part.column("episode_index").to_numpy()
        if not (ep_idx == int(row["episode_index"])).all():
            raise DatasetError(f"{where}: data rows belong to another episode (corrupt index)")
        frames: dict[str, np.ndarray] = {"timestamp": part.column("timestamp").to_numpy().astype(np.float64)}
        for key, ft in self._features.items():
            if ft["dtype"] == "video" and key in video_refs:
                frames[key] = self._video_ref(key, row, frames["timestamp"])
                continue
            if ft["dtype"] == "video":
                frames[key] = self._decode_video(key, row, frames["timestamp"])
                continue
            col = part.column(key)
            if ft["dtype"] == "image":
                encoded = [v["bytes"] for v in col.to_pylist()]  # kept: unchanged frames are not re-encoded
                frames[key] = EncodedFrames.wrap(
                    np.stack([decode_image(b, where, ft) for b in encoded]), encoded, image_form(ft)
                )
            elif ft["dtype"] == "language":
                frames[key] = object_column(col.to_pylist())  # a list of messages per frame
            elif ft["dtype"] == "string":
                frames[key] = np.array(col.to_pylist(), dtype=str).reshape(n, 1)
            else:
                arr = column_to_numpy(col, np.dtype(ft["dtype"]))
                frames[key] = arr.reshape((n, *ft["shape"]))
        task_idx = part.column("task_index").to_numpy()
        frames["task"] = np.array([self.tasks[t] for t in task_idx], dtype=str)
        meta = json.loads(row[META_COLUMN]) if META_COLUMN in row and isinstance(row[META_COLUMN], str) else {}
        meta["source_episode_index"] = i
        if cameras := camera_meta.episode_cameras(self.cameras, i):
            meta["cameras"] = cameras
        return Episode(frames, meta)

    def _video_file(self, key: str, row: Any) -> Path:
        chunk, file = int(row[f"videos/{key}/chunk_index"]), int(row[f"videos/{key}/file_index"])
        return self.root / self.info["video_path"].format(video_key=key, chunk_index=chunk, file_index=file)

    def _decode_video(self, key: str, row: Any, timestamps: np.ndarray) -> np.ndarray:
        offset = float(row[f"videos/{key}/from_timestamp"])
        where = f"{self.root} episode {int(row['episode_index'])} {key}"
        return decode_video(self._video_file(key, row), offset, timestamps, where, self._features[key])

    def video_copy_signature(self, key: str) -> tuple | None:
        """The stream signature of video feature `key` if its episodes can be copied packet for packet
        (`video_copy.copy_signature`), else None."""
        files: dict[Path, list[float]] = {}
        for row in self._rows:
            files.setdefault(self._video_file(key, row), []).append(float(row[f"videos/{key}/from_timestamp"]))
        return copy_signature(files)

    def video_cuttable(self, key: str) -> bool:
        """Whether episodes of video feature `key` can be cut between keyframes (`video_copy.cuttable`)."""
        return cuttable(list(dict.fromkeys(self._video_file(key, row) for row in self._rows)))

    def _video_ref(self, key: str, row: Any, timestamps: np.ndarray) -> VideoRef:
        i = int(row["episode_index"])
        return VideoRef(
            self._video_file(key, row),
            float(row[f"videos/{key}/from_timestamp"]),
            float(row[f"videos/{key}/to_timestamp"]),
            timestamps,
            self._features[key],
            self._recorded_stats(key)[i],
        )

    def _recorded_stats(self, key: str) -> list[dict[str, np.ndarray] | None]:
        """Per episode, the statistics of feature `key` recorded in meta/episodes (lerobot's
        `stats/KEY/...` columns; None where an episode has none), read once."""
        if key not in self._stats:
            self._stats[key] = self._read_stats(key)
        return self._stats[key]

    def _read_stats(self, key: str) -> list[dict[str, np.ndarray] | None]:
        import pyarrow.parquet as pq

        prefix = f"stats/{key}/"
        by_episode: dict[int, dict[str, np.ndarray]] = {}
        for path in sorted((self.root / "meta" / "episodes").glob("*/*.parquet")):
            names = [c for c in pq.read_schema(path).names if c.startswith(prefix)]
            table = pq.read_table(path, columns=["episode_index", *names]).to_pydict()
            for k, e in enumerate(table["episode_index"]):
                by_episode[int(e)] = {c[len(prefix) :]: np.array(table[c][k]) for c in names}
        return [by_episode.get(e) or None for e in range(self.num_episodes)]


def require_utf8_path(path: Path, what: str, verb: str) -> None:
    """pyarrow (LeRobot's parquet files) opens UTF-8 paths only: a one-line error naming the path
    rather than a parquet error about a file that is fine."""
    try:
        str(path).encode("utf-8")
    except UnicodeEncodeError:
        shown = str(path).encode("utf-8", "backslashreplace").decode()
        raise DatasetError(
            f"{what} {shown} is not a UTF-8 path; LeRobot datasets can only be {verb} UTF-8 paths"
        ) from None


def open_lerobot_dataset(root: str | Path) -> LeRobotDatasetReader:
    """Open a local LeRobot v3.0 dataset for streaming; one-line errors for broken metadata."""
    import pyarrow.parquet as pq

    root = Path(root)
    if root.is_dir():
        require_utf8_path(root.resolve(), "dataset", "read from")
    info_path = root / "meta" / "info.json"
    if not root.is_dir():
        raise DatasetError(f"dataset not found: {root}")
    if not info_path.is_file():
        raise DatasetError(f"{info_path} is missing (not a LeRobot dataset)")
    info = loaders.load_checked(info_path, loaders.obj(codebase_version=loaders.opt(loaders.ANY)), "info")
    version = str(info.get("codebase_version", ""))
    if version != "v3.0":
        hint = " (convert v2.1 with lerobot's convert_dataset_v21_to_v30)" if version.startswith("v2") else ""
        raise DatasetError(f"{root}: codebase_version {version!r} is not v3.0{hint}")
    info = loaders.check_value(info, loaders.INFO, str(info_path))
    if "data_path" not in info:
        raise DatasetError(f"{info_path}: 'data_path' is missing")
    ep_files = sorted((root / "meta" / "episodes").glob("*/*.parquet"))
    if not ep_files:
        raise DatasetError(f"{root}/meta/episodes: no episode metadata files")
    import pandas as pd

    frames = []
    for path in ep_files:
        try:
            schema = pq.read_schema(path)
            cols = [c for c in schema.names if not c.startswith("stats/")]
            frames.append(pq.read_table(path, columns=cols).to_pandas())
        except Exception as exc:
            raise DatasetError(f"{path}: unreadable parquet file ({type(exc).__name__})") from None
    episodes = pd.concat(frames, ignore_index=True).sort_values("episode_index").reset_index(drop=True)
    episodes = episodes.rename(columns={"data/chunk_index": "chunk", "data/file_index": "file"})
    if not (episodes["episode_index"].to_numpy() == np.arange(len(episodes))).all():
        raise DatasetError(f"{root}: episode indices in meta/episodes are not 0..{len(episodes) - 1}")
    try:
        tasks_df = pd.read_parquet(root / "meta" / "tasks.parquet")
    except Exception as exc:
        raise DatasetError(f"{root}/meta/tasks.parquet: unreadable ({type(exc).__name__})") from None
    tasks = [""] * len(tasks_df)
    for task, idx in zip(tasks_df.index, tasks_df["task_index"], strict=True):
        tasks[int(idx)] = str(task)
    cameras = camera_meta.read_cameras_file(root)
    if not cameras["cameras"] and not cameras["episodes"]:
        cameras["cameras"] = camera_meta.cameras_from_feature_info(info["features"])
    return LeRobotDatasetReader(root, info, episodes, tasks, cameras)
