"""The LeRobot writer/reader: same content as lerobot's own writer, atomic, streaming round trip."""

from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq
import pytest

from shiftkit import datasets
from shiftkit.datasets.episode import META_COLUMN, Episode
from shiftkit.datasets.errors import DatasetError
from shiftkit.datasets.reader import open_lerobot_dataset
from shiftkit.datasets.writer import DatasetWriter

FEATURES = {
    "observation.state": {"dtype": "float32", "shape": (3,), "names": ["a", "b", "c"]},
    "action": {"dtype": "float32", "shape": (2,), "names": ["u", "v"]},
    "next.success": {"dtype": "bool", "shape": (1,), "names": None},
    "observation.images.cam": {"dtype": "image", "shape": (6, 8, 3), "names": ["height", "width", "channels"]},
}


# Dtypes and shapes FEATURES lacks, for the content-identity test (Arrow built from numpy buffers
# for scalars and vectors of every numeric type; datasets' encoding for n-d arrays).
MORE_FEATURES = {
    "observation.effort": {"dtype": "float64", "shape": (1,), "names": None},
    "observation.counts": {"dtype": "int32", "shape": (4,), "names": ["a", "b", "c", "d"]},
    "observation.flags": {"dtype": "bool", "shape": (2,), "names": ["x", "y"]},
    "observation.grid": {"dtype": "float32", "shape": (2, 3), "names": None},
}


def with_more_features(episodes: list[Episode], seed: int = 1) -> list[Episode]:
    rng = np.random.default_rng(seed)
    out = []
    for ep in episodes:
        n = len(ep)
        extra = {
            "observation.effort": rng.normal(size=(n, 1)),
            "observation.counts": rng.integers(-3, 3, size=(n, 4)).astype(np.int32),
            "observation.flags": rng.integers(0, 2, size=(n, 2)).astype(bool),
            "observation.grid": rng.normal(size=(n, 2, 3)).astype(np.float32),
        }
        out.append(Episode({**ep.frames, **extra}, dict(ep.meta)))
    return out


def make_episodes(n_eps: int = 3, seed: int = 0) -> list[Episode]:
    rng = np.random.default_rng(seed)
    eps = []
    for e in range(n_eps):
        n = 5 + e
        eps.append(
            Episode(
                {
                    "observation.state": rng.normal(size=(n, 3)).astype(np.float32),
                    "action": rng.normal(size=(n, 2)).astype(np.float32),
                    "next.success": (np.arange(n) == n - 1).reshape(n, 1),
                    "observation.images.cam": rng.integers(0, 255, size=(n, 6, 8, 3), dtype=np.uint8),
                    "timestamp": np.arange(n) / 10,
                    "task": np.array(["pick" if e % 2 == 0 else "place"] * n),
                },
                {"outcome": "success"},
            )
        )
    return eps


def write_with_lerobot(root, episodes, features=FEATURES):
    """The reference: lerobot's high-level add_frame/save_episode loop (timestamps = frame_index / fps)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset.create("test/ref", 10, dict(features), root=root, use_videos=False)
    for ep in episodes:
        for t in range(len(ep)):
            frame = {k: ep.frames[k][t] for k in features}
            frame["task"] = str(ep.frames["task"][t])
            ds.add_frame(frame)
        ds.save_episode()
    ds.finalize()


@pytest.mark.parametrize("more", [False, True], ids=["features", "more-dtypes"])
def test_content_identical_to_lerobot_writer(tmp_path, more):
    features = {**FEATURES, **MORE_FEATURES} if more else FEATURES
    episodes = with_more_features(make_episodes()) if more else make_episodes()
    write_with_lerobot(tmp_path / "ref", episodes, features)
    with DatasetWriter("test/ref", tmp_path / "ours", 10, features) as w:
        for ep in episodes:
            w.add_episode(ep)
    ref, ours = tmp_path / "ref", tmp_path / "ours"
    data_ref = pq.read_table(ref / "data/chunk-000/file-000.parquet")
    data_ours = pq.read_table(ours / "data/chunk-000/file-000.parquet")
    assert data_ours.schema == data_ref.schema
    # The HF feature metadata must match; lerobot's extra `fingerprint` is a hash of its
    # datasets.map cache step (embed_images), not of content.
    hf_ref = json.loads(data_ref.schema.metadata[b"huggingface"])
    hf_ref.pop("fingerprint", None)
    assert json.loads(data_ours.schema.metadata[b"huggingface"]) == hf_ref
    assert data_ours.equals(data_ref)
    assert json.loads((ours / "meta/info.json").read_text()) == json.loads((ref / "meta/info.json").read_text())
    stats = json.loads((ours / "meta/stats.json").read_text())
    assert stats == json.loads((ref / "meta/stats.json").read_text())
    quantiles = {"q01", "q10", "q50", "q90", "q99"}
    assert all(quantiles <= set(stats[key]) for key in [*features, "index", "timestamp"])  # quantiles compared too
    assert pq.read_table(ours / "meta/tasks.parquet").equals(pq.read_table(ref / "meta/tasks.parquet"))
    ep_ref = pq.read_table(ref / "meta/episodes/chunk-000/file-000.parquet")
    ep_ours = pq.read_table(ours / "meta/episodes/chunk-000/file-000.parquet").drop_columns([META_COLUMN])
    assert ep_ours.equals(ep_ref)  # per-episode statistics, quantile columns included
    assert {f"stats/{key}/q50" for key in features} <= set(ep_ours.column_names)


def test_lerobot_loads_and_reader_round_trips(tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    episodes = make_episodes()
    with DatasetWriter("test/rt", tmp_path / "ds", 10, FEATURES) as w:
        for ep in episodes:
            w.add_episode(ep)
    ds = LeRobotDataset("test/rt", root=tmp_path / "ds")
    assert ds.num_episodes == 3 and len(ds) == 5 + 6 + 7
    assert ds[5]["task"] == "place"
    reader = open_lerobot_dataset(tmp_path / "ds")
    for original, back in zip(episodes, reader.iter_episodes(), strict=True):
        for key in FEATURES:
            np.testing.assert_array_equal(back.frames[key], original.frames[key])
        assert list(back.frames["task"]) == list(original.frames["task"])
        assert back.meta["outcome"] == "success"
    # Any subset, in any order: each read holds just the row groups of the episodes it serves.
    for order in ([2, 0, 1], [1], [2, 2]):
        for i, back in zip(order, reader.iter_episodes(order), strict=True):
            assert back.meta["source_episode_index"] == i
            np.testing.assert_array_equal(back.frames["action"], episodes[i].frames["action"])
    # Files lerobot wrote itself read back the same.
    write_with_lerobot(tmp_path / "ref", episodes)
    for i, back in zip([0, 2, 1], open_lerobot_dataset(tmp_path / "ref").iter_episodes([0, 2, 1]), strict=True):
        for key in FEATURES:
            np.testing.assert_array_equal(back.frames[key], episodes[i].frames[key])


def test_failed_write_leaves_nothing(tmp_path):
    bad = make_episodes(1)[0]
    bad.frames["action"][2, 1] = np.nan
    with (
        pytest.raises(DatasetError, match="'action' has NaN"),
        DatasetWriter("test/x", tmp_path / "ds", 10, FEATURES) as w,
    ):
        w.add_episode(make_episodes(1)[0])
        w.add_episode(bad)
    assert list(tmp_path.iterdir()) == []


def test_destination_exists_and_schema_mismatch(tmp_path):
    (tmp_path / "ds").mkdir()
    with pytest.raises(DatasetError, match="already exists"):
        DatasetWriter("test/x", tmp_path / "ds", 10, FEATURES)
    ep = make_episodes(1)[0]
    ep.frames["observation.state"] = ep.frames["observation.state"][:, :2]
    with (
        pytest.raises(DatasetError, match="per-frame shape"),
        DatasetWriter("test/x", tmp_path / "ds2", 10, FEATURES) as w,
    ):
        w.add_episode(ep)
    assert not (tmp_path / "ds2").exists()


def test_open_a_dataset_by_id_in_cache(tmp_path, monkeypatch):
    """`datasets.open(ref)`: the one handle (ID, folder, fingerprint, features, provenance, episodes)."""
    monkeypatch.setenv("HF_LEROBOT_HOME", str(tmp_path / "home"))
    episodes = make_episodes(2)
    with DatasetWriter("org/name", tmp_path / "home" / "org" / "name", 10, FEATURES) as w:
        for ep in episodes:
            w.add_episode(ep)
        w.close(provenance={"sources": [], "stages": [], "output": {"repo_id": "org/name"}})
    dataset = datasets.open("org/name")
    assert (dataset.repo_id, dataset.root) == ("org/name", tmp_path / "home" / "org" / "name")
    assert len(dataset.fingerprint) == 16 and dataset.fps == 10 and dataset.num_episodes == 2
    assert {k: (ft["dtype"], tuple(ft["shape"])) for k, ft in dataset.features.items()} == {
        k: (ft["dtype"], ft["shape"]) for k, ft in FEATURES.items()
    }
    assert dataset.provenance["output"] == {"repo_id": "org/name"} and dataset.provenance["quality"]["episodes"] == 2
    assert dataset.provenance is dataset.provenance, "parsed once"
    read = list(dataset.iter_episodes([1, 0]))  # streamed, in the order asked
    np.testing.assert_array_equal(read[0].frames["action"], episodes[1].frames["action"])
    assert [ep.meta["source_episode_index"] for ep in read] == [1, 0]
    by_path = datasets.open(tmp_path / "home" / "org" / "name")
    assert (by_path.repo_id, by_path.fingerprint) == ("name", dataset.fingerprint)
    with pytest.raises(DatasetError, match="not found"):
        datasets.open("not a valid id")
