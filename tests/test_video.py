"""Video-backed LeRobot datasets in and out: a dataset recorded with lerobot's own writer
(`use_videos=True`) runs through filter + trim + subsample on two workers, written as video and
as images; both load in lerobot, pass `shiftkit validate` and train in `lerobot-train`."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from shiftkit.datasets.camera_meta import factor_cameras
from shiftkit.datasets.check import validate_dataset
from shiftkit.datasets.reader import open_lerobot_dataset
from shiftkit.datasets.sources import SourceConfig
from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, StageSpec
from shiftkit.pipelines.runner import run_pipeline
from tests.helpers import SMALL_DIFFUSION, lerobot_train_two_steps

SIZE = 32
INTRINSICS = {"fx": 30.0, "fy": 30.0, "cx": 15.5, "cy": 15.5, "width": SIZE, "height": SIZE}
FRAMES = 30
STAGES = [
    StageSpec("filter", {"indices": [0, 2, 3]}),
    StageSpec("trim", {"head": 1}),
    StageSpec("subsample", {"every": 2}),
]


def _frame(t: int, e: int) -> np.ndarray:
    img = np.zeros((SIZE, SIZE, 3), np.uint8)
    img[..., 0] = 8 * t
    img[t % (SIZE - 4) : t % (SIZE - 4) + 4, 6 * e : 6 * e + 4] = 255
    return img


@pytest.fixture(scope="module")
def lerobot_video(tmp_path_factory):
    """4 episodes x 30 frames, one 32x32 camera as a video, written by lerobot's own recorder."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    names = ["height", "width", "channels"]
    features = {
        "observation.state": {"dtype": "float32", "shape": (2,), "names": ["t", "e"]},
        "action": {"dtype": "float32", "shape": (2,), "names": ["t", "e"]},
        "observation.images.front": {"dtype": "video", "shape": (SIZE, SIZE, 3), "names": names},
    }
    root = tmp_path_factory.mktemp("video") / "src"
    ds = LeRobotDataset.create("test/video", 10, features, root=root, use_videos=True)
    for e in range(4):
        for t in range(FRAMES):
            ds.add_frame(
                {
                    "observation.state": np.array([t, e], np.float32),
                    "action": np.array([t + 1, e], np.float32),
                    "observation.images.front": _frame(t, e),
                    "task": "reach",
                }
            )
        ds.save_episode()
    ds.finalize()
    return root


@pytest.fixture(scope="module")
def outputs(lerobot_video, tmp_path_factory):
    """The same three stages, output as video (as the source) and as images, on two workers."""
    out = {}
    for variant, video in (("video", None), ("image", False)):
        config = PipelineConfig(
            sources=[SourceConfig(path=str(lerobot_video))],
            destination=DestinationConfig(root=str(tmp_path_factory.mktemp(variant) / "out"), video=video),
            stages=STAGES,
        )
        out[variant] = run_pipeline(config, workers=2, progress=False)
    return out


def test_reader_decodes_what_lerobot_decodes(lerobot_video):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ours = list(open_lerobot_dataset(lerobot_video).iter_episodes([1, 3]))
    theirs = LeRobotDataset("test/video", root=lerobot_video, video_backend="pyav")
    for episode, e in zip(ours, (1, 3), strict=True):
        frames = episode.frames["observation.images.front"]
        assert frames.shape == (FRAMES, SIZE, SIZE, 3) and frames.dtype == np.uint8
        for t in (0, 13, FRAMES - 1):
            item = theirs[e * FRAMES + t]["observation.images.front"]
            np.testing.assert_array_equal(frames[t], (item.numpy().transpose(1, 2, 0) * 255).round().astype(np.uint8))
        # lossy AV1, but the scene is what was recorded
        assert np.abs(frames.astype(int) - np.stack([_frame(t, e) for t in range(FRAMES)])).mean() < 6


@pytest.mark.parametrize("variant", ["video", "image"])
def test_stages_run_on_video_sources(outputs, lerobot_video, variant):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root = outputs[variant]
    info = json.loads((root / "meta/info.json").read_text())
    feature = info["features"]["observation.images.front"]
    assert feature["dtype"] == variant
    if variant == "video":  # filled by lerobot's writer from the first episode's file
        assert feature["info"]["video.codec"] == "av1" and feature["info"]["video.height"] == SIZE
    else:
        assert set(feature) == {"dtype", "shape", "names"}
    assert validate_dataset(root)["warnings"] == []
    loaded = LeRobotDataset(f"test/{variant}", root=root, video_backend="pyav")
    assert loaded.meta.total_episodes == 3 and loaded.meta.total_frames == 3 * (FRAMES // 2)

    source = open_lerobot_dataset(lerobot_video).iter_episodes([0, 2, 3])
    for out, src in zip(open_lerobot_dataset(root).iter_episodes(), source, strict=True):
        expected = src.frames["observation.images.front"][1::2]
        got = out.frames["observation.images.front"]
        np.testing.assert_array_equal(out.frames["observation.state"][:, 0], np.arange(1, FRAMES, 2))
        if variant == "image":
            np.testing.assert_array_equal(got, expected)  # decoded once, stored losslessly
        else:
            assert np.abs(got.astype(int) - expected).mean() < 6  # encoded a second time

    stats = json.loads((root / "meta/stats.json").read_text())["observation.images.front"]
    assert np.asarray(stats["mean"]).shape == (3, 1, 1)
    assert 0 < np.asarray(stats["mean"]).ravel()[0] < 1  # lerobot's image statistics scale: [0, 1]


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["video", "image"])
def test_lerobot_train_diffusion_on_outputs(outputs, variant, tmp_path):
    """lerobot's own trainer (diffusion, CPU, offline, 2 steps, a small U-Net) on both outputs."""
    lerobot_train_two_steps(f"test/{variant}", outputs[variant], tmp_path / "train", SMALL_DIFFUSION)


def test_collect_writes_videos(tmp_path):
    """`collect --video`: the RGB camera as a lerobot video and depth through lerobot's depth
    encoder, decodable (depth within its quantisation of the recorded metres) and valid."""
    from shiftkit.app.collect import CollectConfig, collect

    root, counts = collect(
        CollectConfig(
            task="lift",
            episodes=1,
            cameras=("front",),
            depth=True,
            video=True,
            lerobot="test/collect",
            root=str(tmp_path / "ds"),
        )
    )
    info = json.loads((root / "meta/info.json").read_text())
    assert info["features"]["observation.images.front"]["dtype"] == "video"
    depth_info = info["features"]["observation.depth.front"]
    assert depth_info["dtype"] == "video" and depth_info["info"]["is_depth_map"]
    assert depth_info["info"]["video.codec"] == "hevc" and depth_info["info"]["video.pix_fmt"] == "gray12le"
    videos = sorted(p.parent.parent.name for p in (root / "videos").rglob("*.mp4"))
    assert videos == ["observation.depth.front", "observation.images.front"]
    assert validate_dataset(root)["episodes"] == 1
    episode = next(open_lerobot_dataset(root).iter_episodes())
    depth = episode.frames["observation.depth.front"]
    assert counts["episodes"] == 1 and depth.shape == (len(episode), 48, 64, 1) and depth.dtype == np.float32
    assert 0.3 < float(np.median(depth)) < 2.5  # metres from the front camera to the scene
    assert episode.frames["observation.images.front"].shape == (len(episode), 48, 64, 3)


def test_video_needs_lerobot_output(tmp_path):
    from shiftkit.app.collect import CollectConfig, collect
    from shiftkit.datasets.errors import ConfigError

    with pytest.raises(ConfigError, match="--video applies to LeRobot output"):
        collect(CollectConfig(task="lift", episodes=1, cameras=("front",), video=True, out=str(tmp_path / "raw")))


def test_in_memory_encoder_is_lerobots_encoder(tmp_path):
    """The writer encodes from memory; the file is byte for byte what lerobot's encode_video_frames
    makes from the same frames as PNG files (RGB) or TIFF files (depth, its depth encoder), and the
    reader's depth dequantisation is lerobot's."""
    import PIL.Image
    from lerobot.configs import depth_encoder_defaults, rgb_encoder_defaults
    from lerobot.datasets.depth_utils import dequantize_depth, quantize_depth
    from lerobot.datasets.image_writer import write_image
    from lerobot.datasets.video_utils import encode_video_frames

    from shiftkit.datasets.depth import VIDEO_DEFAULTS
    from shiftkit.datasets.video import decode_episode, dequantize_metres, encode_frames

    frames = np.stack([_frame(t, 1) for t in range(12)])
    depth = np.stack([np.full((SIZE, SIZE, 1), 0.3 + 0.1 * t, np.float32) for t in range(12)])
    depth[:, 4:9, 4:9] = 2.4
    (tmp_path / "png").mkdir()
    (tmp_path / "tiff").mkdir()
    for t, (frame, d) in enumerate(zip(frames, depth, strict=True)):
        PIL.Image.fromarray(frame).save(tmp_path / "png" / f"frame-{t:06d}.png")
        write_image(d, tmp_path / "tiff" / f"frame-{t:06d}.tiff")
    for kind, encoder in (("png", rgb_encoder_defaults()), ("tiff", depth_encoder_defaults())):
        encode_video_frames(
            tmp_path / kind, tmp_path / f"lerobot-{kind}.mp4", 10, video_encoder=encoder, overwrite=True
        )
        encode_frames(frames if kind == "png" else depth, tmp_path / f"ours-{kind}.mp4", 10, encoder)
        assert (tmp_path / f"ours-{kind}.mp4").read_bytes() == (tmp_path / f"lerobot-{kind}.mp4").read_bytes(), kind
    decoded = decode_episode(tmp_path / "ours-png.mp4", 0.0, np.arange(12) / 10, "test")
    assert decoded.shape == frames.shape and np.abs(decoded.astype(int) - frames).mean() < 6
    info = {f"video.{k}": v for k, v in VIDEO_DEFAULTS.items()}
    decoded = decode_episode(tmp_path / "ours-tiff.mp4", 0.0, np.arange(12) / 10, "test", info)
    assert decoded.shape == depth.shape and np.abs(decoded - depth).max() < 2e-3  # lossless HEVC: quantiser only
    codes = np.stack([quantize_depth(d, video_backend=None) for d in depth])
    theirs = dequantize_depth(codes[..., None], output_unit="m", output_tensor=False, output_channel_last=True)
    np.testing.assert_allclose(dequantize_metres(codes, info)[..., None], theirs, rtol=0, atol=1e-6)
    assert {k: getattr(depth_encoder_defaults(), k) for k in VIDEO_DEFAULTS} == VIDEO_DEFAULTS


def test_video_dataset_round_trips_through_the_hub(outputs, tmp_path):
    """Push a video output with camera metadata to a loopback hub and pull it: same files, and the
    pulled copy reads the same episodes and cameras."""
    from tests.hub_server import LoopbackHub
    from tests.test_hub import WRITE, assert_ok, file_hashes, shiftkit_batch

    local = tmp_path / "local"
    shutil.copytree(outputs["video"], local)
    (local / "meta/cameras.json").write_text(
        json.dumps(factor_cameras({i: {"front": {"intrinsics": INTRINSICS}} for i in range(3)}))
    )
    pulled = tmp_path / "pulled"
    with LoopbackHub(tmp_path / "store", {WRITE: "write"}) as hub:
        results = shiftkit_batch(
            [
                (["push", str(local), "--repo-id", "shiftkit-test/video"], WRITE),
                (["pull", "shiftkit-test/video", "--root", str(pulled)], WRITE),
            ],
            hub.endpoint,
            tmp_path / "home",
        )
    assert_ok(results)
    ours, theirs = file_hashes(local), file_hashes(pulled)
    assert any(k.startswith("videos/") for k in ours)
    hub_files = ("README.md", ".gitattributes")  # the card and the hub's own file
    assert {k: v for k, v in ours.items() if k not in hub_files} == {
        k: v for k, v in theirs.items() if k not in hub_files
    }
    a, b = (list(open_lerobot_dataset(root).iter_episodes()) for root in (local, pulled))
    assert [ep.meta["cameras"] for ep in b] == [{"front": {"intrinsics": INTRINSICS}}] * 3
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.frames["observation.images.front"], y.frames["observation.images.front"])


@pytest.mark.parametrize("length", [1, 2])
def test_one_and_two_frame_depth_episodes_encode(length, tmp_path):
    """lerobot's depth encoder (libx265, lossless 12-bit) through PyAV leaves the decode time of a
    one-frame stream's packet uninitialised, which the MP4 muxer refused on most seeds (a success
    example is a one-frame episode); every seed now encodes and decodes to its quantised depth."""
    from shiftkit.datasets.video import decode_episode, default_encoders, encode_frames

    encoder = default_encoders()["depth"]
    for seed in range(12):
        metres = np.random.default_rng(seed).uniform(0.2, 2.0, (length, 16, 32, 1)).astype(np.float32)
        path = tmp_path / f"depth-{seed}.mp4"
        encode_frames(metres, path, 10, encoder)
        info = {"video.is_depth_map": True, "video.depth_min": encoder.depth_min, "video.depth_max": encoder.depth_max}
        info.update({"video.shift": encoder.shift, "video.use_log": encoder.use_log})
        decoded = decode_episode(path, 0.0, np.arange(length) / 10, str(path), info)
        assert decoded.shape == metres.shape
        np.testing.assert_allclose(decoded, metres, rtol=0.01)


def test_a_camera_too_narrow_for_svt_av1_is_refused_before_anything_runs(lerobot_video, tmp_path, capsys):
    """SVT-AV1 (lerobot's default codec) kills the process with a floating-point exception on frames
    24 px wide or less: a pipeline that would encode such a camera stops at planning, in one line."""
    import subprocess
    import sys

    from shiftkit.datasets.errors import DatasetError
    from shiftkit.datasets.video import default_encoders, encode_frames

    config = tmp_path / "narrow.toml"
    config.write_text(
        f'[[sources]]\npath = "{lerobot_video}"\n[destination]\nroot = "{tmp_path / "out"}"\n'
        '[[stages]]\nname = "resize"\nparams = { width = 24, height = 16 }\n'
    )
    proc = subprocess.run(
        [sys.executable, "-m", "shiftkit.app.cli", "run", str(config)], capture_output=True, text=True
    )
    assert proc.returncode == 2 and not (tmp_path / "out").exists()
    err = [line for line in proc.stderr.splitlines() if line.startswith("shiftkit")]
    assert len(err) == 1 and "24 px wide" in err[0], proc.stderr[-2000:]
    with pytest.raises(DatasetError, match="24 px wide"):  # and the encoder itself never gets such frames
        encode_frames(np.zeros((2, 16, 24, 3), np.uint8), tmp_path / "x.mp4", 10, default_encoders()["rgb"])


def test_encoding_leaves_the_thread_s_scheduling_as_it_was(tmp_path):
    """SVT-AV1, run as root, makes the thread that opens it real-time (SCHED_FIFO 99), and every
    process that thread starts inherits it: pipeline workers, trainers and cluster nodes that starve
    a small machine. Every encoder shiftkit opens (a worker's or writer's encode, the plan's check of
    the destination's settings, a smart cut) leaves the policy as it found it. Where this runs as root
    the change itself is shown first, on a bare PyAV encoder."""
    import os
    from fractions import Fraction

    import av

    from shiftkit.datasets.video import default_encoders, encode_frames
    from shiftkit.datasets.video_encoder import check_rgb_encoder

    before = os.sched_getscheduler(0)
    if os.geteuid() == 0:
        ctx = av.CodecContext.create("libsvtav1", "w")
        ctx.width, ctx.height, ctx.pix_fmt, ctx.time_base = 48, 32, "yuv420p", Fraction(1, 10)
        frame = av.VideoFrame.from_ndarray(np.zeros((32, 48, 3), np.uint8), format="rgb24").reformat(format="yuv420p")
        ctx.encode(frame)
        assert os.sched_getscheduler(0) == os.SCHED_FIFO  # what the guard undoes
        os.sched_setscheduler(0, before, os.sched_param(0))
    encode_frames(np.zeros((3, 32, 48, 3), np.uint8), tmp_path / "a.mp4", 10, default_encoders()["rgb"])
    assert os.sched_getscheduler(0) == before
    camera = {"dtype": "video", "shape": [32, 48, 3], "names": ["height", "width", "channels"], "info": {}}
    check_rgb_encoder("observation.images.front", camera, {"crf": 28})  # the plan opens the encoder
    assert os.sched_getscheduler(0) == before


def test_the_episodes_of_one_video_file_share_one_open_container(monkeypatch):
    """lerobot stores many episodes in one video file: the reader opens it once per process, not once
    per episode and camera (the Ray Data `read_lerobot` lesson), and frames decoded in any episode
    order through the one container are those lerobot's own loader gives."""
    import av
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from shiftkit.datasets import video
    from tests.lerobot_recordings import Recording, recording

    rec = Recording(video=True, cameras=("front", "wrist"), depth=("front",), size=(32, 48), lengths=(5, 6, 7),
                    language=False)  # fmt: skip
    source = recording(rec)
    keys = ("observation.images.front", "observation.images.wrist", "observation.depth.front")
    opened: list[str] = []
    real_open = av.open
    monkeypatch.setattr(av, "open", lambda path, *a, **k: opened.append(str(path)) or real_open(path, *a, **k))
    video._OPEN.clear()
    reader = open_lerobot_dataset(source)
    order = [2, 0, 1, 2]  # backwards and forwards within each file
    episodes = [next(reader.iter_episodes([e])) for e in order]
    assert sorted(opened) == sorted({str(p) for p in source.glob("videos/*/chunk-*/file-*.mp4")})  # once each
    loader = LeRobotDataset("test/loaded", root=source, video_backend="pyav", depth_output_unit="m")
    starts = np.cumsum((0, *rec.lengths))
    for e, episode in zip(order, episodes, strict=True):
        for key in keys:
            expected = np.stack([loader[int(starts[e]) + t][key].numpy() for t in range(rec.lengths[e])])
            got = np.asarray(episode.frames[key], np.float32)
            if key.startswith("observation.images"):
                np.testing.assert_array_equal(got.transpose(0, 3, 1, 2) / 255.0, expected)
            else:
                np.testing.assert_allclose(got.transpose(0, 3, 1, 2), expected, rtol=0, atol=2e-6)  # float32 rounding


@pytest.mark.parametrize("pick", ["every other", "every other from 1", "one", "scattered"])
def test_a_selection_of_frames_decodes_only_the_packets_it_needs(pick, monkeypatch):
    """Frames asked of an AV1 stream in presentation order (lerobot's) are decoded from the keyframe
    before each, skipping packets no asked frame needs (every other frame of lerobot's `g=2` stream:
    its keyframes alone), and are the frames lerobot's loader gives; depth (12-bit HEVC) alike."""
    import av
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from shiftkit.datasets import video
    from shiftkit.datasets.images import decode_video
    from tests.lerobot_recordings import Recording, recording

    rec = Recording(video=True, cameras=("front",), depth=("front",), size=(32, 48), lengths=(9, 8), language=False)
    source = recording(rec)
    picked = {"every other": [0, 2, 4, 6], "every other from 1": [1, 3, 5, 7], "one": [5], "scattered": [0, 5, 6]}[pick]
    loader = LeRobotDataset("test/loaded", root=source, video_backend="pyav", depth_output_unit="m")
    meta = json.loads((source / "meta/info.json").read_text())
    decoded: list[int] = []

    class Counted:  # a packet whose decoding is counted
        def __init__(self, packet):
            self.packet = packet

        def decode(self):
            decoded.append(self.packet.pts)
            return self.packet.decode()

        def __getattr__(self, name):
            return getattr(self.packet, name)

    class Container:
        def __init__(self, container):
            self.container, self.streams, self.seek = container, container.streams, container.seek

        def demux(self, stream):
            return (Counted(p) for p in self.container.demux(stream))

        def decode(self, stream):  # every packet in turn
            return (frame for packet in self.demux(stream) for frame in packet.decode())

    real = video._opened
    monkeypatch.setattr(video, "_opened", lambda path: (lambda key, c: (key, Container(c)))(*real(path)))
    video._OPEN.clear()
    for key in ("observation.images.front", "observation.depth.front"):
        path = source / "videos" / key / "chunk-000/file-000.mp4"
        with av.open(str(path)) as container:  # episode 1 starts after episode 0's 9 frames
            stream = container.streams.video[0]
            packets = [
                p for p in container.demux(stream) if p.dts is not None and p.pts * stream.time_base >= 0.9 - 1e-6
            ]
            keyframes = [t for t, p in enumerate(packets) if p.is_keyframe]
        decoded.clear()
        frames = decode_video(path, 0.9, np.array(picked) / rec.fps, "test", meta["features"][key])
        expected = np.stack([loader[9 + t][key].numpy().transpose(1, 2, 0) for t in picked])
        if key.startswith("observation.images"):
            np.testing.assert_array_equal(frames / np.float32(255.0), expected)
            needed = {u for t in picked for u in range(max(k for k in keyframes if k <= t), t + 1)}
            assert keyframes[:2] == [0, 2] and len(decoded) == len(needed)
            assert len(needed) == {"every other": 4, "every other from 1": 8, "one": 2, "scattered": 4}[pick]
        else:
            np.testing.assert_allclose(frames, expected, rtol=0, atol=2e-6)
