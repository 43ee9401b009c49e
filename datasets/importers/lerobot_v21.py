"""Import a LeRobot v2.1 dataset (per-episode parquet files, `meta/*.jsonl`) as a v3.0 dataset through
lerobot's own converter (`lerobot.scripts.convert_dataset_v21_to_v30`), into a new directory.

lerobot's `convert_dataset` works in place: it renames the source to `<name>_old` and moves the
result to the source's name. Its steps (`convert_info`, `convert_tasks`, `convert_data`,
`convert_videos`, `convert_episodes_metadata`) only read the old root and write the new one, so
they run here with the source as the old root and a temporary sibling of the destination as the
new one: the source is never renamed or written, and the destination appears only when the
converted dataset loads. Frames, videos, statistics and tasks are exactly what the converter
writes; shiftkit adds its provenance file and dataset card (`importers.convert_import`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from shiftkit.datasets import loaders
from shiftkit.datasets.errors import DatasetError
from shiftkit.datasets.ids import fingerprint
from shiftkit.datasets.importers import Importer, register_importer

LEGACY_FILES = ("meta/info.json", "meta/episodes.jsonl", "meta/tasks.jsonl", "meta/episodes_stats.jsonl")


def _check_source(source: Path) -> dict:
    if not (source / "meta" / "info.json").is_file():
        raise DatasetError(f"{source}: not a LeRobot dataset (meta/info.json missing)")
    info = loaders.load_checked(
        source / "meta" / "info.json", loaders.obj(codebase_version=loaders.opt(loaders.ANY)), "not a LeRobot dataset"
    )
    version = info.get("codebase_version")
    if version != "v2.1":
        hint = " (already v3.0: use it as a source directly)" if version == "v3.0" else ""
        raise DatasetError(f"{source}: codebase_version {version!r}, this importer converts v2.1{hint}")
    missing = [f for f in LEGACY_FILES if not (source / f).is_file()]
    if missing:
        raise DatasetError(f"{source}: missing {missing} (a v2.1 dataset has them)")
    if not any((source / "data").glob("*/*.parquet")):
        raise DatasetError(f"{source}: no data/chunk-*/episode_*.parquet files")
    info = loaders.check_value(info, _INFO, str(source / "meta" / "info.json"))
    for name, line in _LINES.items():
        loaders.load_jsonl(source / "meta" / name, line)
    return info


def _whole_fps(value: object, where: str) -> object:
    # v2.1 writers stored fps as 30 or 30.0; the converter takes either
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0 or value != int(value):
        return loaders.integer(1)(value, where)  # its message
    return value


# What lerobot's converter reads from info.json and from each line of the v2.1 metadata files.
_INFO = loaders.obj(
    fps=_whole_fps,
    total_chunks=loaders.integer(0),
    total_videos=loaders.integer(0),
    video_path=loaders.nullable(loaders.string),
    features=loaders.map_of(loaders.FEATURE, non_empty=True),
)
_LINES = {
    "episodes.jsonl": loaders.obj(
        episode_index=loaders.integer(0), tasks=loaders.list_of(loaders.string), length=loaders.integer(1)
    ),
    "tasks.jsonl": loaders.obj(task_index=loaders.integer(0), task=loaders.string),
    "episodes_stats.jsonl": loaders.obj(
        episode_index=loaders.integer(0), stats=loaders.map_of(loaders.map_of(loaders.ANY))
    ),
}


V21_CONVERTER = "lerobot.scripts.convert_dataset_v21_to_v30"


def convert_v21(source: Path, dest: Path) -> None:
    """lerobot's v2.1 -> v3.0 conversion steps from `source` into a new folder `dest`: its
    `convert_dataset` works in place (renames the source), these steps read `source` only; the
    result must load with lerobot's metadata reader."""
    import importlib

    from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata
    from lerobot.datasets.utils import DEFAULT_DATA_FILE_SIZE_IN_MB, DEFAULT_VIDEO_FILE_SIZE_IN_MB

    converter = importlib.import_module(V21_CONVERTER)
    converter.convert_info(source, dest, DEFAULT_DATA_FILE_SIZE_IN_MB, DEFAULT_VIDEO_FILE_SIZE_IN_MB)
    converter.convert_tasks(source, dest)
    episodes = converter.convert_data(source, dest, DEFAULT_DATA_FILE_SIZE_IN_MB)
    videos = converter.convert_videos(source, dest, DEFAULT_VIDEO_FILE_SIZE_IN_MB)
    converter.convert_episodes_metadata(source, dest, episodes, videos)
    LeRobotDatasetMetadata(dest.name, root=dest)  # loads: info, tasks, episodes, stats


@dataclass
class LeRobotV21Options:
    """Options of the LeRobot v2.1 importer (`shiftkit import lerobot-v2.1 DIR`)."""

    source: str
    """A local LeRobot v2.1 dataset directory (only read)."""


def convert(options: LeRobotV21Options, tmp: Path) -> dict[str, Any]:
    """Convert the v2.1 dataset `options.source` into the new folder `tmp` with lerobot's converter (the
    source is only read); returns its provenance entry."""
    source = Path(options.source).resolve()
    if not source.is_dir():
        raise DatasetError(f"{source}: no such dataset directory")
    _check_source(source)
    entry = {
        "kind": "lerobot-v2.1",
        "path": str(source),
        "fingerprint": fingerprint(source),
        "importer": {"name": "lerobot-v2.1", "converter": V21_CONVERTER},
    }
    try:
        convert_v21(source, tmp)
    except Exception as exc:  # the converter raises ValueError/KeyError/ArrowInvalid/... on malformed input
        detail = " ".join(str(exc).split())[:300]
        raise DatasetError(
            f"{source}: lerobot's v2.1 -> v3.0 converter failed ({type(exc).__name__}: {detail})"
        ) from None
    return entry


IMPORTER = register_importer(
    Importer(
        name="lerobot-v2.1",
        help="LeRobot v2.1 datasets, converted to v3.0 by lerobot's own converter into a new directory",
        Options=LeRobotV21Options,
        inputs=("source",),
        convert=convert,
        report=lambda source: [f"{Path(source['path']).name}: converted"],
    )
)
