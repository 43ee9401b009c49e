"""Raw episode format v1: round trip, determinism, and one-line errors for broken recordings."""

from __future__ import annotations

import json

import numpy as np
import pytest

from shiftkit.datasets.errors import DatasetError
from shiftkit.datasets.sources.raw import RawDatasetWriter, open_raw_dataset
from tests.helpers import tree_hashes


def arrays(n=6, a=2):
    return {
        "timestamp": np.arange(n) / 10.0,
        "action": np.ones((n, a), dtype=np.float32),
        "state": np.zeros((n, 3), dtype=np.float32),
        "wrench_raw": np.zeros((n, 4), dtype=np.float32),
        "success": np.arange(n) == n - 1,
    }


def write(tmp_path, name="raw", **kw):
    with RawDatasetWriter(tmp_path / name, fps=10, names={"state": ["x", "y", "z"]}) as w:
        w.add_episode(
            arrays(),
            images={"wrist": np.full((6, 4, 5, 3), 7, np.uint8)},
            meta={"task": "push", "outcome": "success", "segments": [{"task": "reach", "start": 0, "end": 2}]},
            **kw,
        )
    return tmp_path / name


def test_round_trip_maps_to_lerobot_features(tmp_path):
    raw = open_raw_dataset(write(tmp_path))
    feats = raw.features()
    assert feats["observation.state"]["names"] == ["x", "y", "z"]
    assert feats["observation.wrench"]["names"] == ["Fx", "Fy", "Fz", "tau_z"]
    assert feats["observation.images.wrist"] == {
        "dtype": "image",
        "shape": (4, 5, 3),
        "names": ["height", "width", "channels"],
    }
    assert feats["next.success"]["dtype"] == "bool"
    ep = raw.read_episode(0)
    assert list(ep.frames["task"]) == ["reach", "reach", "push", "push", "push", "push"]
    assert ep.frames["observation.images.wrist"].shape == (6, 4, 5, 3)
    assert (ep.frames["observation.images.wrist"] == 7).all()
    assert ep.meta["outcome"] == "success" and ep.meta["source_episode_index"] == 0


def test_same_recording_same_bytes(tmp_path):
    assert tree_hashes(write(tmp_path, "a")) == tree_hashes(write(tmp_path, "b"))


def test_writer_rejects_and_leaves_nothing(tmp_path):
    bad = arrays()
    bad["action"] = bad["action"][:4]
    with (
        pytest.raises(DatasetError, match="'action' has 4 frames, 'timestamp' has 6"),
        RawDatasetWriter(tmp_path / "raw", fps=10) as w,
    ):
        w.add_episode(bad, meta={"task": "t"})
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "corrupt, message",
    [
        (
            lambda r: np.save(r / "episode_000000/arrays/action.npy", np.ones((3, 2), np.float32)),
            "'action' has 3 frames",
        ),
        (
            lambda r: np.save(r / "episode_000000/arrays/state.npy", np.full((6, 3), np.nan, np.float32)),
            "'state' contains NaN",
        ),
        (lambda r: (r / "episode_000000/images/wrist/frame_000003.png").unlink(), "5 image files for 6 frames"),
        (lambda r: (r / "episode_000000/meta.json").write_text("{"), "meta.json: invalid JSON"),
        (
            lambda r: np.save(r / "episode_000000/arrays/timestamp.npy", np.array([0, 1, 1, 2, 3, 4.0])),
            "not strictly increasing",
        ),
    ],
)
def test_reader_one_line_errors(tmp_path, corrupt, message):
    root = write(tmp_path)
    corrupt(root)
    with pytest.raises(DatasetError, match=message) as info:
        open_raw_dataset(root).read_episode(0)
    assert "\n" not in str(info.value)


def test_index_errors(tmp_path):
    with pytest.raises(DatasetError, match="not found"):
        open_raw_dataset(tmp_path / "nope")
    root = write(tmp_path)
    index = json.loads((root / "dataset.json").read_text())
    (root / "dataset.json").write_text(json.dumps({**index, "version": 9}))
    with pytest.raises(DatasetError, match="version 9 is not supported"):
        open_raw_dataset(root)
