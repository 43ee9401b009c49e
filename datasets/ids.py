"""Dataset IDs and what names a dataset: where LeRobot datasets live on this machine (the cache
folder, local references) and a dataset's content fingerprint.

`shiftkit.datasets.open` and the hub client (`hub`) resolve local datasets through here, so neither
needs the other for it."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path


def lerobot_home() -> Path:
    """`$HF_LEROBOT_HOME`, where local dataset IDs live (lerobot's default: ~/.cache/huggingface/lerobot)."""
    return Path(os.environ.get("HF_LEROBOT_HOME", Path.home() / ".cache" / "huggingface" / "lerobot")).expanduser()


def find_local_dataset(ref: str | Path) -> Path | None:
    """The dataset directory `ref` names locally: the directory itself, or `$HF_LEROBOT_HOME/<ref>`."""
    for path in (Path(ref).expanduser(), lerobot_home() / str(ref)):
        if (path / "meta" / "info.json").is_file():
            return path
    return None


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


def not_a_dataset(path: Path) -> str:
    """Why `path` is not a LeRobot dataset, in words a user can act on."""
    if (path / "dataset.json").is_file():
        return f"{path} is a raw episode folder, not a LeRobot dataset: convert it with `shiftkit run` first"
    if path.is_dir():
        return f"{path} is not a LeRobot dataset: {path / 'meta' / 'info.json'} is missing"
    if path.exists():
        return f"{path} is a file, not a LeRobot dataset folder"
    return f"dataset not found: {path} (neither a dataset directory nor an ORG/NAME id)"
