"""Camera metadata lives in meta/cameras.json (per camera, per episode where it varies), never in
lerobot's feature dicts, so shiftkit datasets merge with datasets lerobot's own writer recorded."""

from __future__ import annotations

import json

import numpy as np
import pytest

from shiftkit.app.cli import main
from shiftkit.datasets.camera_meta import episode_cameras, factor_cameras
from shiftkit.datasets.errors import DatasetError
from shiftkit.datasets.reader import open_lerobot_dataset
from shiftkit.datasets.sources.raw import RawDatasetWriter, open_raw_dataset
from tests.helpers import write_raw_as_lerobot

INTRINSICS = {"fx": 57.9, "fy": 57.9, "cx": 31.5, "cy": 23.5, "width": 64, "height": 48}
ROTATION = [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]
STATE_NAMES = ["x", "y"]


def _extrinsics(e: int) -> dict:
    return {"frame": "base", "position": [0.5 + 0.01 * e, 0.0, 0.4], "rotation": ROTATION}


def _write_raw(path, episodes=3, length=6, bad_meta=None):
    """Raw episodes: a fixed `front` camera whose pose moves per episode (like multiview), a wrist
    camera given as a bare intrinsics dict (what collect wrote before meta/cameras.json)."""
    rng = np.random.default_rng(0)
    info = {"cameras": {"front": {"intrinsics": INTRINSICS}, "wrist": dict(INTRINSICS, fx=40.0, fy=40.0)}}
    with RawDatasetWriter(path, fps=10, robot="point", names={"state": STATE_NAMES}, info=info) as w:
        for e in range(episodes):
            cams = {"front": {"extrinsics": _extrinsics(e), "base_pose": {"x": 0.1 * e, "y": 0.0, "yaw": 0.2}}}
            w.add_episode(
                {
                    "timestamp": np.arange(length) / 10.0,
                    "state": rng.normal(size=(length, 2)).astype(np.float32),
                    "action": rng.normal(size=(length, 2)).astype(np.float32),
                },
                images={
                    "front": rng.integers(0, 255, (length, 48, 64, 3), dtype=np.uint8),
                    "wrist": rng.integers(0, 255, (length, 48, 64, 3), dtype=np.uint8),
                },
                meta={"task": "reach", "cameras": bad_meta if bad_meta is not None else cams},
            )
    return path


def test_factoring_keeps_constant_entries_once_and_round_trips():
    per_episode = {
        0: {"front": {"intrinsics": INTRINSICS, "extrinsics": _extrinsics(0)}},
        1: {"front": {"intrinsics": INTRINSICS, "extrinsics": _extrinsics(1)}, "side": {"intrinsics": INTRINSICS}},
    }
    doc = factor_cameras(per_episode)
    assert doc["cameras"] == {"front": {"intrinsics": INTRINSICS}}  # `side` is missing from episode 0
    assert set(doc["episodes"]) == {"0", "1"}
    assert doc["episodes"]["1"]["side"] == {"intrinsics": INTRINSICS}
    for i, cams in per_episode.items():
        assert episode_cameras(doc, i) == cams


def test_lerobot_dataset_carries_cameras_outside_the_features(tmp_path, capsys):
    raw = _write_raw(tmp_path / "raw")
    root = write_raw_as_lerobot(raw, "test/cams", tmp_path / "ds")
    info = json.loads((root / "meta/info.json").read_text())
    for cam in ("front", "wrist"):
        assert info["features"][f"observation.images.{cam}"] == {
            "dtype": "image",
            "shape": [48, 64, 3],
            "names": ["height", "width", "channels"],
        }
    doc = json.loads((root / "meta/cameras.json").read_text())
    assert doc["format"] == "shiftkit-cameras" and doc["version"] == 1
    assert doc["cameras"]["front"] == {"intrinsics": INTRINSICS}
    assert doc["cameras"]["wrist"] == {"intrinsics": dict(INTRINSICS, fx=40.0, fy=40.0)}
    assert doc["episodes"]["1"]["front"]["base_pose"] == {"x": 0.1, "y": 0.0, "yaw": 0.2}
    assert doc["episodes"]["2"]["front"]["extrinsics"] == _extrinsics(2)
    # Not twice: the episodes table holds the other metadata only.
    assert "cameras" not in json.loads(open_lerobot_dataset(root).episodes["shiftkit/meta"][0])

    episodes = list(open_lerobot_dataset(root).iter_episodes())
    assert [ep.meta["cameras"]["front"]["extrinsics"] for ep in episodes] == [_extrinsics(e) for e in range(3)]
    assert episodes[0].meta["cameras"]["wrist"]["intrinsics"]["fx"] == 40.0

    prov = json.loads((root / "meta/shiftkit_provenance.json").read_text())
    assert prov["cameras"]["file"] == "meta/cameras.json"
    assert prov["cameras"]["per_episode"] == {"front": ["base_pose", "extrinsics"]}

    assert main(["info", str(root)]) == 0
    out = capsys.readouterr().out
    assert "front: 64x48 fx 57.9" in out
    assert "per episode: base_pose, extrinsics (3/3 episodes)" in out


def test_stages_carry_each_episodes_cameras_to_its_new_index(tmp_path):
    from shiftkit.datasets.sources import SourceConfig
    from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, StageSpec
    from shiftkit.pipelines.runner import run_pipeline

    src = write_raw_as_lerobot(_write_raw(tmp_path / "raw"), "test/cams", tmp_path / "ds")
    config = PipelineConfig(
        sources=[SourceConfig(path=str(src))],
        destination=DestinationConfig(root=str(tmp_path / "out")),
        stages=[StageSpec("filter", {"indices": [1, 2]})],
    )
    out = run_pipeline(config, progress=False)
    doc = json.loads((out / "meta/cameras.json").read_text())
    assert doc["episodes"]["0"]["front"]["extrinsics"] == _extrinsics(1)
    assert doc["episodes"]["1"]["front"]["extrinsics"] == _extrinsics(2)


def test_sharded_executor_keeps_the_cameras(tmp_path):
    """The datatrove executor's workers transform shards of episodes: the dataset keeps every
    episode's cameras, indexed by its place in the whole dataset."""
    from shiftkit.datasets.sources import SourceConfig
    from shiftkit.pipelines.config import DestinationConfig, PipelineConfig
    from shiftkit.pipelines.runner import run_pipeline

    raw = _write_raw(tmp_path / "raw")
    config = PipelineConfig(
        sources=[SourceConfig(path=str(raw))], destination=DestinationConfig(root=str(tmp_path / "out"))
    )
    out = run_pipeline(config, executor="datatrove-local", executor_options={"shard_episodes": 1}, progress=False)
    episodes = list(open_lerobot_dataset(out).iter_episodes())
    assert [ep.meta["cameras"]["front"]["extrinsics"] for ep in episodes] == [_extrinsics(e) for e in range(3)]
    prov = json.loads((out / "meta/shiftkit_provenance.json").read_text())
    assert prov["cameras"]["per_episode"] == {"front": ["base_pose", "extrinsics"]}


def test_aggregate_datasets_merges_shiftkit_with_lerobot_written(tmp_path):
    from lerobot.datasets.aggregate import aggregate_datasets
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ours = write_raw_as_lerobot(_write_raw(tmp_path / "raw"), "test/ours", tmp_path / "ours")
    camera = {"dtype": "image", "shape": (48, 64, 3), "names": ["height", "width", "channels"]}
    features = {  # what a user declares for lerobot's own recorder
        "action": {"dtype": "float32", "shape": (2,), "names": ["action_0", "action_1"]},
        "observation.state": {"dtype": "float32", "shape": (2,), "names": STATE_NAMES},
        "observation.images.front": camera,
        "observation.images.wrist": camera,
    }
    theirs = LeRobotDataset.create("test/theirs", 10, features, root=tmp_path / "theirs", robot_type="point")
    rng = np.random.default_rng(1)
    for _ in range(2):
        for _ in range(5):
            theirs.add_frame(
                {
                    "observation.state": rng.normal(size=2).astype(np.float32),
                    "action": rng.normal(size=2).astype(np.float32),
                    "observation.images.front": rng.integers(0, 255, (48, 64, 3), dtype=np.uint8),
                    "observation.images.wrist": rng.integers(0, 255, (48, 64, 3), dtype=np.uint8),
                    "task": "reach",
                }
            )
        theirs.save_episode()
    theirs.finalize()

    aggregate_datasets(
        ["test/ours", "test/theirs"], "test/both", roots=[ours, theirs.root], aggr_root=tmp_path / "both"
    )
    both = LeRobotDataset("test/both", root=tmp_path / "both")
    assert both.meta.total_episodes == 5 and both.meta.total_frames == 3 * 6 + 2 * 5
    assert both[0]["observation.images.front"].shape == (3, 48, 64)


@pytest.mark.parametrize(
    "bad, message",
    [
        ({"front": {"extrinsics": {"frame": "camera", "position": [0, 0, 0], "rotation": ROTATION}}}, "extrinsics"),
        ({"front": {"intrinsics": {"fx": 1.0}}}, "intrinsics lacks"),
        (["front"], "must map camera names"),
    ],
)
def test_bad_camera_metadata_is_a_one_line_error(tmp_path, bad, message):
    with pytest.raises(DatasetError, match=message):
        _write_raw(tmp_path / "raw", episodes=1, bad_meta=bad)
    assert not (tmp_path / "raw").exists()


def test_legacy_feature_info_intrinsics_still_read(tmp_path):
    """Datasets written before meta/cameras.json kept intrinsics in the image feature's `info`."""
    root = write_raw_as_lerobot(_write_raw(tmp_path / "raw", episodes=1), "test/old", tmp_path / "ds")
    info_path = root / "meta/info.json"
    info = json.loads(info_path.read_text())
    info["features"]["observation.images.front"]["info"] = INTRINSICS
    info_path.write_text(json.dumps(info))
    (root / "meta/cameras.json").unlink()
    episode = next(open_lerobot_dataset(root).iter_episodes())
    assert episode.meta["cameras"] == {"front": {"intrinsics": INTRINSICS}}
    assert open_raw_dataset(tmp_path / "raw").read_episode(0).meta["cameras"]["wrist"]["intrinsics"]["fx"] == 40.0
