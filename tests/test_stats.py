"""shiftkit's episode statistics equal lerobot 0.6.1's, value for value and dtype for dtype: every
reference here is computed by lerobot's own `compute_stats` functions (camera features from the
PNG / TIFF frames lerobot's image writer stores)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from lerobot.datasets import compute_stats as lerobot_stats
from lerobot.datasets.image_writer import write_image

from shiftkit.datasets.stats import (
    NUM_BINS,
    QUANTILE_KEYS,
    QUANTILES,
    RunningStats,
    depth_stats,
    feature_stats,
    image_stats,
    numeric_stats,
)


def assert_same(ours: dict, ref: dict) -> None:
    assert list(ours) == list(ref)  # key order fixes the episodes-parquet column order
    for key in ref:
        assert ours[key].dtype == ref[key].dtype, key
        assert ours[key].shape == ref[key].shape, key
        np.testing.assert_array_equal(ours[key], ref[key], err_msg=key)
        if ref[key].dtype.kind == "f":
            np.testing.assert_array_equal(np.signbit(ours[key]), np.signbit(ref[key]), err_msg=key)


def lerobot_feature_stats(data: np.ndarray) -> dict:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return lerobot_stats.get_feature_stats(data, axis=0, keepdims=data.ndim == 1)


def lerobot_image_stats(frames: np.ndarray) -> dict:
    """lerobot's `sample_images` + `get_feature_stats` path for RGB, on frames held in memory
    (any channel count; `lerobot_camera_stats` goes through files)."""
    sampled = np.stack(
        [
            lerobot_stats.auto_downsample_height_width(frames[i].transpose(2, 0, 1))
            for i in lerobot_stats.sample_indices(len(frames))
        ]
    )
    stats = lerobot_stats.get_feature_stats(sampled, axis=(0, 2, 3), keepdims=True)
    return {k: v if k == "count" else np.squeeze(v / 255.0, axis=0) for k, v in stats.items()}


def lerobot_camera_stats(frames: np.ndarray, directory, depth_unit: str | None = None, dtype: str = "image") -> dict:
    """lerobot's `compute_episode_stats` of one camera feature: `frames` (T, H, W, C) written as its
    writer does (PNG for RGB, raw TIFF for a depth map, `write_image`) and read back by lerobot."""
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, frame in enumerate(frames):
        path = directory / f"frame-{i:06d}.{'png' if depth_unit is None else 'tiff'}"
        write_image(frame, path)
        paths.append(str(path))
    info = {} if depth_unit is None else {"is_depth_map": True, "depth_unit": depth_unit}
    features = {"cam": {"dtype": dtype, "shape": frames.shape[1:], "info": info}}
    return lerobot_stats.compute_episode_stats({"cam": paths}, features)["cam"]


def depth_frames(n: int, height: int, width: int, unit: str, rng: np.random.Generator) -> np.ndarray:
    """A depth camera's frames: a tilted plane 0.3-2.5 m away, an object in front moving, sensor
    noise and a few invalid (zero) pixels; float32 metres or uint16 millimetres, (n, H, W, 1)."""
    rows, cols = np.mgrid[0:height, 0:width]
    plane = 2.5 - 1.6 * rows / max(height - 1, 1)
    out = np.empty((n, height, width), np.float32)
    for t in range(n):
        d = plane + rng.normal(0, 0.004, size=plane.shape)
        cx, cy = width * (0.3 + 0.4 * t / max(n, 1)), height / 2
        d = np.where((cols - cx) ** 2 + (rows - cy) ** 2 < (min(height, width) / 4) ** 2, 0.3 + 0.2 * rows / height, d)
        d[rng.random(d.shape) < 0.01] = 0.0  # no return
        out[t] = np.clip(d, 0.0, 2.5)
    if unit == "mm":
        return np.round(out * 1000).astype(np.uint16)[..., None]
    return out[..., None]


def test_constants_are_lerobots():
    assert list(QUANTILES) == lerobot_stats.DEFAULT_QUANTILES
    assert lerobot_stats.RunningQuantileStats()._num_quantile_bins == NUM_BINS
    assert list(QUANTILE_KEYS) == lerobot_stats.RunningQuantileStats()._quantile_keys


def _cases(n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    return {
        "float32 vector": rng.normal(size=(n, 8)).astype(np.float32),
        "float64 scalar": rng.normal(size=n),
        "int64 few values": rng.integers(-5, 5, size=(n, 3)),
        "bool column": (np.arange(n) >= n - 2).reshape(n, 1),
        "bool 1-D": np.arange(n) >= n - 2,
        "constant float32": np.full((n, 2), 0.3, np.float32),
        "constant int64": np.full(n, 7, np.int64),
        "index": np.arange(n, dtype=np.int64),
        "negative zeros": np.full(n, -0.0),
        "negative zeros 2-D": np.full((n, 2), -0.0, np.float32),
        "ties float32": rng.integers(0, 3, size=(n, 4)).astype(np.float32),
        "3-D": rng.normal(size=(n, 2, 3)).astype(np.float32),
        "tiny range": (rng.normal(size=(n, 3)) * 1e-30).astype(np.float32),
        "timestamps": np.arange(n) / 20.0,
        "uint8": rng.integers(0, 255, size=(n, 5), dtype=np.uint8),
        "int32": rng.integers(0, 2, size=(n, 1)).astype(np.int32),
        "uint16": rng.integers(0, 4000, size=(n, 2)).astype(np.uint16),
        "int8": rng.integers(-100, 100, size=(n, 2)).astype(np.int8),
        "float16": rng.normal(size=(n, 2)).astype(np.float16),
        "large int64": rng.integers(-(2**62), 2**62, size=(n, 2)),
    }


@pytest.mark.parametrize("n", [1, 2, 3, 40, 101, 1500])
def test_feature_stats_equal_lerobot(n):
    for name, data in _cases(n, np.random.default_rng(n)).items():
        try:
            assert_same(feature_stats(data), lerobot_feature_stats(data))
        except AssertionError as exc:
            raise AssertionError(f"{name}: {exc}") from None


def test_numeric_stats_equal_compute_episode_stats():
    """Columns of one dtype are sorted together; every column's values stay its own."""
    columns = _cases(40, np.random.default_rng(7))
    features = {k: {"dtype": str(v.dtype), "shape": v.shape[1:]} for k, v in columns.items()}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = lerobot_stats.compute_episode_stats(columns, features)
    ours = numeric_stats(columns)
    assert list(ours) == list(ref)
    for key in ref:
        assert_same(ours[key], ref[key])


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(2, 60),
    dim=st.integers(1, 4),
    dtype=st.sampled_from(["float32", "float64", "int64", "bool", "uint8", "uint16", "float16"]),
    levels=st.integers(1, 1000),
    seed=st.integers(0, 2**32 - 1),
)
def test_feature_stats_equal_lerobot_property(n, dim, dtype, levels, seed):
    """Random shapes, dtypes and numbers of distinct values (ties land on bin edges)."""
    rng = np.random.default_rng(seed)
    scale = abs(rng.normal()) if dtype.startswith("u") else rng.normal()
    data = (rng.integers(0, levels, size=(n, dim)) * scale).astype(dtype)
    assert_same(feature_stats(data), lerobot_feature_stats(data))


@pytest.mark.parametrize(
    "shape",
    [
        (1, 1, 1, 3),
        (1, 4, 4, 3),
        (7, 6, 8, 3),
        (40, 48, 64, 3),
        (3, 320, 240, 3),
        (1500, 2, 3, 3),
        (2, 299, 300, 1),
        (2, 480, 640, 3),
    ],
)
def test_image_stats_equal_lerobot(shape):
    """Sampled and downscaled frames as lerobot does (shape (3, 1, 1), divided by 255)."""
    frames = np.random.default_rng(0).integers(0, 255, size=shape, dtype=np.uint8)
    assert_same(image_stats(frames), lerobot_image_stats(frames))
    dark = np.zeros(shape, np.uint8)
    assert_same(image_stats(dark), lerobot_image_stats(dark))


@pytest.mark.parametrize("unit", ["m", "mm"])
def test_depth_stats_equal_compute_episode_stats(unit, tmp_path):
    """A depth map (`is_depth_map`, `depth_unit`): lerobot's statistics of its TIFF frames, read
    back in their native dtype, not divided by 255; episodes shorter and longer than the 100
    frames sampled, one frame of one pixel (lerobot's special case), large frames downscaled."""
    rng = np.random.default_rng(11)
    for n, height, width in [(1, 1, 1), (1, 24, 32), (2, 24, 32), (37, 24, 32), (150, 12, 16), (3, 480, 640)]:
        frames = depth_frames(n, height, width, unit, rng)
        ref = lerobot_camera_stats(frames, tmp_path / f"{unit}-{n}-{height}", depth_unit=unit)
        case = f"{unit} {frames.shape}"
        try:
            assert_same(depth_stats(frames), ref)
            assert_same(image_stats(frames, depth=True), ref)
            assert_same(image_stats(frames[..., 0], depth=True), ref)  # (T, H, W) too
        except AssertionError as exc:
            raise AssertionError(f"{case}: {exc}") from None
        assert ref["mean"].shape == (1, 1, 1), case
        if height > 1:  # in the stored unit: metres or millimetres, not divided by 255
            scale = 1000 if unit == "mm" else 1
            assert 0.3 * scale < ref["q50"].item() < 2.5 * scale, case
            assert ref["max"].item() == frames.max(), case


def test_depth_video_feature_equal_compute_episode_stats(tmp_path):
    """A depth `video` feature: lerobot computes its statistics from the same TIFF frames."""
    frames = depth_frames(20, 30, 40, "m", np.random.default_rng(5))
    assert_same(depth_stats(frames), lerobot_camera_stats(frames, tmp_path, depth_unit="m", dtype="video"))


def test_depth_stats_reject_what_lerobot_cannot_store():
    """lerobot's image writer stores single-channel float32 or uint16 only."""
    for bad in (np.zeros((3, 4, 4, 1), np.float64), np.zeros((3, 4, 4, 3), np.float32), np.zeros((4, 4), np.uint16)):
        with pytest.raises(ValueError, match="depth frames"):
            depth_stats(bad)


@pytest.mark.parametrize(
    ("dtype", "shape"), [("image", (1, 2, 1, 3)), ("image", (5, 20, 30, 3)), ("video", (3, 300, 200, 3))]
)
def test_rgb_stats_equal_compute_episode_stats(dtype, shape, tmp_path):
    """An RGB camera: lerobot's statistics of its PNG frames, divided by 255."""
    frames = np.random.default_rng(1).integers(0, 255, size=shape, dtype=np.uint8)
    assert_same(image_stats(frames), lerobot_camera_stats(frames, tmp_path, dtype=dtype))


def test_running_stats_equal_lerobots_pairwise_aggregation():
    """The writer's dataset statistics: aggregate_stats([stats, episode]) after every episode,
    depth maps ((1, 1, 1) statistics, in metres or millimetres) among them."""
    rng = np.random.default_rng(3)
    episodes = []
    for e in range(6):
        n = 1 if e == 0 else 3 + 7 * e  # the first episode has lerobot's unpromoted dtypes
        columns = {k: v for k, v in _cases(n, rng).items() if k != "3-D"}
        stats = numeric_stats(columns)
        stats["observation.images.rgb"] = image_stats(rng.integers(0, 255, size=(n, 6, 8, 3), dtype=np.uint8))
        stats["observation.images.depth"] = depth_stats(depth_frames(n, 6, 8, "m", rng))
        stats["observation.images.depth_mm"] = depth_stats(depth_frames(n, 6, 8, "mm", rng))
        episodes.append(stats)
    running, ref = RunningStats(), None
    assert running.result() is None
    for k, stats in enumerate(episodes):
        running.add(stats)
        ref = stats if ref is None else lerobot_stats.aggregate_stats([ref, stats])
        ours = running.result()
        assert set(ours) == set(ref), k
        for key in ref:
            assert_same(ours[key], ref[key])


def test_image_stats_sample_like_lerobot_without_importing_it():
    """The frames sampled for statistics are lerobot's (evenly spaced, large frames downscaled), and a
    worker computing them does not load lerobot's module (which imports torch)."""
    import subprocess
    import sys

    from shiftkit.datasets.stats import _image_samples

    for length in (1, 2, 99, 100, 101, 500, 1000, 5000, 20_000):
        expected = lerobot_stats.sample_indices(length)
        frames = np.arange(length).reshape(length, 1, 1, 1).astype(np.int64)
        assert _image_samples(frames)[:, 0, 0, 0].tolist() == expected, length
    for height, width in [(299, 299), (300, 300), (299, 450), (451, 300), (480, 640), (1080, 1920), (640, 480)]:
        frame = np.arange(height * width * 3, dtype=np.int64).reshape(1, height, width, 3)
        channels_first = lerobot_stats.auto_downsample_height_width(frame[0].transpose(2, 0, 1))
        np.testing.assert_array_equal(_image_samples(frame)[0].transpose(2, 0, 1), channels_first)
    code = (
        "import sys, numpy as np; from shiftkit.datasets.stats import image_stats, depth_stats, feature_stats; "
        "image_stats(np.zeros((5, 4, 4, 3), np.uint8)); depth_stats(np.ones((1, 1, 1, 1), np.float32)); "
        "feature_stats(np.zeros((1, 3))); print('torch' in sys.modules, 'lerobot' in sys.modules)"
    )
    assert (
        subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
        == "False False\n"
    )
