"""Where LeRobot datasets live on this machine: the cache folder and local dataset references.

Both the reader (`lerobot_io`) and the hub client (`hub`) resolve local datasets through here, so
neither needs the other for it."""

from __future__ import annotations

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
