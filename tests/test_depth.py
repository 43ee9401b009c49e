"""Depth as grey-level `image` features: lerobot's own dataset tools work on a `collect --depth`
dataset, the encoding's error stays within its bound, and float-depth datasets migrate."""

from __future__ import annotations

import json

import numpy as np
import pytest

from shiftkit.pipelines.dataset_check import validate_dataset
from shiftkit.pipelines.depth import DEFAULT_ENCODING, decode_depth, encode_depth
from shiftkit.pipelines.features import DEFAULT_KEYS
from shiftkit.pipelines.lerobot_io import DatasetWriter, open_lerobot_dataset
from shiftkit.pipelines.sources.raw import open_raw_dataset
from tests.helpers import write_raw_as_lerobot

STEP = (DEFAULT_ENCODING["far"] - DEFAULT_ENCODING["near"]) / 255


@pytest.fixture(scope="module")
def collected(tmp_path_factory):
    """`shiftkit collect --cameras front --depth` (2 episodes), raw and as a LeRobot dataset."""
    from shiftkit.pipelines.sources.simulator import CollectConfig, collect

    tmp = tmp_path_factory.mktemp("depth")
    raw, _ = collect(CollectConfig(task="lift", episodes=2, cameras=("front",), depth=True, out=str(tmp / "raw")))
    return raw, write_raw_as_lerobot(raw, "test/depth", tmp / "ds")


def test_depth_is_an_image_feature_within_its_error_bound(collected):
    raw, root = collected
    info = json.loads((root / "meta/info.json").read_text())
    assert info["features"]["observation.depth.front"] == {
        "dtype": "image",
        "shape": [48, 64, 3],
        "names": ["height", "width", "channels"],
    }
    cameras = json.loads((root / "meta/cameras.json").read_text())["cameras"]
    assert cameras["front"]["depth"] == DEFAULT_ENCODING
    metres = np.load(raw / "episode_000000/depth/front.npy")
    episode = next(open_lerobot_dataset(root).iter_episodes())
    decoded = decode_depth(episode.frames["observation.depth.front"], episode.meta["cameras"]["front"]["depth"])
    inside = metres <= DEFAULT_ENCODING["far"]
    assert inside.mean() > 0.5  # the table and objects are in range; the background is not
    assert np.abs(decoded - metres)[inside].max() <= STEP / 2 + 1e-6
    assert np.all(decoded[~inside] == np.float32(DEFAULT_ENCODING["far"]))


def _lerobot_written_twin(root, out):
    """A dataset of the same features, recorded with lerobot's own `add_frame` writer."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    info = json.loads((root / "meta/info.json").read_text())
    features = {k: {**ft, "shape": tuple(ft["shape"])} for k, ft in info["features"].items() if k not in DEFAULT_KEYS}
    ds = LeRobotDataset.create("test/twin", info["fps"], features, root=out, robot_type=info["robot_type"])
    rng = np.random.default_rng(0)
    for _ in range(4):
        frame = {"task": "lift"}
        for key, ft in features.items():
            dtype = np.uint8 if ft["dtype"] == "image" else np.dtype(ft["dtype"])
            frame[key] = (rng.random(ft["shape"]) * (255 if dtype == np.uint8 else 1)).astype(dtype)
        ds.add_frame(frame)
    ds.save_episode()
    ds.finalize()
    return ds.root


def test_lerobot_dataset_tools_accept_depth(collected, tmp_path):
    from lerobot.datasets.aggregate import aggregate_datasets
    from lerobot.datasets.dataset_tools import convert_image_to_video_dataset, delete_episodes, split_dataset
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    _, root = collected
    ds = LeRobotDataset("test/depth", root=root)
    results = {
        "delete": delete_episodes(ds, [0], output_dir=tmp_path / "delete", repo_id="test/delete").root,
        "split": split_dataset(ds, {"a": [0], "b": [1]}, output_dir=tmp_path / "split")["b"].root,
        "video": convert_image_to_video_dataset(ds, tmp_path / "video", repo_id="test/video", num_workers=1).root,
    }
    twin = _lerobot_written_twin(root, tmp_path / "twin")
    aggregate_datasets(["test/depth", "test/twin"], "test/both", roots=[root, twin], aggr_root=tmp_path / "aggregate")
    results["aggregate"] = tmp_path / "aggregate"
    for name, path in results.items():
        loaded = LeRobotDataset(f"test/{name}", root=path, video_backend="pyav")
        assert loaded[len(loaded) - 1]["observation.depth.front"].shape == (3, 48, 64), name
        counts = validate_dataset(path)
        assert counts["frames"] == loaded.meta.total_frames, name


def test_float_depth_datasets_still_load_and_migrate(collected, tmp_path):
    """A dataset with depth as float (H, W, 1) metres (how shiftkit wrote it before) is read as it
    is, and the `depth_image` stage turns it into the image encoding."""
    from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, StageSpec
    from shiftkit.pipelines.runner import run_pipeline
    from shiftkit.pipelines.sources import SourceConfig

    raw, _ = collected
    raw_ds = open_raw_dataset(raw)
    features = raw_ds.features()
    features["observation.depth.front"] = {
        "dtype": "float32",
        "shape": (48, 64, 1),
        "names": ["height", "width", "channels"],
    }
    metres = np.load(raw / "episode_000000/depth/front.npy")
    with DatasetWriter("test/old", tmp_path / "old", raw_ds.fps, features) as writer:
        episode = raw_ds.read_episode(0)
        episode.frames["observation.depth.front"] = metres[..., None]
        writer.add_episode(episode)
    old = next(open_lerobot_dataset(tmp_path / "old").iter_episodes())
    assert old.frames["observation.depth.front"].dtype == np.float32

    config = PipelineConfig(
        sources=[SourceConfig(path=str(tmp_path / "old"))],
        destination=DestinationConfig(root=str(tmp_path / "new")),
        stages=[StageSpec("depth_image", {"far": 2.0})],
    )
    new_root = run_pipeline(config, progress=False)
    new = next(open_lerobot_dataset(new_root).iter_episodes())
    encoding = new.meta["cameras"]["front"]["depth"]
    assert encoding["far"] == 2.0
    decoded = decode_depth(new.frames["observation.depth.front"], encoding)
    inside = metres <= 2.0
    assert np.abs(decoded - metres)[inside].max() <= 2.0 / 255 / 2 + 1e-6
    validate_dataset(new_root)


def test_encoding_clips_and_rounds():
    d = np.array([[-1.0, 0.0, 0.004, 0.006, 1.0, 2.55, 9.0, np.inf]], dtype=np.float32)
    img = encode_depth(d)
    assert img.shape == (1, 8, 3) and (img[..., 0] == img[..., 2]).all()
    assert img[0, :, 0].tolist() == [0, 0, 0, 1, 100, 255, 255, 255]
    assert decode_depth(img)[0, 4] == pytest.approx(1.0)
