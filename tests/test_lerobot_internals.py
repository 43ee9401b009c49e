"""The lerobot private names shiftkit relies on exist with the signatures it calls, and no module
but `datasets/writer.py` uses them: when lerobot moves one, this fails by name, not deep
inside a pipeline run."""

from __future__ import annotations

import inspect
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# name -> (owner, parameters shiftkit passes)
PRIVATE = {
    "_save_episode_metadata": ("lerobot.datasets.dataset_metadata.LeRobotDatasetMetadata", ["episode_dict"]),
    "_save_episode_video": (
        "lerobot.datasets.dataset_writer.DatasetWriter",
        ["video_key", "episode_index", "temp_path"],
    ),
}


def _owner(path: str):
    import importlib

    module, cls = path.rsplit(".", 1)
    return getattr(importlib.import_module(module), cls)


@pytest.mark.parametrize("name", sorted(PRIVATE))
def test_private_methods_exist_with_the_parameters_shiftkit_passes(name):
    owner, params = PRIVATE[name]
    method = getattr(_owner(owner), name, None)
    assert method is not None, f"lerobot moved {owner}.{name}: update datasets/writer.py"
    assert params == [p for p in inspect.signature(method).parameters if p != "self"][: len(params)]


def test_metadata_buffer(tmp_path):
    from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata

    features = {"action": {"dtype": "float32", "shape": (1,), "names": ["a"]}}
    meta = LeRobotDatasetMetadata.create("test/internals", 10, features, root=tmp_path / "ds", use_videos=False)
    assert isinstance(meta._metadata_buffer, list), "lerobot renamed LeRobotDatasetMetadata._metadata_buffer"


def test_only_the_io_module_uses_lerobot_private_names():
    """No other shiftkit module touches lerobot's dataset internals (names in PRIVATE, or a private
    name imported from lerobot)."""
    pattern = re.compile(
        r"\._save_episode_metadata|\._save_episode_video|\._metadata_buffer|\._close_writer|from lerobot[\w.]* import _"
    )
    users = set()
    for package in ("datasets", "pipelines", "transforms", "policies", "envs", "cards", "app"):
        for path in (REPO / package).rglob("*.py"):
            if pattern.search(path.read_text()):
                users.add(path.relative_to(REPO).as_posix())
    assert users == {"datasets/writer.py"}
