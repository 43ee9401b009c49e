"""Depth as lerobot 0.6 defines it, end to end.

* Datasets recorded with lerobot's own writer, depth as float32 (m) images, uint16 (mm) images and
  depth video, go through filter + trim + subsample on two workers: the outputs keep lerobot's
  `depth_keys` and the feature's unit and `video.*` keys, their depth equals the input's within
  lerobot's own quantisation error, and lerobot's diffusion policy trains on one.
* `shiftkit collect --cameras front --depth` writes native depth that lerobot's dataset tools
  (delete, split, merge, convert to video, recompute stats) process; their outputs reload and pass
  `shiftkit validate`.
* The `depth_image` stage migrates the 8-bit grey depth older shiftkit versions wrote.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from shiftkit.datasets.check import validate_dataset
from shiftkit.datasets.depth import LEGACY_DEFAULT, VIDEO_DEFAULTS, legacy_grey
from shiftkit.datasets.reader import open_lerobot_dataset
from shiftkit.datasets.sources import SourceConfig
from shiftkit.datasets.writer import DatasetWriter
from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, StageSpec
from shiftkit.pipelines.runner import run_pipeline
from tests.helpers import SMALL_DIFFUSION, lerobot_train_two_steps, tree_hashes

H, W = 48, 64  # lerobot's diffusion backbone needs > 1 pixel after its stride-32 trunk
NAMES = ["height", "width", "channels"]
KINDS = ("float_image", "uint16_image", "video")
STAGES = [
    StageSpec("filter", {"indices": [0, 2, 3]}),
    StageSpec("trim", {"head": 1}),
    StageSpec("subsample", {"every": 2}),
]


def _depth(t: int, e: int) -> np.ndarray:
    """A plane tilting over time, 0.3-2.5 m, with a near object: (H, W, 1) float32 metres."""
    ramp = np.linspace(0.3, 2.5, W, dtype=np.float32)[None, :, None] * np.ones((H, 1, 1), np.float32)
    d = ramp + np.float32(0.02 * t)
    d[8 + e : 20 + e, 16:28] = 0.45
    return d.astype(np.float32)


def _write_with_lerobot(root, kind: str) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    camera = "video" if kind == "video" else "image"
    features = {
        "observation.state": {"dtype": "float32", "shape": (2,), "names": ["t", "e"]},
        "action": {"dtype": "float32", "shape": (2,), "names": ["t", "e"]},
        "observation.images.front": {"dtype": camera, "shape": (H, W, 3), "names": NAMES},
        "observation.depth.front": {
            "dtype": camera,
            "shape": (H, W, 1),
            "names": NAMES,
            "info": {"is_depth_map": True},
        },
    }
    ds = LeRobotDataset.create("test/depth", 10, features, root=root, use_videos=camera == "video")
    for e in range(4):
        for t in range(16):
            d = _depth(t, e)
            ds.add_frame(
                {
                    "observation.state": np.array([t, e], np.float32),
                    "action": np.array([t + 1, e], np.float32),
                    "observation.images.front": np.full((H, W, 3), 8 * t, np.uint8),
                    "observation.depth.front": np.rint(d * 1000).astype(np.uint16) if kind == "uint16_image" else d,
                    "task": "reach",
                }
            )
        ds.save_episode()
    ds.finalize()


def _lerobot_depth(root, unit: str = "m") -> np.ndarray:
    """Every frame's depth as lerobot's own loader returns it, (N, H, W, 1)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset("test/depth", root=root, video_backend="pyav", depth_output_unit=unit)
    return np.stack([ds[i]["observation.depth.front"].numpy() for i in range(len(ds))]).transpose(0, 2, 3, 1)


def _quantisation_step(depth_m: float) -> float:
    """lerobot's 12-bit log quantiser: the width of one code at `depth_m` (m)."""
    lo, hi, shift = VIDEO_DEFAULTS["depth_min"], VIDEO_DEFAULTS["depth_max"], VIDEO_DEFAULTS["shift"]
    return (depth_m + shift) * (np.log(hi + shift) - np.log(lo + shift)) / 4095


@pytest.fixture(scope="module")
def native(tmp_path_factory):
    """Per kind: the lerobot-written source and the pipeline's output (two workers)."""
    out = {}
    for kind in KINDS:
        tmp = tmp_path_factory.mktemp(kind)
        _write_with_lerobot(tmp / "src", kind)
        before = tree_hashes(tmp / "src")
        config = PipelineConfig(
            sources=[SourceConfig(path=str(tmp / "src"))],
            destination=DestinationConfig(root=str(tmp / "out"), repo_id="test/depth"),
            stages=STAGES,
        )
        out[kind] = (tmp / "src", run_pipeline(config, workers=2, progress=False), before)
    return out


@pytest.mark.parametrize("kind", KINDS)
def test_lerobot_depth_survives_a_pipeline(native, kind):
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    src, out, before = native[kind]
    assert tree_hashes(src) == before, "the input is never modified"
    src_meta, out_meta = LeRobotDatasetMetadata("test/depth", root=src), LeRobotDatasetMetadata("test/depth", root=out)
    assert out_meta.depth_keys == src_meta.depth_keys == ["observation.depth.front"]
    # The feature as lerobot wrote it: dtype, unit and (for video) every `video.*` key, the frame
    # rate being the subsampled one.
    expected = src_meta.features["observation.depth.front"]
    if "video.fps" in expected["info"]:
        expected = {**expected, "info": {**expected["info"], "video.fps": out_meta.fps}}
    assert out_meta.fps == src_meta.fps // 2
    assert out_meta.features["observation.depth.front"] == expected
    assert out_meta.total_episodes == 3 and out_meta.total_frames == 3 * 8

    ours = _lerobot_depth(out)
    kept = [i for e in (0, 2, 3) for i in range(e * 16 + 1, e * 16 + 16, 2)]
    source = _lerobot_depth(src)[kept]
    truth = np.stack([_depth(i % 16, i // 16) for i in kept])
    if kind == "video":
        # Re-encoding quantises again: within one code of the source, and of the true depth.
        tolerance = 1.01 * _quantisation_step(float(truth.max()))
        assert np.abs(ours - source).max() <= tolerance
        assert np.abs(ours - truth).max() <= 2 * tolerance
    elif kind == "uint16_image":
        np.testing.assert_array_equal(ours, source)  # mm stay mm: exact
        assert np.abs(ours - truth).max() <= 0.0005 + 1e-6
    else:
        np.testing.assert_array_equal(ours, truth)  # float metres: exact
    validate_dataset(out)
    validate_dataset(src)  # lerobot's own depth, as recorded, is a valid input


def test_lerobot_stats_of_depth_are_in_its_unit(native):
    """Depth statistics are lerobot's: in the stored unit, not scaled to [0, 1]."""
    _, out, _ = native["uint16_image"]
    stats = json.loads((out / "meta/stats.json").read_text())["observation.depth.front"]
    assert 300 < np.asarray(stats["min"]).item() < np.asarray(stats["max"]).item() < 3000  # millimetres


def test_diffusion_trains_on_depth(native, tmp_path):
    """lerobot-train loads the dataset with its depth; lerobot 0.6.1's diffusion policy takes only
    3-channel cameras of one shape, so the policy's inputs are the RGB camera and the state."""
    _, out, _ = native["float_image"]
    inputs = {
        "observation.state": {"type": "STATE", "shape": [2]},
        "observation.images.front": {"type": "VISUAL", "shape": [3, H, W]},
    }
    diffusion = (*SMALL_DIFFUSION, f"--policy.input_features={json.dumps(inputs)}")
    lerobot_train_two_steps("test/depth", out, tmp_path / "train", policy_args=diffusion)


@pytest.fixture(scope="module")
def collected(tmp_path_factory):
    """`shiftkit collect --cameras front --depth` (2 episodes) as a LeRobot dataset."""
    from shiftkit.app.collect import CollectConfig, collect

    tmp = tmp_path_factory.mktemp("collect")
    config = CollectConfig(task="lift", episodes=2, cameras=("front",), depth=True, out=str(tmp / "raw"))
    raw, _ = collect(config)
    run_pipeline(
        PipelineConfig(
            sources=[SourceConfig(path=str(raw))],
            destination=DestinationConfig(root=str(tmp / "ds"), repo_id="test/collected"),
        ),
        workers=1,
        progress=False,
    )
    return raw, tmp / "ds"


def test_collected_depth_is_native_and_exact(collected):
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    raw, root = collected
    meta = LeRobotDatasetMetadata("test/collected", root=root)
    assert meta.depth_keys == ["observation.depth.front"]
    assert meta.features["observation.depth.front"] == {
        "dtype": "image",
        "shape": (48, 64, 1),
        "names": NAMES,
        "info": {"is_depth_map": True, "depth_unit": "m"},
    }
    metres = np.load(raw / "episode_000000/depth/front.npy")
    episode = next(open_lerobot_dataset(root).iter_episodes())
    np.testing.assert_array_equal(episode.frames["observation.depth.front"][..., 0], metres)


def test_lerobot_dataset_tools_accept_depth(collected, tmp_path):
    from lerobot.datasets.dataset_tools import (
        convert_image_to_video_dataset,
        delete_episodes,
        merge_datasets,
        recompute_stats,
        split_dataset,
    )
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    _, root = collected
    before = tree_hashes(root)
    ds = LeRobotDataset("test/collected", root=root)
    split = split_dataset(ds, {"a": [0], "b": [1]}, output_dir=tmp_path / "split")
    results = {
        "delete": delete_episodes(ds, [0], output_dir=tmp_path / "delete", repo_id="test/delete").root,
        "split": split["b"].root,
        "merge": merge_datasets([split["a"], split["b"]], "test/merge", output_dir=tmp_path / "merge").root,
        "video": convert_image_to_video_dataset(ds, tmp_path / "video", repo_id="test/video", num_workers=1).root,
    }
    recomputed = recompute_stats(LeRobotDataset("test/delete", root=results["delete"]))
    assert tree_hashes(root) == before
    for name, out in results.items():
        reloaded = LeRobotDataset(f"test/{name}", root=out, video_backend="pyav")
        assert reloaded.meta.depth_keys == ["observation.depth.front"], name
        assert reloaded[0]["observation.depth.front"].shape == (1, 48, 64), name
        validate_dataset(out)
    assert recomputed.meta.stats["observation.depth.front"]["max"].max() > 0.3  # metres, not [0, 1]


def test_depth_image_migrates_older_grey_depth(collected, tmp_path):
    """A dataset as older shiftkit wrote it (8-bit grey RGB depth, range in meta/cameras.json)
    becomes native depth in metres within the old encoding's half step."""
    from shiftkit.datasets.features import image_feature

    raw, root = collected
    reader = open_lerobot_dataset(root)
    features = dict(reader.features)
    features["observation.depth.front"] = image_feature((48, 64, 3))
    with DatasetWriter("test/old", tmp_path / "old", reader.fps, features) as writer:
        for episode in reader.iter_episodes():
            grey = np.stack([legacy_grey(f) for f in episode.frames["observation.depth.front"]])
            cameras = {**episode.meta.get("cameras", {})}
            cameras["front"] = {**cameras.get("front", {}), "depth": LEGACY_DEFAULT}
            old = episode.with_frames(**{"observation.depth.front": grey})
            old.meta = {**old.meta, "cameras": cameras}
            writer.add_episode(old)
    config = PipelineConfig(
        sources=[SourceConfig(path=str(tmp_path / "old"))],
        destination=DestinationConfig(root=str(tmp_path / "new")),
        stages=[StageSpec("depth_image", {})],
    )
    new = run_pipeline(config, workers=1, progress=False)
    info = json.loads((new / "meta/info.json").read_text())
    assert info["features"]["observation.depth.front"]["shape"] == [48, 64, 1]
    assert info["features"]["observation.depth.front"]["info"] == {"is_depth_map": True, "depth_unit": "m"}
    metres = np.load(raw / "episode_000000/depth/front.npy")
    migrated = next(open_lerobot_dataset(new).iter_episodes()).frames["observation.depth.front"][..., 0]
    inside = metres <= LEGACY_DEFAULT["far"]
    assert inside.mean() > 0.5
    assert np.abs(migrated - metres)[inside].max() <= (LEGACY_DEFAULT["far"] / 255) / 2 + 1e-6
    assert "depth" not in json.loads((new / "meta/cameras.json").read_text())["cameras"].get("front", {})
