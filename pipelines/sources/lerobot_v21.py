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

from shiftkit.pipelines.errors import DatasetError
from shiftkit.pipelines.jsonutil import read_json_file
from shiftkit.pipelines.sources import Importer, ImportSummary
from shiftkit.pipelines.staging import publish, remove_dead_staging, staging_path

LEGACY_FILES = ("meta/info.json", "meta/episodes.jsonl", "meta/tasks.jsonl", "meta/episodes_stats.jsonl")


def _check_source(source: Path) -> dict:
    if not (source / "meta" / "info.json").is_file():
        raise DatasetError(f"{source}: not a LeRobot dataset (meta/info.json missing)")
    info = read_json_file(source / "meta" / "info.json", "not a LeRobot dataset")
    version = info.get("codebase_version")
    if version != "v2.1":
        hint = " (already v3.0: use it as a source directly)" if version == "v3.0" else ""
        raise DatasetError(f"{source}: codebase_version {version!r}, this importer converts v2.1{hint}")
    missing = [f for f in LEGACY_FILES if not (source / f).is_file()]
    if missing:
        raise DatasetError(f"{source}: missing {missing} (a v2.1 dataset has them)")
    if not any((source / "data").glob("*/*.parquet")):
        raise DatasetError(f"{source}: no data/chunk-*/episode_*.parquet files")
    _check_info(source / "meta" / "info.json", info)
    for name, fields in _LINE_FIELDS.items():
        _check_lines(source / "meta" / name, fields)
    return info


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_shape(value: object) -> bool:
    return isinstance(value, list) and all(_is_int(v) and v >= 0 for v in value)


# What lerobot's converter reads from each line of the v2.1 metadata files, and the check it must pass.
_LINE_FIELDS = {
    "episodes.jsonl": {
        "episode_index": (lambda v: _is_int(v) and v >= 0, "a non-negative integer"),
        "tasks": (lambda v: isinstance(v, list) and all(isinstance(t, str) for t in v), "a list of strings"),
        "length": (lambda v: _is_int(v) and v > 0, "a positive integer"),
    },
    "tasks.jsonl": {
        "task_index": (lambda v: _is_int(v) and v >= 0, "a non-negative integer"),
        "task": (lambda v: isinstance(v, str), "a string"),
    },
    "episodes_stats.jsonl": {
        "episode_index": (lambda v: _is_int(v) and v >= 0, "a non-negative integer"),
        "stats": (
            lambda v: isinstance(v, dict) and all(isinstance(s, dict) for s in v.values()),
            "an object of objects",
        ),
    },
}


def _check_info(path: Path, info: dict) -> None:
    """The info.json fields the converter reads, each of the type it needs."""
    fps = info.get("fps")
    if not isinstance(fps, (int, float)) or isinstance(fps, bool) or not fps > 0 or fps != int(fps):
        raise DatasetError(f"{path}: 'fps' must be a positive integer, got {fps!r}")
    for key in ("total_chunks", "total_videos"):
        if not _is_int(info.get(key)) or info[key] < 0:
            raise DatasetError(f"{path}: {key!r} must be a non-negative integer, got {info.get(key)!r}")
    if not isinstance(info.get("video_path", ""), (str, type(None))) or "video_path" not in info:
        raise DatasetError(f"{path}: 'video_path' must be a string or null, got {info.get('video_path')!r}")
    features = info.get("features")
    if not isinstance(features, dict) or not features:
        raise DatasetError(f"{path}: 'features' must be a non-empty object")
    for key, ft in features.items():
        if not isinstance(ft, dict) or not isinstance(ft.get("dtype"), str) or not _is_shape(ft.get("shape")):
            raise DatasetError(f"{path}: features[{key!r}] needs a string 'dtype' and a list of integers 'shape'")


def _check_lines(path: Path, fields: dict) -> None:
    """Every line of a v2.1 `.jsonl` metadata file: a JSON object holding `fields`, each as its check requires."""
    import json

    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError:
        raise DatasetError(f"{path}: not UTF-8 text") from None
    for n, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            item = json.loads(line)
        except json.JSONDecodeError as exc:
            raise DatasetError(f"{path}: line {n}: invalid JSON ({exc.msg})") from None
        if not isinstance(item, dict):
            raise DatasetError(f"{path}: line {n}: expected a JSON object, got {type(item).__name__}")
        for key, (ok, what) in fields.items():
            if not ok(item.get(key)):
                raise DatasetError(f"{path}: line {n}: {key!r} must be {what}, got {item.get(key)!r:.60}")


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
    if dest.is_relative_to(source):
        raise DatasetError(f"destination {dest} lies inside the source dataset; choose a directory outside it")
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
