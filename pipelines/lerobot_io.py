"""LeRobot v3.0 IO: an atomic, fast episode writer on lerobot's own format code, a streaming
per-episode reader, and dataset-ID resolution.

The writer creates the dataset with `LeRobotDataset.create` and stores each episode through
lerobot's own pieces (`datasets.Dataset.from_dict` with lerobot's HF features, lerobot's episode
statistics, `LeRobotDatasetMetadata.save_episode`), so the files are what lerobot writes. It skips
the two costs of the high-level path that do not apply to whole episodes held in memory: the
per-frame `add_frame` loop, and `embed_images`, a `datasets.map` over every row that re-reads PNG
files from disk (here images are encoded straight into the row, with the same PNG bytes and file
name lerobot would embed). Camera features are written as `image` (PNG in parquet, no codec) or,
declared `video`, through lerobot's own video encoder (`pipelines/video.py`).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
import uuid
import warnings
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
from shiftkit.pipelines.video import decode_episode, save_episode_videos

META_COLUMN = "shiftkit/meta"  # episode-level metadata (JSON) in meta/episodes/*.parquet
PROVENANCE_PATH = "meta/shiftkit_provenance.json"
_PNG_COMPRESS_LEVEL = 6  # what lerobot's add_frame uses for `image` features


def _png_bytes(frame: np.ndarray) -> bytes:
    import PIL.Image

    buf = io.BytesIO()
    PIL.Image.fromarray(frame).save(buf, format="PNG", compress_level=_PNG_COMPRESS_LEVEL)
    return buf.getvalue()


def _image_stats(frames: np.ndarray) -> dict[str, np.ndarray]:
    """lerobot's image statistics (`sample_images` + `get_feature_stats`) from in-memory frames."""
    from lerobot.datasets.compute_stats import auto_downsample_height_width, get_feature_stats, sample_indices

    frames = np.asarray(frames)  # a plain array (not EncodedFrames) for the statistics

    sampled = np.stack(
        [auto_downsample_height_width(frames[i].transpose(2, 0, 1)) for i in sample_indices(len(frames))]
    )
    stats = get_feature_stats(sampled, axis=(0, 2, 3), keepdims=True)
    return {k: v if k == "count" else np.squeeze(v / 255.0, axis=0) for k, v in stats.items()}


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


def _stats(columns: dict[str, Any], all_features: Features) -> dict[str, dict[str, np.ndarray]]:
    from lerobot.datasets.compute_stats import compute_episode_stats

    with warnings.catch_warnings():
        # lerobot's histogram code warns for every bool feature (e.g. next.success).
        warnings.filterwarnings("ignore", message="Converting input from bool", category=RuntimeWarning)
        return compute_episode_stats(columns, all_features)


def episode_stats(episode: Episode, features: Features) -> dict[str, dict[str, np.ndarray]]:
    """lerobot's per-episode statistics of every position-independent column of `episode`."""
    from lerobot.datasets.utils import DEFAULT_FEATURES

    columns = _episode_columns(episode, features)
    # Camera features, image or video: lerobot computes both from the frames before encoding.
    images = {k: columns.pop(k) for k, ft in features.items() if ft["dtype"] in CAMERA_DTYPES}
    stats = _stats(columns, {**features, **DEFAULT_FEATURES})
    stats.update({k: _image_stats(v) for k, v in images.items()})
    return stats


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
        self.tmp = self.root.parent / f".{self.root.name}.partial-{uuid.uuid4().hex[:8]}"
        video_keys = [k for k, ft in self.features.items() if ft["dtype"] == "video"]  # pipelines/video.py
        try:
            self.root.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise DatasetError(f"cannot create the destination's folder {self.root.parent}: {exc.strerror}") from None
        self._ds = LeRobotDataset.create(
            repo_id, self.fps, dict(self.features), root=self.tmp, robot_type=robot_type, use_videos=bool(video_keys)
        )
        self._meta = self._ds.meta
        self._hf_features = get_hf_features_from_features(self._ds.features)
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
        from lerobot.datasets.compute_stats import aggregate_stats
        from lerobot.datasets.utils import flatten_dict, get_file_size_in_mb, update_chunk_file_indices

        where = f"episode {episode.meta.get('source_episode_index', self.num_episodes)}"
        check_episode(episode, self.features, self.fps, where)
        episode_meta = self._take_cameras(episode.meta, where)
        n = len(episode)
        tasks = [str(t) for t in episode.frames["task"]]
        episode_tasks = list(dict.fromkeys(tasks))  # first-appearance order: deterministic
        self._meta.save_episode_tasks(episode_tasks)
        task_index = {t: self._meta.get_task_index(t) for t in episode_tasks}

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
        stats = {**stats, **_stats({k: columns[k] for k in POSITION_KEYS}, self._ds.features)}
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
        self._meta.stats = aggregate_stats([self._meta.stats, stats]) if self._meta.stats is not None else stats
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
        without the Dataset object, whose fingerprinting pickles every value (~50 ms/episode)."""
        from datasets.arrow_writer import OptimizedTypedSequence
        from datasets.table import InMemoryTable

        features = self._hf_features
        typed = {
            key: OptimizedTypedSequence(features.encode_column(columns[key], key), type=features[key], col=key)
            for key in features
        }
        return InMemoryTable.from_pydict(mapping=typed).table.cast(features.arrow_schema)

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
        stats = self._meta.stats
        write_stats({k: stats[k] for k in self._ds.features if k in stats}, self.tmp)

    def abort(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        self._meta.metadata_buffer.clear()
        self._meta._close_writer()
        shutil.rmtree(self.tmp, ignore_errors=True)
        self._closed = True


def write_provenance(root: Path, provenance: dict[str, Any]) -> None:
    """The machine-readable provenance and the dataset card rendered from it (after info/stats)."""
    from shiftkit.cards import render_dataset_card

    (root / PROVENANCE_PATH).write_text(dumps(provenance, indent=2))
    (root / "README.md").write_text(render_dataset_card(root, provenance))


# --------------------------------------------------------------------------- reading


@dataclass
class LeRobotDatasetReader:
    """Streams a local LeRobot v3.0 dataset one episode at a time (one data file open at a time)."""

    root: Path
    info: dict[str, Any]
    episodes: Any  # pandas DataFrame of meta/episodes without stats columns
    tasks: list[str]
    cameras: dict[str, Any] = field(default_factory=dict)  # meta/cameras.json (camera_meta)

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
        import pyarrow.parquet as pq

        indices = list(range(self.num_episodes)) if indices is None else list(indices)
        table, table_key, table_start = None, None, 0
        for i in indices:
            if not 0 <= i < self.num_episodes:
                raise DatasetError(f"{self.root}: no episode {i} (dataset has {self.num_episodes})")
            row = self.episodes.iloc[i]
            key = (int(row["chunk"]), int(row["file"]))
            if key != table_key:
                path = self.root / self.info["data_path"].format(chunk_index=key[0], file_index=key[1])
                try:
                    table = pq.read_table(path)
                except FileNotFoundError:
                    raise DatasetError(f"{path}: data file is missing") from None
                except Exception as exc:  # pyarrow raises several types for corrupt files
                    raise DatasetError(f"{path}: unreadable parquet file ({type(exc).__name__}: {exc})") from None
                table_key = key
                same_file = self.episodes[(self.episodes["chunk"] == key[0]) & (self.episodes["file"] == key[1])]
                table_start = int(same_file["dataset_from_index"].min())
            start, stop = int(row["dataset_from_index"]), int(row["dataset_to_index"])
            part = table.slice(start - table_start, stop - start)
            yield self._episode_from_table(i, part, row)

    def _episode_from_table(self, i: int, part: Any, row: Any) -> Episode:
        where = f"{self.root} episode {i}"
        n = part.num_rows
        if n != int(row["length"]) or n == 0:
            raise DatasetError(f"{where}: {n} rows in the data file, metadata says {int(row['length'])}")
        ep_idx = part.column("episode_index").to_numpy()
        if not (ep_idx == int(row["episode_index"])).all():
            raise DatasetError(f"{where}: data rows belong to another episode (corrupt index)")
        frames: dict[str, np.ndarray] = {"timestamp": part.column("timestamp").to_numpy().astype(np.float64)}
        for key, ft in self.features.items():
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


def resolve_dataset(ref: str, root: str | Path | None = None, revision: str | None = None) -> ResolvedDataset:
    """Find a dataset given a local path or a dataset ID.

    Order: `root` (the dataset directory) if given; `ref` itself if it is a dataset directory;
    `$HF_LEROBOT_HOME/<ref>`; then the hub (`HF_ENDPOINT`), pulled into the cache at `revision`.
    """
    if root is not None:
        if not (Path(root) / "meta" / "info.json").is_file():
            raise DatasetError(f"no LeRobot dataset at {root} (meta/info.json missing)")
        return ResolvedDataset(ref, Path(root), revision, fingerprint(root))
    path = find_local_dataset(ref)
    if path is not None:
        repo_id = Path(ref).name if Path(ref).exists() else ref
        return ResolvedDataset(repo_id, path, revision, fingerprint(path))
    if Path(ref).exists() or ref.startswith((".", "/")) or ref.count("/") != 1:
        raise DatasetError(f"dataset not found: {ref} (neither a dataset directory nor an ORG/NAME id)")
    from shiftkit.pipelines import hub

    path = hub.pull_dataset(ref, revision=revision, root=lerobot_home() / ref)
    return ResolvedDataset(ref, path, revision, fingerprint(path))


def write_raw_as_lerobot(
    raw_dir: str | Path,
    repo_id: str,
    root: str | Path,
    workers: int = 1,
    progress: bool = False,
    video: bool = False,
) -> Path:
    """Convert a raw-episode directory into a LeRobot dataset at `root` (a pipeline with no stages)."""
    from shiftkit.pipelines.config import DestinationConfig, PipelineConfig
    from shiftkit.pipelines.runner import run_pipeline
    from shiftkit.pipelines.sources import SourceConfig

    config = PipelineConfig(
        sources=[SourceConfig(path=str(Path(raw_dir).resolve()))],
        destination=DestinationConfig(root=str(Path(root).resolve()), repo_id=repo_id, video=video),
    )
    return run_pipeline(config, workers=workers, progress=progress)
