"""LeRobot v3.0 IO, the one module that touches lerobot's dataset internals: an atomic, fast
episode writer on lerobot 0.6's own format code, a streaming per-episode reader with the one image
and video decoder of stages and trainers, the v2.1 conversion, and dataset-ID resolution. Every
shiftkit producer of a dataset (pipelines under every executor, importers, `collect`, FIRE) writes
through `DatasetWriter`.

The writer creates the dataset with `LeRobotDatasetMetadata.create` and stores each episode through
lerobot's own pieces (its HF features and their Arrow schema, its episode statistics' values,
`io_utils.write_info` / `write_stats`, its `DatasetWriter` for video files), so the files are what
lerobot's `add_frame` / `save_episode` write (tests/test_lerobot_io.py compares them). It skips the
costs of the high-level path that do not apply to whole episodes held in memory: the per-frame
`add_frame` loop, `embed_images`, a `datasets.map` over every row that re-reads image files from
disk (here images are encoded straight into the row, with the same PNG / TIFF bytes and file name
lerobot would embed), per-value Python conversion (numeric columns go to Arrow from their numpy
buffers), and rewriting info.json and re-aggregating all statistics after every episode.
Statistics come from `shiftkit.pipelines.stats` (lerobot's values, vectorised), computed by the
worker that produced the episode. Cameras are `image` (PNG; depth: TIFF, `pipelines/depth.py`) or
`video` (lerobot's encoder settings, `pipelines/video.py`).

lerobot's private names still used, because its public API has no per-episode equivalent without
those costs (tests/test_lerobot_internals.py fails loudly when lerobot moves one):
* `LeRobotDatasetMetadata._save_episode_metadata`: appends one episode's row to the episodes
  table; the public `save_episode` also rewrites info.json and stats.json and aggregates all
  statistics again, per episode.
* `LeRobotDatasetMetadata._metadata_buffer`: cleared on abort, so that finalizing does not write
  buffered rows into the folder being removed.
* `lerobot.datasets.dataset_writer.DatasetWriter._save_episode_video`: appends an encoded episode
  to the current video file (rotating files at `video_files_size_in_mb`) and fills the feature's
  `info` from the first episode; public only through `save_episode`, which encodes from image
  files on disk.
"""

from __future__ import annotations

import hashlib
import io
import json
import shutil
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from shiftkit.pipelines import camera_meta, depth, loaders
from shiftkit.pipelines.arrow_columns import column_to_numpy
from shiftkit.pipelines.encoded_frames import PNG, EncodedFrames, source_bytes
from shiftkit.pipelines.episode import Episode
from shiftkit.pipelines.errors import DatasetError
from shiftkit.pipelines.features import (
    CAMERA_DTYPES,
    TEXT_DTYPES,
    Features,
    check_episode,
    check_features,
    object_column,
    plain_camera_features,
    user_features,
)
from shiftkit.pipelines.jsonutil import dumps
from shiftkit.pipelines.local_datasets import find_local_dataset, lerobot_home
from shiftkit.pipelines.staging import publish, remove_dead_staging, staging_path
from shiftkit.pipelines.stats import RunningStats, image_stats, numeric_stats
from shiftkit.pipelines.video import decode_episode, encode_frames

_EPISODES_PER_READ = 64  # a reader holds at most this many episodes' rows of one data file
META_COLUMN = "shiftkit/meta"  # episode-level metadata (JSON) in meta/episodes/*.parquet
PROVENANCE_PATH = "meta/shiftkit_provenance.json"
_PNG_COMPRESS_LEVEL = 6  # what lerobot's add_frame uses for `image` features


def _png_bytes(frame: np.ndarray) -> bytes:
    import PIL.Image

    buf = io.BytesIO()
    PIL.Image.fromarray(frame).save(buf, format="PNG", compress_level=_PNG_COMPRESS_LEVEL)
    return buf.getvalue()


def _tiff_bytes(stored: np.ndarray) -> bytes:
    """One depth frame, (H, W, 1) float32 or uint16, as the raw TIFF lerobot's `write_image` writes
    for depth (PIL mode F / I;16, no compression)."""
    import PIL.Image

    buf = io.BytesIO()
    PIL.Image.fromarray(np.ascontiguousarray(stored[..., 0])).save(buf, format="TIFF", compression="raw")
    return buf.getvalue()


def image_form(ft: dict[str, Any]) -> str:
    """What the encoded bytes of an `image` feature store (`encoded_frames`): PNG RGB, or depth in
    its unit."""
    return f"depth-{depth.depth_unit(ft)}" if depth.is_depth(ft) else PNG


def _frame_bytes(frames: np.ndarray, ft: dict[str, Any]) -> list[bytes]:
    """The encoded bytes of every frame of an `image` feature, a frame's source bytes where it is
    unchanged and stored in the same form (`encoded_frames`): PNG for RGB, TIFF in the stored unit
    for depth."""
    form = image_form(ft)
    if depth.is_depth(ft):
        unit = depth.depth_unit(ft)
        return [source_bytes(f, frames, form) or _tiff_bytes(depth.to_stored(f, unit)) for f in frames]
    return [source_bytes(f, frames, form) or _png_bytes(f) for f in frames]


# Statistics that depend on where an episode lands in the dataset; all others are a function of
# the episode alone and can be computed in parallel workers (`episode_stats`).
POSITION_KEYS = ("episode_index", "index", "task_index")


def _episode_columns(episode: Episode, features: Features) -> dict[str, Any]:
    """Per-frame columns as lerobot's writer buffers them (scalar features flattened)."""
    n = len(episode)
    columns: dict[str, Any] = {}
    for key, ft in features.items():
        arr = episode.frames[key]
        columns[key] = arr.reshape(n) if tuple(ft["shape"]) == (1,) and ft["dtype"] not in CAMERA_DTYPES else arr
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
    # (EncodedFrames carry decoded pixels: statistics read a plain array). Depth statistics are
    # in the stored unit, not scaled to [0, 1].
    cameras = {k: np.asarray(columns.pop(k)) for k, ft in features.items() if ft["dtype"] in CAMERA_DTYPES}
    stats = numeric_stats(
        {k: v for k, v in columns.items() if k not in features or features[k]["dtype"] not in TEXT_DTYPES}
    )
    for key, frames in cameras.items():
        ft = features[key]
        if depth.is_depth(ft):
            stats[key] = image_stats(depth.to_stored(frames, depth.depth_unit(ft)), depth=True)
        else:
            stats[key] = image_stats(frames)
    return stats


def encode_images(episode: Episode, features: Features) -> Episode:
    """`episode` with every `image` feature as `EncodedFrames` holding each frame's encoded bytes
    (a frame's source bytes where it is unchanged), so that the writer reuses them. Pipeline
    workers call this, so that image encoding, the largest cost of writing images, runs in
    parallel rather than in the one writer."""
    keys = [k for k, ft in features.items() if ft["dtype"] == "image"]
    return episode.with_frames(
        **{
            k: EncodedFrames.wrap(
                episode.frames[k], _frame_bytes(episode.frames[k], features[k]), image_form(features[k])
            )
            for k in keys
        }
    )


def preload_writer() -> None:
    """Import what `DatasetWriter` needs from lerobot (which pulls in torch: seconds of start-up), so a
    caller can do it in a thread while other work runs; an import that fails here fails again, with
    its message, where the writer imports it."""
    import importlib

    for module in ("lerobot.configs", "lerobot.datasets.dataset_writer", "lerobot.datasets.feature_utils"):
        try:
            importlib.import_module(module)
        except Exception:  # noqa: BLE001 - reported by the writer's own import
            return


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
        from lerobot.configs import depth_encoder_defaults, rgb_encoder_defaults
        from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata
        from lerobot.datasets.dataset_writer import DatasetWriter as LeRobotWriter
        from lerobot.datasets.feature_utils import get_hf_features_from_features

        self.root = Path(root)
        if self.root.exists():
            raise DatasetError(f"destination already exists: {self.root}")
        self.features = plain_camera_features(user_features(features))
        check_features(self.features, where=f"schema of {self.root}")
        self.fps = int(fps)
        self.repo_id = repo_id
        self.tmp = staging_path(self.root)
        video_keys = [k for k, ft in self.features.items() if ft["dtype"] == "video"]  # pipelines/video.py
        try:
            self.root.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise DatasetError(f"cannot create the destination's folder {self.root.parent}: {exc.strerror}") from None
        remove_dead_staging(self.root)
        # lerobot's own metadata and writer objects: the writer appends video files and fills a
        # video feature's `info` (`video.*`, the depth quantiser) exactly as its save_episode does.
        self._meta = LeRobotDatasetMetadata.create(
            repo_id, self.fps, dict(self.features), robot_type=robot_type, root=self.tmp, use_videos=bool(video_keys)
        )
        self._encoders = {"rgb": rgb_encoder_defaults(), "depth": depth_encoder_defaults()}
        self._lerobot = LeRobotWriter(
            self._meta,
            self.tmp,
            rgb_encoder=self._encoders["rgb"],
            depth_encoder=self._encoders["depth"],
            encoder_threads=None,
            batch_encoding_size=1,
        )
        self._stats = RunningStats()
        self._task_index: dict[str, int] = {}
        self._hf_features = get_hf_features_from_features(self._meta.features)
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
        from lerobot.datasets.io_utils import get_file_size_in_mb
        from lerobot.datasets.utils import update_chunk_file_indices
        from lerobot.utils.utils import flatten_dict

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
            suffix = "tiff" if depth.is_depth(self.features[key]) else "png"  # lerobot's file names
            columns[key] = [
                {"bytes": b, "path": f"frame-{t:06d}.{suffix}"}
                for t, b in enumerate(_frame_bytes(columns[key], self.features[key]))
            ]
        columns["episode_index"] = np.full(n, self.num_episodes, dtype=np.int64)
        columns["index"] = np.arange(start, start + n, dtype=np.int64)
        columns["task_index"] = np.array([task_index[t] for t in tasks], dtype=np.int64)

        if stats is None:
            stats = episode_stats(episode, self.features)
        stats = {**stats, **numeric_stats({k: columns[k] for k in POSITION_KEYS})}
        # Same key order as lerobot (feature order), which fixes the episodes-parquet columns.
        stats = {k: stats[k] for k in self._meta.features if k in stats}

        table = self._arrow_table(columns)
        videos = self._save_videos({k: episode.frames[k] for k in self._video_keys})

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
        # stats.json (and aggregating all statistics again) after every episode: the writer
        # writes them once, in close().
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
        info.total_episodes += 1
        info.total_frames += n
        info.total_tasks = len(self._meta.tasks)
        info.splits = {"train": f"0:{info.total_episodes}"}
        self._stats.add(stats)  # lerobot's aggregate_stats([stats, episode stats]), vectorised
        self.num_episodes += 1
        self.num_frames += n

    def _save_videos(self, videos: dict[str, np.ndarray]) -> dict[str, Any]:
        """Encode this episode's video features with lerobot's encoder settings (RGB, or depth
        through its quantiser) and append them to the dataset's video files as lerobot's writer
        does; returns the `videos/KEY/...` episode metadata."""
        import tempfile

        metadata: dict[str, Any] = {}
        for key, frames in videos.items():
            is_depth = depth.is_depth(self.features[key])
            encoder = self._encoders["depth" if is_depth else "rgb"]
            if is_depth:  # lerobot encodes depth from its stored unit (float32 m or uint16 mm)
                frames = depth.to_stored(frames, depth.depth_unit(self.features[key]))
            # lerobot's layout: a temporary folder in the dataset root, removed by _save_episode_video.
            path = Path(tempfile.mkdtemp(dir=self.tmp)) / f"{key}_{self.num_episodes:03d}.mp4"
            encode_frames(frames, path, self.fps, encoder)
            metadata.update(self._lerobot._save_episode_video(key, self.num_episodes, temp_path=path))
        metadata.pop("episode_index", None)
        return metadata

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
        Numeric columns go straight from their numpy arrays; the others (images, n-d arrays,
        language) through datasets' own per-value encoding."""
        import pyarrow as pa

        schema = self._arrow_schema
        arrays = {field.name: _numeric_arrow_array(columns[field.name], field.type) for field in schema}
        encoded = [key for key, array in arrays.items() if array is None]
        if encoded:
            from datasets.arrow_writer import OptimizedTypedSequence
            from datasets.table import InMemoryTable

            features = self._hf_features
            typed = {
                key: OptimizedTypedSequence(
                    features.encode_column(list(columns[key]), key), type=features[key], col=key
                )
                for key in encoded
            }
            table = InMemoryTable.from_pydict(mapping=typed).table.cast(pa.schema([schema.field(k) for k in encoded]))
            arrays.update({key: table.column(key) for key in encoded})
        return pa.Table.from_arrays([arrays[field.name] for field in schema], schema=schema)

    def close(self, provenance: dict[str, Any] | None = None, carry_from: list[Path] = ()) -> Path:
        """Finalize, write provenance and the dataset card rendered from it, and move the dataset
        into place. `carry_from`: source datasets whose own metadata the output keeps
        (`carry_source_metadata`)."""
        if self._closed:
            return self.root
        if self.num_episodes == 0:
            self.abort()
            raise DatasetError(f"no episodes to write to {self.root} (every episode was filtered out)")
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        self._lerobot.finalize()  # lerobot's: flushes the episodes table, closes its files
        shutil.rmtree(self.tmp / "images", ignore_errors=True)  # the video encoder's input frames
        self._write_info_and_stats()
        carry_source_metadata(self.tmp, carry_from)
        cameras = camera_meta.provenance_entry(camera_meta.write_cameras_file(self.tmp, self._cameras))
        if provenance is not None:
            write_provenance(self.tmp, {**provenance, "cameras": cameras} if cameras else provenance)
        self._closed = True
        publish(self.tmp, self.root)
        return self.root

    def _write_info_and_stats(self) -> None:
        """info.json and stats.json, once. lerobot aggregates stats over a `set` of keys, so their
        order would follow the process's string-hash seed: write them in feature order instead."""
        from lerobot.datasets.io_utils import write_info, write_stats

        write_info(self._meta.info, self.tmp)
        stats = self._meta.stats = self._stats.result()
        write_stats({k: stats[k] for k in self._meta.features if k in stats}, self.tmp)

    def abort(self) -> None:
        """Drop what was written so far (the staging folder); nothing reaches the destination."""
        if self._closed:
            return
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        # Drop the buffered episode rows first: finalizing would write them into the folder
        # about to be removed (and re-create it).
        self._meta._metadata_buffer.clear()
        self._lerobot.finalize()
        shutil.rmtree(self.tmp, ignore_errors=True)
        self._closed = True


# What every dataset's meta/ holds, written anew for each output (lerobot's tables, shiftkit's files).
_OWN_META = {
    "info.json",
    "stats.json",
    "tasks.parquet",
    "episodes",
    *(Path(p).name for p in (camera_meta.CAMERAS_PATH, PROVENANCE_PATH)),
}


def lerobot_roots(sources: list[Any]) -> list[Path]:
    """The folders of the pipeline sources that are LeRobot datasets (their metadata is carried)."""
    roots = [Path(s.root) for s in sources if getattr(s, "root", None) is not None]
    return [r for r in roots if (r / "meta" / "info.json").is_file()]


def carry_source_metadata(dest: Path, sources: list[Path]) -> None:
    """Keep what the source datasets carry beyond the tables a writer makes: the other files in
    their `meta/` (e.g. lerobot's annotation outputs) and the `tools` of their info.json, the first
    source's where several have one."""
    from lerobot.datasets.io_utils import load_info, write_info

    tools = None
    for source in sources:
        meta = Path(source) / "meta"
        for entry in sorted(meta.iterdir()) if meta.is_dir() else []:
            target = dest / "meta" / entry.name
            if entry.name in _OWN_META or target.exists():
                continue
            if entry.is_dir():
                shutil.copytree(entry, target)
            else:
                shutil.copy2(entry, target)
        if tools is None and (meta / "info.json").is_file():
            tools = loaders.load_info(meta / "info.json").get("tools")
    if tools is not None:
        info = load_info(dest)
        info.tools = tools
        write_info(info, dest)


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
    """The machine-readable provenance, with the quality verdict on what was written
    (`pipelines.quality`), and the dataset card rendered from it (after info/stats)."""
    from shiftkit.cards import render_dataset_card
    from shiftkit.pipelines.quality import quality_verdict

    provenance = {**provenance, "quality": quality_verdict(root)}
    (root / PROVENANCE_PATH).write_text(dumps(provenance, indent=2))
    # errors=: a source path that is not UTF-8 is shown escaped rather than failing the write.
    (root / "README.md").write_text(render_dataset_card(root, provenance), errors="backslashreplace")


# --------------------------------------------------------------------------- v2.1 conversion

V21_CONVERTER = "lerobot.scripts.convert_dataset_v21_to_v30"


def convert_v21(source: Path, dest: Path) -> tuple[int, int, int]:
    """lerobot's v2.1 -> v3.0 conversion steps from `source` into a new folder `dest`: its
    `convert_dataset` works in place (renames the source), these steps read `source` only.
    Returns (episodes, frames, fps)."""
    import importlib

    from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata
    from lerobot.datasets.utils import DEFAULT_DATA_FILE_SIZE_IN_MB, DEFAULT_VIDEO_FILE_SIZE_IN_MB

    converter = importlib.import_module(V21_CONVERTER)
    converter.convert_info(source, dest, DEFAULT_DATA_FILE_SIZE_IN_MB, DEFAULT_VIDEO_FILE_SIZE_IN_MB)
    converter.convert_tasks(source, dest)
    episodes = converter.convert_data(source, dest, DEFAULT_DATA_FILE_SIZE_IN_MB)
    videos = converter.convert_videos(source, dest, DEFAULT_VIDEO_FILE_SIZE_IN_MB)
    converter.convert_episodes_metadata(source, dest, episodes, videos)
    meta = LeRobotDatasetMetadata(dest.name, root=dest)  # loads: info, tasks, episodes, stats
    return meta.total_episodes, meta.total_frames, meta.fps


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

    def _decode_video(self, key: str, row: Any, timestamps: np.ndarray) -> np.ndarray:
        chunk, file = int(row[f"videos/{key}/chunk_index"]), int(row[f"videos/{key}/file_index"])
        path = self.root / self.info["video_path"].format(video_key=key, chunk_index=chunk, file_index=file)
        offset = float(row[f"videos/{key}/from_timestamp"])
        where = f"{self.root} episode {int(row['episode_index'])} {key}"
        return decode_video(path, offset, timestamps, where, self._features[key])


def decode_image(data: bytes, where: str, ft: dict[str, Any]) -> np.ndarray:
    """One frame of an `image` feature as shiftkit holds it: RGB uint8 (H, W, 3) (grey (H, W, 1) for
    a one-channel camera), depth float32 metres (H, W, 1). The one image decoder of stages and
    trainers."""
    if depth.is_depth(ft):
        return _decode_depth(data, where, ft)
    return _decode_png(data, where, grey=tuple(ft["shape"])[-1] == 1)


def decode_video(path: Path, start: float, timestamps: np.ndarray, where: str, ft: dict[str, Any]) -> np.ndarray:
    """The frames of a `video` feature at `start + timestamps` in the file at `path`, as
    `decode_image` gives them. The one video decoder of stages and trainers."""
    return decode_episode(path, start, timestamps, where, ft.get("info") if depth.is_depth(ft) else None)


def _decode_png(data: bytes, where: str, grey: bool = False) -> np.ndarray:
    import cv2

    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_COLOR)
    if img is None:
        raise DatasetError(f"{where}: undecodable image bytes")
    return img[..., None] if grey else cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _decode_depth(data: bytes, where: str, ft: dict[str, Any]) -> np.ndarray:
    """A lerobot depth image (TIFF, float32 m or uint16 mm; PNG for 16-bit writers) -> (H, W, 1) metres."""
    import PIL.Image

    try:
        with PIL.Image.open(io.BytesIO(data)) as img:
            arr = np.array(img)
    except Exception as exc:  # PIL raises several types for corrupt files
        raise DatasetError(f"{where}: undecodable depth image bytes ({type(exc).__name__})") from None
    if arr.ndim != 2 or arr.dtype not in (np.float32, np.uint16):
        raise DatasetError(f"{where}: depth image of shape {arr.shape} and dtype {arr.dtype} is not one lerobot writes")
    shape = tuple(ft["shape"])
    if arr.shape != shape[:2]:
        raise DatasetError(f"{where}: depth image has shape {arr.shape}, expected {shape[:2]}")
    return depth.clean_metres(depth.to_metres(arr, (ft.get("info") or {}).get("depth_unit")))


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


# --------------------------------------------------------------------------- dataset IDs


@dataclass(frozen=True)
class ResolvedDataset:
    """A dataset ID resolved to a local folder, with the revision pulled and its content fingerprint."""

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


def dataset_fingerprint(root: Path) -> str | None:
    """`fingerprint` of a LeRobot dataset folder, None for any other path (so that two folders that
    are no datasets never look alike): the content key of `staging.check_inputs_and_outputs`."""
    return fingerprint(root) if (Path(root) / "meta" / "info.json").is_file() else None


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
