"""Import a LeRobot v2.1 dataset (per-episode parquet files, `meta/*.jsonl`) as a v3.0 dataset through
lerobot's own converter (`lerobot.scripts.convert_dataset_v21_to_v30`), into a new directory.

lerobot's `convert_dataset` works in place: it renames the source to `<name>_old` and moves the
result to the source's name. Its steps (`convert_info`, `convert_tasks`, `convert_data`,
`convert_videos`, `convert_episodes_metadata`) only read the old root and write the new one, so
they run here with the source as the old root and a temporary sibling of the destination as the
new one: the source is never renamed or written, and the destination appears only when the
converted dataset loads. Frames, videos, statistics and tasks are exactly what the converter
writes; shiftkit adds its provenance file and dataset card.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from shiftkit.pipelines import loaders
from shiftkit.pipelines.errors import DatasetError
from shiftkit.pipelines.sources import Importer, ImportSummary
from shiftkit.pipelines.staging import check_inputs_and_outputs, publish, remove_dead_staging, staging_path

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


def import_lerobot_v21(source: str | Path, repo_id: str, root: str | Path) -> ImportSummary:
    """Convert the v2.1 dataset at `source` into a new v3.0 dataset at `root` (the source is only read)."""
    from shiftkit.pipelines.hub import validate_repo_id
    from shiftkit.pipelines.lerobot_io import V21_CONVERTER, convert_v21, fingerprint, write_provenance
    from shiftkit.pipelines.provenance import make_provenance

    validate_repo_id(repo_id)
    source, dest = Path(source).resolve(), Path(root).resolve()
    if not source.is_dir():
        raise DatasetError(f"{source}: no such dataset directory")
    _check_source(source)
    if dest.exists():
        raise DatasetError(f"destination already exists: {dest}")
    check_inputs_and_outputs([("source", source)], [("--root", dest)])
    source_fingerprint = fingerprint(source)
    tmp = staging_path(dest)
    try:
        dest.parent.mkdir(parents=True, exist_ok=True)
        remove_dead_staging(dest)
        num_episodes, num_frames, fps = convert_v21(source, tmp)
        write_provenance(
            tmp,
            make_provenance(
                repo_id=repo_id,
                fps=fps,
                num_episodes=num_episodes,
                num_frames=num_frames,
                sources=[{"kind": "lerobot-v2.1", "path": str(source), "fingerprint": source_fingerprint}],
                importer={"name": "lerobot-v2.1", "converter": V21_CONVERTER},
            ),
        )
        publish(tmp, dest)
    except DatasetError:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    except Exception as exc:  # the converter raises ValueError/KeyError/ArrowInvalid/... on malformed input
        shutil.rmtree(tmp, ignore_errors=True)
        detail = " ".join(str(exc).split())[:300]
        raise DatasetError(
            f"{source}: lerobot's v2.1 -> v3.0 converter failed ({type(exc).__name__}: {detail})"
        ) from None
    per_file = [{"file": source.name, "episodes": num_episodes}]
    return ImportSummary(dest, "converted", fps, num_episodes, num_frames, per_file)


def _add_arguments(parser) -> None:
    parser.add_argument("source", metavar="DIR", help="a local LeRobot v2.1 dataset directory (only read)")


IMPORTER = Importer(
    name="lerobot-v2.1",
    help="LeRobot v2.1 datasets, converted to v3.0 by lerobot's own converter into a new directory",
    add_arguments=_add_arguments,
    run=lambda args: import_lerobot_v21(args.source, args.repo_id, args.root),
    report=lambda summary: [f"{f['file']}: {f['episodes']} episodes converted" for f in summary.per_file],
)
