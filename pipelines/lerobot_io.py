"""LeRobot v3.0 IO: an atomic, fast episode writer on lerobot's own format code, a streaming
per-episode reader, and dataset-ID resolution.

The writer creates the dataset with `LeRobotDataset.create` and stores each episode through
lerobot's own pieces (lerobot's HF features and their Arrow schema, lerobot's episode statistics,
`LeRobotDatasetMetadata.save_episode`), so the files are what lerobot writes. It skips the costs of
the high-level path that do not apply to whole episodes held in memory: the per-frame `add_frame`
loop, `embed_images`, a `datasets.map` over every row that re-reads PNG files from disk (here
images are encoded straight into the row, with the same PNG bytes and file name lerobot would
embed), and per-value Python conversion (numeric columns go to Arrow from their numpy buffers).
Statistics come from `shiftkit.pipelines.stats` (lerobot's values, vectorised), computed by the
worker that produced the episode. Camera features are written as `image` (PNG in parquet, no codec) or,
declared `video`, through lerobot's own video encoder (`pipelines/video.py`).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from shiftkit.pipelines import camera_meta
from shiftkit.pipelines.encoded_frames import EncodedFrames, source_png
from shiftkit.pipelines.episode import Episode
from shiftkit.pipelines.errors import DatasetError
from shiftkit.pipelines.features import (
    CAMERA_DTYPES,
    Features,
    check_episode,
    check_features,
    plain_camera_features,
    user_features,
)
from shiftkit.pipelines.jsonutil import dumps, read_json_file
from shiftkit.pipelines.stats import RunningStats, image_stats, numeric_stats
from shiftkit.pipelines.video import decode_episode, save_episode_videos

_EPISODES_PER_READ = 64  # a reader holds at most this many episodes' rows of one data file
META_COLUMN = "shiftkit/meta"  # episode-level metadata (JSON) in meta/episodes/*.parquet
PROVENANCE_PATH = "meta/shiftkit_provenance.json"
_PNG_COMPRESS_LEVEL = 6  # what lerobot's add_frame uses for `image` features


def _png_bytes(frame: np.ndarray) -> bytes:
    import PIL.Image

    buf = io.BytesIO()
    PIL.Image.fromarray(frame).save(buf, format="PNG", compress_level=_PNG_COMPRESS_LEVEL)
    return buf.getvalue()


# Statistics that depend on where an episode lands in the dataset; all others are a function of
# the episode alone and can be computed in parallel workers (`episode_stats`).
POSITION_KEYS = ("episode_index", "index", "task_index")


def _episode_columns(episode: Episode, features: Features) -> dict[str, Any]:
    """Per-frame columns as lerobot's writer buffers them (scalar features flattened)."""
    n = len(episode)
    columns: dict[str, Any] = {}
    for key, ft in features.items():
        arr = episode.frames[key]
        columns[key] = arr.reshape(n) if tuple(ft["shape"]) == (1,) and ft["dtype"] != "image" else arr
    columns["timestamp"] = episode.frames["timestamp"].astype(
        np.float64
    )  # stored as float32; stats in float64 as lerobot
    columns["frame_index"] = np.arange(n, dtype=np.int64)
    return columns


def episode_stats(episode: Episode, features: Features) -> dict[str, dict[str, np.ndarray]]:
    """lerobot's per-episode statistics of every position-independent column of `episode`
    (`compute_episode_stats`' values, computed by `shiftkit.pipelines.stats`)."""
    columns = _episode_columns(episode, features)
    # Camera features, image or video: lerobot computes both from the frames before encoding
    # (EncodedFrames carry decoded pixels: statistics read a plain array).
    images = {k: np.asarray(columns.pop(k)) for k, ft in features.items() if ft["dtype"] in CAMERA_DTYPES}
    stats = numeric_stats({k: v for k, v in columns.items() if k not in features or features[k]["dtype"] != "string"})
    stats.update({k: image_stats(v) for k, v in images.items()})
    return stats


def encode_images(episode: Episode, features: Features) -> Episode:
    """`episode` with every `image` feature as `EncodedFrames` holding each frame's PNG bytes (a
    frame's source bytes where it is unchanged), so that the writer reuses them. Pipeline workers
    call this, so that PNG encoding, the largest cost of writing images, runs in parallel rather
    than in the one writer."""
    keys = [k for k, ft in features.items() if ft["dtype"] == "image"]
    return episode.with_frames(
        **{
            k: EncodedFrames.wrap(
                episode.frames[k], [source_png(f, episode.frames[k]) or _png_bytes(f) for f in episode.frames[k]]
            )
            for k in keys
        }
    )


class DatasetWriter:
    """Writes episodes into a new LeRobot v3.0 dataset at `root`, atomically.

    Everything goes to a temporary sibling directory; `close()` finalizes it, adds shiftkit's
    provenance and dataset card, and renames it to `root`. `abort()` (or an exception inside a
    `with` block) removes it, so a failed run leaves no dataset behind.
    """

    def __init__(
        self,
        repo_id: str,
        root: str | Path,
        fps: int,
        features: Features,
        robot_type: str | None = None,
    ) -> None:
        from lerobot.datasets.lerobot_dataset import LeRobotDataset
        from lerobot.datasets.utils import get_hf_features_from_features

        self.root = Path(root)
        if self.root.exists():
            raise DatasetError(f"destination already exists: {self.root}")
        self.features = plain_camera_features(user_features(features))
        check_features(self.features, where=f"schema of {self.root}")
        self.fps = int(fps)
        self.repo_id = repo_id
        self.tmp = self.root.parent / f".{self.root.name}.partial-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        video_keys = [k for k, ft in self.features.items() if ft["dtype"] == "video"]  # pipelines/video.py
        try:
            self.root.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise DatasetError(f"cannot create the destination's folder {self.root.parent}: {exc.strerror}") from None
        self._ds = LeRobotDataset.create(
            repo_id, self.fps, dict(self.features), root=self.tmp, robot_type=robot_type, use_videos=bool(video_keys)
        )
        self._meta = self._ds.meta
        self._stats = RunningStats()
        self._task_index: dict[str, int] = {}
        self._hf_features = get_hf_features_from_features(self._ds.features)
        self._arrow_schema = self._hf_features.arrow_schema  # with datasets' feature metadata
        self._image_keys = [k for k, ft in self.features.items() if ft["dtype"] == "image"]
        self._video_keys = video_keys
        self._writer = None  # pyarrow ParquetWriter of the current data file
        self._chunk_file = (0, 0)
        self._file_start = 0  # global index of the first frame in the current data file
        self.num_episodes = 0
        self.num_frames = 0
        self._cameras: dict[int, camera_meta.Cameras] = {}  # episode index -> its camera metadata
        self._closed = False

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def add_episode(self, episode: Episode, stats: dict[str, dict[str, np.ndarray]] | None = None) -> None:
        """Validate and append one episode (NaNs, shapes, dtypes and fps are checked).

        `stats` may hold the episode's position-independent statistics, computed earlier (in a
        worker) with `episode_stats`; the writer adds those that depend on the episode's position
        (index, episode_index, task_index).
        """
        import pyarrow.parquet as pq
        from lerobot.datasets.utils import flatten_dict, get_file_size_in_mb, update_chunk_file_indices

        where = f"episode {episode.meta.get('source_episode_index', self.num_episodes)}"
        check_episode(episode, self.features, self.fps, where)
        episode_meta = self._take_cameras(episode.meta, where)
        n = len(episode)
        tasks = [str(t) for t in episode.frames["task"]]
        episode_tasks = list(dict.fromkeys(tasks))  # first-appearance order: deterministic
        self._meta.save_episode_tasks(episode_tasks)
        for t in episode_tasks:  # lerobot's lookup is a pandas .loc (~1 ms); indices never change
            if t not in self._task_index:
                self._task_index[t] = self._meta.get_task_index(t)
        task_index = self._task_index

        start = self.num_frames
        columns = _episode_columns(episode, self.features)
        for key in self._image_keys:
            columns[key] = [
                {"bytes": source_png(f, columns[key]) or _png_bytes(f), "path": f"frame-{t:06d}.png"}
                for t, f in enumerate(columns[key])
            ]
        columns["episode_index"] = np.full(n, self.num_episodes, dtype=np.int64)
        columns["index"] = np.arange(start, start + n, dtype=np.int64)
        columns["task_index"] = np.array([task_index[t] for t in tasks], dtype=np.int64)

        if stats is None:
            stats = episode_stats(episode, self.features)
        stats = {**stats, **numeric_stats({k: columns[k] for k in POSITION_KEYS})}
        # Same key order as lerobot (feature order), which fixes the episodes-parquet columns.
        stats = {k: stats[k] for k in self._ds.features}

        table = self._arrow_table(columns)
        videos = save_episode_videos(self._ds, self.num_episodes, {k: episode.frames[k] for k in self._video_keys})

        # Same file rotation rule as lerobot's writer: start a new data file when this episode
        # would push the current one past data_files_size_in_mb.
        if self._writer is not None:
            path = self.tmp / self._meta.data_path.format(
                chunk_index=self._chunk_file[0], file_index=self._chunk_file[1]
            )
            size = get_file_size_in_mb(path)
            per_frame = size / (start - self._file_start) if start > self._file_start else 0.0
            if size + per_frame * n >= self._meta.data_files_size_in_mb:
                self._writer.close()
                self._writer = None
                self._chunk_file = update_chunk_file_indices(*self._chunk_file, self._meta.chunks_size)
                self._file_start = start
        if self._writer is None:
            path = self.tmp / self._meta.data_path.format(
                chunk_index=self._chunk_file[0], file_index=self._chunk_file[1]
            )
            path.parent.mkdir(parents=True, exist_ok=True)
            self._writer = pq.ParquetWriter(path, schema=table.schema, compression="snappy", use_dictionary=True)
        self._writer.write_table(table)

        # What LeRobotDatasetMetadata.save_episode does, minus rewriting info.json and
        # stats.json after every episode: the writer writes them once, in close().
        info = self._meta.info
        self._meta._save_episode_metadata(
            {
                "episode_index": self.num_episodes,
                "tasks": episode_tasks,
                "length": n,
                "data/chunk_index": self._chunk_file[0],
                "data/file_index": self._chunk_file[1],
                "dataset_from_index": start,
                "dataset_to_index": start + n,
                **videos,
                META_COLUMN: dumps(episode_meta),
                **flatten_dict({"stats": stats}),
            }
        )
        info["total_episodes"] += 1
        info["total_frames"] += n
        info["total_tasks"] = len(self._meta.tasks)
        info["splits"] = {"train": f"0:{info['total_episodes']}"}
        self._stats.add(stats)  # lerobot's aggregate_stats([stats, episode stats]), vectorised
        self.num_episodes += 1
        self.num_frames += n

    def _take_cameras(self, meta: dict[str, Any], where: str) -> dict[str, Any]:
        """Keep the episode's camera metadata for meta/cameras.json; the rest of `meta` is returned
        for the episodes table (the cameras live in their own file, not twice)."""
        if meta.get("cameras"):
            cameras = camera_meta.check_cameras(meta["cameras"], f"{where} meta")
            self._cameras[self.num_episodes] = json.loads(dumps(cameras))
        return {k: v for k, v in meta.items() if k != "cameras"}

    def _arrow_table(self, columns: dict[str, Any]) -> Any:
        """The episode as Arrow, encoded exactly as `datasets.Dataset.from_dict` does for lerobot,
        without the Dataset object, whose fingerprinting pickles every value (~50 ms/episode).
        Numeric columns go straight from their numpy arrays; the others (images, n-d arrays)
        through datasets' own per-value encoding."""
        import pyarrow as pa

        schema = self._arrow_schema
        arrays = {field.name: _numeric_arrow_array(columns[field.name], field.type) for field in schema}
        encoded = [key for key, array in arrays.items() if array is None]
        if encoded:
            from datasets.arrow_writer import OptimizedTypedSequence
            from datasets.table import InMemoryTable

            features = self._hf_features
            typed = {
                key: OptimizedTypedSequence(features.encode_column(columns[key], key), type=features[key], col=key)
                for key in encoded
            }
            table = InMemoryTable.from_pydict(mapping=typed).table.cast(pa.schema([schema.field(k) for k in encoded]))
            arrays.update({key: table.column(key) for key in encoded})
        return pa.Table.from_arrays([arrays[field.name] for field in schema], schema=schema)

    def close(self, provenance: dict[str, Any] | None = None) -> Path:
        """Finalize, write provenance and the dataset card rendered from it, and move the dataset
        into place."""
        if self._closed:
            return self.root
        if self.num_episodes == 0:
            self.abort()
            raise DatasetError(f"no episodes to write to {self.root} (every episode was filtered out)")
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        self._meta._close_writer()
        shutil.rmtree(self.tmp / "images", ignore_errors=True)  # the video encoder's input frames
        self._write_info_and_stats()
        cameras = camera_meta.provenance_entry(camera_meta.write_cameras_file(self.tmp, self._cameras))
        if provenance is not None:
            write_provenance(self.tmp, {**provenance, "cameras": cameras} if cameras else provenance)
        if self.root.exists():
            self.abort()
            raise DatasetError(f"destination already exists: {self.root}")
        os.rename(self.tmp, self.root)
        self._closed = True
        return self.root

    def _write_info_and_stats(self) -> None:
        """info.json and stats.json, once. lerobot aggregates stats over a `set` of keys, so their
        order would follow the process's string-hash seed: write them in feature order instead."""
        from lerobot.datasets.utils import write_info, write_stats

        write_info(self._meta.info, self.tmp)
        stats = self._meta.stats = self._stats.result()
        write_stats({k: stats[k] for k in self._ds.features if k in stats}, self.tmp)

    def abort(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        self._meta.metadata_buffer.clear()
        self._meta._close_writer()
        shutil.rmtree(self.tmp, ignore_errors=True)
        self._closed = True


def _numeric_arrow_array(values: Any, arrow_type: Any) -> Any:
    """`values` (a numpy column) as an Arrow array of a numeric or fixed-size-list-of-numeric type,
    built from its buffer; None for other types."""
    import pyarrow as pa

    def numeric(t: Any) -> bool:
        return pa.types.is_integer(t) or pa.types.is_floating(t) or pa.types.is_boolean(t)

    if not isinstance(values, np.ndarray):
        return None
    if numeric(arrow_type):
        return pa.array(values.reshape(-1).astype(arrow_type.to_pandas_dtype(), copy=False), type=arrow_type)
    if pa.types.is_fixed_size_list(arrow_type) and numeric(arrow_type.value_type):
        flat = values.reshape(-1).astype(arrow_type.value_type.to_pandas_dtype(), copy=False)
        return pa.FixedSizeListArray.from_arrays(pa.array(flat, type=arrow_type.value_type), type=arrow_type)
    return None


def write_provenance(root: Path, provenance: dict[str, Any]) -> None:
    """The machine-readable provenance and the dataset card rendered from it (after info/stats)."""
    from shiftkit.cards import render_dataset_card

    (root / PROVENANCE_PATH).write_text(dumps(provenance, indent=2))
    # errors=: a source path that is not UTF-8 is shown escaped rather than failing the write.
    (root / "README.md").write_text(render_dataset_card(root, provenance), errors="backslashreplace")


# --------------------------------------------------------------------------- reading


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

    @property
    def fps(self) -> int:
        return int(self.info["fps"])

    @property
    def features(self) -> Features:
        return user_features(self.info["features"])

    @property
    def num_episodes(self) -> int:
        return len(self.episodes)

    @property
    def robot_type(self) -> str | None:
        return self.info.get("robot_type")

    def episode_groups(self) -> list[list[int]]:
        """Episode indices grouped by data file, so a worker opens each file once."""
        groups: dict[tuple[int, int], list[int]] = {}
        for i, row in enumerate(self.episodes.itertuples(index=False)):
            groups.setdefault((row.chunk, row.file), []).append(i)
        return list(groups.values())

    def iter_episodes(self, indices: list[int] | None = None) -> Iterator[Episode]:
        """The episodes at `indices`, in that order. Consecutive episodes of one data file (a work
        unit's) share one read of just the row groups that hold them."""
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
                yield self._episode_from_table(i, table.slice(start - table_start, stop - start), row)
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

    def _episode_from_table(self, i: int, part: Any, row: Any) -> Episode:
        where = f"{self.root} episode {i}"
        n = part.num_rows
        if n != int(row["length"]) or n == 0:
            raise DatasetError(f"{where}: {n} rows in the data file, metadata says {int(row['length'])}")
        ep_idx = part.column("episode_index").to_numpy()
        if not (ep_idx == int(row["episode_index"])).all():
            raise DatasetError(f"{where}: data rows belong to another episode (corrupt index)")
        frames: dict[str, np.ndarray] = {"timestamp": part.column("timestamp").to_numpy().astype(np.float64)}
        for key, ft in self._features.items():
            if ft["dtype"] == "video":
                frames[key] = self._decode_video(key, row, frames["timestamp"])
                continue
            col = part.column(key)
            if ft["dtype"] == "image":
                encoded = [v["bytes"] for v in col.to_pylist()]  # kept: unchanged frames are not re-encoded
                frames[key] = EncodedFrames.wrap(np.stack([_decode_png(b, where) for b in encoded]), encoded)
            elif ft["dtype"] == "string":
                frames[key] = np.array(col.to_pylist(), dtype=str).reshape(n, 1)
            else:
                arr = _column_to_numpy(col, tuple(ft["shape"]), np.dtype(ft["dtype"]))
                frames[key] = arr.reshape((n, *ft["shape"]))
        task_idx = part.column("task_index").to_numpy()
        frames["task"] = np.array([self.tasks[t] for t in task_idx], dtype=str)
        meta = json.loads(row[META_COLUMN]) if META_COLUMN in row and isinstance(row[META_COLUMN], str) else {}
        meta["source_episode_index"] = i
        if cameras := camera_meta.episode_cameras(self.cameras, i):
            meta["cameras"] = cameras
        return Episode(frames, meta)

    def _decode_video(self, key: str, row: Any, timestamps: np.ndarray) -> np.ndarray:
        chunk, file = int(row[f"videos/{key}/chunk_index"]), int(row[f"videos/{key}/file_index"])
        path = self.root / self.info["video_path"].format(video_key=key, chunk_index=chunk, file_index=file)
        offset = float(row[f"videos/{key}/from_timestamp"])
        return decode_episode(path, offset, timestamps, f"{self.root} episode {int(row['episode_index'])} {key}")


def _column_to_numpy(col: Any, shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
    import pyarrow as pa

    col = col.combine_chunks() if isinstance(col, pa.ChunkedArray) else col
    while pa.types.is_list(col.type) or pa.types.is_fixed_size_list(col.type) or pa.types.is_large_list(col.type):
        col = col.flatten()
    if hasattr(col, "storage"):  # datasets' ArrayND extension types
        col = col.storage
        while hasattr(col, "flatten") and not pa.types.is_primitive(col.type) and not pa.types.is_boolean(col.type):
            col = col.flatten()
    return np.asarray(col.to_numpy(zero_copy_only=False), dtype=dtype)


def _decode_png(data: bytes, where: str) -> np.ndarray:
    import cv2

    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise DatasetError(f"{where}: undecodable image bytes")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def check_info_values(info: dict[str, Any], info_path: Path) -> None:
    """The types of info.json values the reader relies on (a hand-edited file may be off)."""
    fps = info["fps"]
    if isinstance(fps, bool) or not isinstance(fps, int) or fps <= 0:
        raise DatasetError(f"{info_path}: 'fps' must be a positive integer, got {fps!r}")
    if not isinstance(info["data_path"], str) or (
        "video_path" in info and info["video_path"] is not None and not isinstance(info["video_path"], str)
    ):
        raise DatasetError(f"{info_path}: 'data_path' / 'video_path' must be strings")
    features = info["features"]
    if not isinstance(features, dict) or not features:
        raise DatasetError(f"{info_path}: 'features' must be a non-empty object")
    for key, ft in features.items():
        shape = ft.get("shape") if isinstance(ft, dict) else None
        if (
            not isinstance(ft.get("dtype") if isinstance(ft, dict) else None, str)
            or not isinstance(shape, list | tuple)
            or not all(isinstance(d, int) and not isinstance(d, bool) and d >= 0 for d in shape)
        ):
            raise DatasetError(f"{info_path}: feature {key!r} needs a 'dtype' string and a 'shape' list of sizes")


def open_lerobot_dataset(root: str | Path) -> LeRobotDatasetReader:
    """Open a local LeRobot v3.0 dataset for streaming; one-line errors for broken metadata."""
    import pyarrow.parquet as pq

    root = Path(root)
    info_path = root / "meta" / "info.json"
    if not root.is_dir():
        raise DatasetError(f"dataset not found: {root}")
    info = read_json_file(info_path, "not a LeRobot dataset")
    version = str(info.get("codebase_version", ""))
    if version != "v3.0":
        hint = " (convert v2.1 with lerobot's convert_dataset_v21_to_v30)" if version.startswith("v2") else ""
        raise DatasetError(f"{root}: codebase_version {version!r} is not v3.0{hint}")
    for key in ("fps", "features", "data_path"):
        if key not in info:
            raise DatasetError(f"{info_path}: missing key {key!r}")
    check_info_values(info, info_path)
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


# --------------------------------------------------------------------------- dataset IDs


@dataclass(frozen=True)
class ResolvedDataset:
    repo_id: str
    root: Path
    revision: str | None
    fingerprint: str


def fingerprint(root: str | Path) -> str:
    """Content fingerprint of a LeRobot dataset from its metadata (info, stats, episodes, tasks),
    which pins frame counts, schema and per-episode statistics without reading the frames."""
    root = Path(root)
    h = hashlib.sha256()
    paths = [root / "meta" / "info.json", root / "meta" / "stats.json", root / "meta" / "tasks.parquet"]
    paths += sorted((root / "meta" / "episodes").glob("*/*.parquet"))
    for path in paths:
        if path.exists():
            h.update(path.relative_to(root).as_posix().encode())
            h.update(path.read_bytes())
    return h.hexdigest()[:16]


def lerobot_home() -> Path:
    return Path(os.environ.get("HF_LEROBOT_HOME", Path.home() / ".cache" / "huggingface" / "lerobot")).expanduser()


def find_local_dataset(ref: str | Path) -> Path | None:
    """The dataset directory `ref` names locally: the directory itself, or `$HF_LEROBOT_HOME/<ref>`."""
    for path in (Path(ref).expanduser(), lerobot_home() / str(ref)):
        if (path / "meta" / "info.json").is_file():
            return path
    return None


def _not_a_dataset(path: Path) -> str:
    """Why `path` is not a LeRobot dataset, in words a user can act on."""
    if (path / "dataset.json").is_file():
        return f"{path} is a raw episode folder, not a LeRobot dataset: convert it with `shiftkit run` first"
    if path.is_dir():
        return f"{path} is not a LeRobot dataset: {path / 'meta' / 'info.json'} is missing"
    if path.exists():
        return f"{path} is a file, not a LeRobot dataset folder"
    return f"dataset not found: {path} (neither a dataset directory nor an ORG/NAME id)"


def resolve_dataset(ref: str, root: str | Path | None = None, revision: str | None = None) -> ResolvedDataset:
    """Find a dataset given a local path or a dataset ID.

    Order: `root` (the dataset directory) if given; `ref` itself if it is a dataset directory;
    `$HF_LEROBOT_HOME/<ref>`; then the hub (`HF_ENDPOINT`), pulled into the cache at `revision`.
    """
    if root is not None:
        if not (Path(root) / "meta" / "info.json").is_file():
            raise DatasetError(_not_a_dataset(Path(root)))
        return ResolvedDataset(ref, Path(root), revision, fingerprint(root))
    path = find_local_dataset(ref)
    if path is not None:
        repo_id = Path(ref).name if Path(ref).exists() else ref
        return ResolvedDataset(repo_id, path, revision, fingerprint(path))
    if Path(ref).exists() or ref.startswith((".", "/")) or ref.count("/") != 1:
        raise DatasetError(_not_a_dataset(Path(ref)))
    from shiftkit.pipelines import hub

    path = hub.pull_dataset(ref, revision=revision, root=lerobot_home() / ref)
    return ResolvedDataset(ref, path, revision, fingerprint(path))
