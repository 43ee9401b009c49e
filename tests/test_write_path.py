"""One write path: no module outside `shiftkit.datasets` writes dataset files (parquet, info.json and
the other metadata, videos), and the dataset writer is entered only by the engine's writer step and
the recorders listed here. Checked on the code itself (its syntax tree), so a new writer anywhere
else fails here by name; a planted one shows the check catches each kind."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("pipelines", "transforms", "policies", "envs", "cards", "app")  # every package but datasets/

# Calls that write a dataset's files: parquet (pyarrow, pandas), lerobot's writers of data, metadata and
# videos, shiftkit's own encoders and its provenance writer (all of them live in shiftkit.datasets).
FILE_WRITERS = {
    "write_table",
    "ParquetWriter",
    "to_parquet",
    "write_info",
    "write_stats",
    "write_tasks",
    "write_json",
    "add_frame",
    "save_episode",
    "encode_video_frames",
    "encode_frames",
    "write_provenance",
    "write_cameras_file",
}
# `X.create(...)` of lerobot's dataset classes makes a dataset folder
CREATORS = {"LeRobotDataset", "LeRobotDatasetMetadata"}
# The entry points of the one writer (`shiftkit.datasets.writer`)
WRITER_ENTRIES = {"DatasetWriter", "write_episodes"}
# Who enters the writer: the engine's writer step (every pipeline, so every import) opens it; the
# recorders, whose episodes come as a stream of unknown length (`collect`, FIRE's aggregate and its
# DAgger recorder), hand their stream to `write_episodes`, which records the provenance too.
WRITER_USERS = {
    "DatasetWriter": {"pipelines/assembly.py"},
    "write_episodes": {"app/collect.py", "policies/fire/aggregate.py", "policies/fire/dagger_recording.py"},
}
# A video that is no dataset file: an evaluation's rollout video in a run folder.
OTHER_VIDEOS = {"policies/evaluation.py"}


def _name(node: ast.AST) -> str | None:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    return None


def writes(source: str) -> list[str]:
    """What a module's code writes of a dataset, as `kind name` strings (empty: nothing)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Call):
            continue
        name = _name(node.func)
        if name in FILE_WRITERS:
            found.append(f"file {name}")
        elif name in WRITER_ENTRIES:
            found.append(f"writer {name}")
        elif name == "create" and isinstance(node.func, ast.Attribute) and _name(node.func.value) in CREATORS:
            found.append(f"file {_name(node.func.value)}.create")
        elif (
            name == "open"
            and isinstance(node.func, ast.Attribute)
            and _name(node.func.value) == "av"
            and any(
                isinstance(a, ast.Constant) and str(a.value).startswith("w")
                for a in [*node.args[1:], *(k.value for k in node.keywords if k.arg == "mode")]
            )
        ):
            found.append("video av.open")
    return found


def _modules() -> dict[str, str]:
    return {
        path.relative_to(REPO).as_posix(): path.read_text()
        for package in PACKAGES
        for path in sorted((REPO / package).rglob("*.py"))
    }


def test_no_module_outside_the_dataset_layer_writes_dataset_files():
    allowed = {
        **{f"writer {entry}": users for entry, users in WRITER_USERS.items()},
        "video av.open": OTHER_VIDEOS,
    }
    wrong = {}
    for path, source in _modules().items():
        bad = [w for w in writes(source) if path not in allowed.get(w, set())]
        if bad:
            wrong[path] = bad
    assert not wrong, f"dataset files written outside shiftkit.datasets (write through it): {wrong}"


def test_the_exceptions_are_still_needed():
    """Each listed exception still does what it is listed for (a stale entry would hide a new writer)."""
    modules = _modules()
    for entry, users in WRITER_USERS.items():
        for path in users:
            assert f"writer {entry}" in writes(modules[path]), path
    for path in OTHER_VIDEOS:
        assert "video av.open" in writes(modules[path]), path


@pytest.mark.parametrize(
    ("code", "kind"),
    [
        ("import pyarrow.parquet as pq\npq.write_table(table, 'meta/episodes.parquet')", "file write_table"),
        ("frame.to_parquet('data/chunk-000/file-000.parquet')", "file to_parquet"),
        ("from lerobot.datasets.io_utils import write_info\nwrite_info(info, root)", "file write_info"),
        ("ds = LeRobotDataset.create('a/b', 10, features)\nds.add_frame(f)\nds.save_episode()", "file add_frame"),
        ("with av.open(path, mode='w') as out:\n    pass", "video av.open"),
        (
            "from shiftkit.datasets.writer import DatasetWriter\nDatasetWriter('a/b', root, 10, f)",
            "writer DatasetWriter",
        ),
    ],
)
def test_the_check_finds_each_kind_of_writer(code, kind):
    assert kind in writes(code)
