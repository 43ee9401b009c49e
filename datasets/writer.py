"""The one writer of LeRobot v3.0 datasets: atomic, fast, on lerobot 0.6's own format code, and
always with provenance. Every shiftkit producer of a dataset (pipelines under every executor, and so
imports; `collect`; FIRE) writes through `DatasetWriter`, and only modules of `shiftkit.datasets`
write dataset files (tests/test_write_path.py checks it).

The writer creates the dataset with `LeRobotDatasetMetadata.create` and stores each episode through
lerobot's own pieces (its HF features and their Arrow schema, its episode statistics' values,
`io_utils.write_info` / `write_stats`, its `DatasetWriter` for video files), so the files are what
lerobot's `add_frame` / `save_episode` write (tests/test_writer.py compares them). It skips the
costs of the high-level path that do not apply to whole episodes held in memory: the per-frame
`add_frame` loop, `embed_images`, a `datasets.map` over every row that re-reads image files from
disk (here images are encoded straight into the row, with the same PNG / TIFF bytes and file name
lerobot would embed), per-value Python conversion (numeric columns go to Arrow from their numpy
buffers), and rewriting info.json and re-aggregating all statistics after every episode.
Statistics come from `shiftkit.datasets.stats` (lerobot's values, vectorised), computed by the
worker that produced the episode. Cameras are `image` (PNG; depth: TIFF, `images.py`, `depth.py`) or
`video` (`video.py`: encoded with the source's settings recorded in the feature's `info`, else
lerobot's defaults; a source's frames that pass unchanged are copied packet for packet instead,
`video_copy.py`).

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

import json
import shutil
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from shiftkit.datasets import camera_meta, depth, loaders
from shiftkit.datasets.episode import META_COLUMN, Episode
from shiftkit.datasets.errors import DatasetError
from shiftkit.datasets.features import Features, check_episode, check_features, plain_camera_features, user_features
from shiftkit.datasets.images import frame_bytes
from shiftkit.datasets.jsonutil import dumps
from shiftkit.datasets.provenance import PROVENANCE_PATH, write_provenance
from shiftkit.datasets.staging import publish, remove_dead_staging, staging_path
from shiftkit.datasets.stats import POSITION_KEYS, RunningStats, episode_columns, episode_stats, numeric_stats
from shiftkit.datasets.video import EncodedVideo, default_encoders, encode_episode_video, encoder_for
from shiftkit.datasets.video_copy import VideoFileCopier, VideoRef


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
        video_keys = [k for k, ft in self.features.items() if ft["dtype"] == "video"]  # datasets/video.py
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
        self._lerobot = LeRobotWriter(
            self._meta,
            self.tmp,
            rgb_encoder=default_encoders()["rgb"],
            depth_encoder=default_encoders()["depth"],
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
        self.video_modes: dict[str, str] = {}
        """Per video feature, whether its frames were "copied" from the source's video or "encoded"."""
        self._copiers: dict[str, VideoFileCopier] = {}

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
        columns = episode_columns(episode, self.features)
        for key in self._image_keys:
            suffix = "tiff" if depth.is_depth(self.features[key]) else "png"  # lerobot's file names
            columns[key] = [
                {"bytes": b, "path": f"frame-{t:06d}.{suffix}"}
                for t, b in enumerate(frame_bytes(columns[key], self.features[key]))
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
        """Append this episode's video features to the dataset's video files as lerobot's writer
        does: copied from the source's video where they are its unchanged frames (`_copies`), else
        encoded with `video.encoder_for`'s settings (RGB, or depth through its quantiser), here or
        already by a pipeline worker (`EncodedVideo`); returns the `videos/KEY/...` episode metadata."""
        import tempfile

        metadata: dict[str, Any] = {}
        for key, frames in videos.items():
            if self._copies(key, frames):
                metadata.update(self._copiers[key].add(frames))
                continue
            encoder = encoder_for(self.features[key])
            # lerobot's layout: a temporary folder in the dataset root, removed by _save_episode_video.
            path = Path(tempfile.mkdtemp(dir=self.tmp)) / f"{key}_{self.num_episodes:03d}.mp4"
            if isinstance(frames, EncodedVideo):
                shutil.copyfile(frames.path, path)  # the worker's file stays until the run ends
            else:  # frames, or a source's frames not copied (decoded here)
                encode_episode_video(frames, self.features[key], self.fps, path)
            metadata.update(self._lerobot._save_episode_video(key, self.num_episodes, temp_path=path))
            lerobots = default_encoders()["depth" if depth.is_depth(self.features[key]) else "rgb"]
            if self.num_episodes == 0 and encoder != lerobots:
                # lerobot recorded its writer's encoder settings in the feature's info: these instead
                self._meta.update_video_info(key, video_encoder=encoder)
        metadata.pop("episode_index", None)
        return metadata

    def _copies(self, key: str, frames: Any) -> bool:
        """Whether this episode's `key` frames are copied from their source video (`VideoRef`): then
        all of that feature's are (one file takes packets of one stream or an encoder's, not both),
        decided on its first episode; the feature's `info` is the source's (`video.*`, its codec
        settings). A reference in an encoded feature is decoded."""
        mode = self.video_modes.get(key)
        if mode is None:
            source = frames.feature if isinstance(frames, VideoRef) else None
            copyable = source is not None and _copyable(source, self.features[key])
            mode = self.video_modes[key] = "copied" if copyable else "encoded"
            if copyable:
                info = dict(source.get("info") or {})
                if "video.fps" in info:
                    info["video.fps"] = self.fps  # `subsample`'s kept frames are shown at the output's
                self._meta.info.features[key]["info"] = info
                self._copiers[key] = VideoFileCopier(
                    self.tmp,
                    key,
                    self._meta.video_path,
                    self._meta.chunks_size,
                    self._meta.video_files_size_in_mb,
                    self.fps,
                )
        if mode == "copied" and not isinstance(frames, VideoRef):
            raise DatasetError(f"{key}: decoded frames after copied ones; a video file cannot hold both")
        return mode == "copied"

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
        for copier in self._copiers.values():
            copier.close()
        cut = {k: c.encoded_frames for k, c in sorted(self._copiers.items()) if c.encoded_frames}
        if cut and provenance is not None:  # frames encoded where a copied camera was cut between keyframes
            provenance = {**provenance, "video_encoded_at_cuts": cut}
        self._lerobot.finalize()  # lerobot's: flushes the episodes table, closes its files
        shutil.rmtree(self.tmp / "images", ignore_errors=True)  # the video encoder's input frames
        self._write_info_and_stats()
        carry_source_metadata(self.tmp, carry_from)
        cameras = camera_meta.provenance_entry(camera_meta.write_cameras_file(self.tmp, self._cameras))
        self._closed = True
        if provenance is None:  # test fixtures and benchmark sources: shiftkit's commands always record it
            publish(self.tmp, self.root)
            return self.root
        return finish(self.tmp, self.root, {**provenance, "cameras": cameras} if cameras else provenance)

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
        for copier in self._copiers.values():
            copier.close_source()
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


def _copyable(source: dict[str, Any], out: dict[str, Any]) -> bool:
    """Whether frames of the source video feature `source` can be copied into the output feature
    `out`: both RGB or both depth in one unit (whose quantiser, in the source's `info`, comes along),
    the same shape (at another fps the copier shows them at the output's)."""
    return (
        depth.is_depth(source) == depth.is_depth(out)
        and (not depth.is_depth(out) or depth.depth_unit(source) == depth.depth_unit(out))
        and tuple(source["shape"]) == tuple(out["shape"])
    )


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


def finish(tmp: Path, root: Path, provenance: dict[str, Any]) -> Path:
    """The last step of every write: the provenance (with the quality verdict) and the dataset card
    into the complete dataset in its staging folder `tmp`, then `tmp` renamed to `root` (atomic)."""
    write_provenance(tmp, provenance)
    publish(tmp, root)
    return root


def write_episodes(
    repo_id: str,
    root: str | Path,
    fps: int,
    features: Features,
    episodes: Iterable[Episode],
    *,
    robot_type: str | None,
    sources: list[dict[str, Any]],
    seed: int | None = None,
    files: Mapping[str, Callable[[Path], None]] | None = None,
    **extra: Any,
) -> tuple[int, int]:
    """A stream of episodes (a recorder's, whose number is not known before it ends) into a new
    dataset at `root`: repo id checked before anything is read, written atomically, provenance naming
    the sources and `extra` entries. `files`: the producer's own files in the dataset folder (path
    relative to it -> a function writing that path), published with the dataset or not at all.
    Returns (episodes, frames)."""
    from shiftkit.datasets.hub import validate_repo_id
    from shiftkit.datasets.provenance import make_provenance

    validate_repo_id(repo_id)
    with DatasetWriter(repo_id, root, fps, features, robot_type=robot_type) as writer:
        for episode in episodes:
            writer.add_episode(episode)
        for name, write in (files or {}).items():
            write(writer.tmp / name)
        provenance = make_provenance(
            repo_id=repo_id,
            fps=fps,
            num_episodes=writer.num_episodes,
            num_frames=writer.num_frames,
            sources=sources,
            seed=seed,
            **extra,
        )
        writer.close(provenance=provenance)
    return writer.num_episodes, writer.num_frames
