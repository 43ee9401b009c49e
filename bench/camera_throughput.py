"""Camera dataset throughput: shiftkit pass-through vs lerobot's own copy loop, image and video.

Builds, in one run, a camera dataset (state, action and one RGB camera; default 10 episodes x 200
frames at 96x96) stored once as `image` features (PNG in parquet) and once as `video` features
(lerobot's AV1 encoder), then copies each into a new dataset of the same format:
  * shiftkit: a pass-through pipeline (LeRobot source -> LeRobot destination, one worker);
  * lerobot: its own loop (`LeRobotDataset[i]` with the pyav video backend, `add_frame`,
    `save_episode`, `finalize`).
Reports frames/s of both per format, the speed-up, bytes per frame and how fast lerobot reads
frames in random order (a trainer's access pattern) for each format (what docs/video_depth.md
cites for the default format). Goal: speed-up >= 3x for both formats; the
metric is the smaller of the two. The last line printed is the JSON result.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np  # noqa: E402

FPS = 20
FORMATS = ("image", "video")


def _frames(length: int, size: int, rng: np.random.Generator) -> np.ndarray:
    """A moving bright square over a shaded background with faint sensor noise (like a rendered
    scene: compressible, not constant)."""
    y, x = np.mgrid[0:size, 0:size]
    shade = np.stack([40 + 80 * x / size, 60 + 60 * y / size, 90 + 30 * (x + y) / (2 * size)], axis=-1)
    base = np.clip(shade + rng.integers(0, 4, (size, size, 3)), 0, 255).astype(np.uint8)
    frames = np.repeat(base[None], length, axis=0)
    for t in range(length):
        r, c = (3 * t) % (size - 12), (5 * t) % (size - 12)
        frames[t, r : r + 12, c : c + 12] = (230, 180, 40)
    return frames


def make_source(root: Path, dtype: str, episodes: int, length: int, size: int) -> Path:
    from shiftkit.datasets.episode import Episode
    from shiftkit.datasets.writer import DatasetWriter

    rng = np.random.default_rng(0)
    features = {
        "observation.state": {"dtype": "float32", "shape": (8,), "names": [f"s{i}" for i in range(8)]},
        "action": {"dtype": "float32", "shape": (4,), "names": ["dx", "dy", "dz", "grip"]},
        "observation.images.front": {
            "dtype": dtype,
            "shape": (size, size, 3),
            "names": ["height", "width", "channels"],
        },
    }
    with DatasetWriter("bench/source", root, FPS, features) as writer:
        for _ in range(episodes):
            writer.add_episode(
                Episode(
                    {
                        "observation.state": rng.normal(size=(length, 8)).astype(np.float32),
                        "action": rng.uniform(-1, 1, size=(length, 4)).astype(np.float32),
                        "observation.images.front": _frames(length, size, rng),
                        "timestamp": np.arange(length) / FPS,
                        "task": np.array(["lift"] * length),
                    }
                )
            )
    return root


def lerobot_copy(src: Path, dst: Path, dtype: str) -> float:
    """lerobot's own loop; returns seconds."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from tqdm import tqdm

    t0 = time.perf_counter()
    ds = LeRobotDataset("bench/source", root=src, video_backend="pyav")
    skip = ("timestamp", "frame_index", "episode_index", "index", "task_index")
    features = {k: v for k, v in ds.features.items() if k not in skip}
    out = LeRobotDataset.create("bench/copy", ds.fps, features, root=dst, use_videos=dtype == "video")
    current = 0
    for i in tqdm(range(len(ds)), desc=f"lerobot copy ({dtype})", unit="frame", leave=False):
        item = ds[i]
        if int(item["episode_index"]) != current:
            out.save_episode()
            current = int(item["episode_index"])
        frame = {"task": item["task"]}
        for key, ft in features.items():
            value = item[key].numpy()
            if ft["dtype"] in ("image", "video"):  # lerobot hands out (C, H, W) floats in [0, 1]
                value = (value.transpose(1, 2, 0) * 255).round().astype(np.uint8)
            frame[key] = value.astype(ft["dtype"] if ft["dtype"] not in ("image", "video") else np.uint8)
        out.add_frame(frame)
    out.save_episode()
    out.finalize()
    return time.perf_counter() - t0


def shiftkit_copy(src: Path, dst: Path) -> float:
    from shiftkit.datasets.sources import SourceConfig
    from shiftkit.pipelines.config import DestinationConfig, PipelineConfig
    from shiftkit.pipelines.runner import run_pipeline

    t0 = time.perf_counter()
    config = PipelineConfig(sources=[SourceConfig(path=str(src))], destination=DestinationConfig(root=str(dst)))
    run_pipeline(config, workers=1, progress=True)
    return time.perf_counter() - t0


def lerobot_read_fps(root: Path, samples: int) -> float:
    """Frames/s of `LeRobotDataset[i]` in random order (what a trainer's data loader does)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset("bench/read", root=root, video_backend="pyav")
    order = np.random.default_rng(0).permutation(len(ds))[:samples]
    ds[int(order[0])]  # open files once before timing
    t0 = time.perf_counter()
    for i in order:
        ds[int(i)]
    return len(order) / (time.perf_counter() - t0)


def dataset_bytes(root: Path) -> int:
    return sum(p.stat().st_size for p in root.rglob("*") if p.is_file() and p.suffix in (".parquet", ".mp4"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="short run (< 1 minute)")
    parser.add_argument("--episodes", type=int, default=None)
    parser.add_argument("--length", type=int, default=None)
    parser.add_argument("--size", type=int, default=96, help="square frame size in pixels (default 96)")
    args = parser.parse_args()
    episodes = args.episodes or (4 if args.quick else 10)
    length = args.length or (100 if args.quick else 200)
    frames = episodes * length
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for dtype in FORMATS:
            src = make_source(tmp / f"src_{dtype}", dtype, episodes, length, args.size)
            t_lerobot = lerobot_copy(src, tmp / f"lerobot_{dtype}", dtype)
            t_shiftkit = shiftkit_copy(src, tmp / f"shiftkit_{dtype}")
            results[dtype] = {
                "frames_per_s_shiftkit": round(frames / t_shiftkit, 1),
                "frames_per_s_lerobot": round(frames / t_lerobot, 1),
                "speedup": round(t_lerobot / t_shiftkit, 2),
                "bytes_per_frame": round(dataset_bytes(tmp / f"shiftkit_{dtype}") / frames, 1),
                "train_read_frames_per_s": round(lerobot_read_fps(tmp / f"shiftkit_{dtype}", min(frames, 400)), 1),
            }
    for dtype, r in results.items():
        print(
            f"{dtype:5s}: shiftkit {r['frames_per_s_shiftkit']:7.0f} frames/s, lerobot {r['frames_per_s_lerobot']:7.0f}"
            f" frames/s -> {r['speedup']:.1f}x; {r['bytes_per_frame']:.0f} bytes/frame;"
            f" lerobot random reads {r['train_read_frames_per_s']:.0f} frames/s"
        )
    speedup = min(r["speedup"] for r in results.values())
    print(
        json.dumps(
            {
                "bench": "camera_throughput",
                "metric": "min_speedup_vs_lerobot_copy_loop",
                "value": speedup,
                "goal": 3.0,
                "higher_is_better": True,
                **{f"{dtype}_{k}": v for dtype, r in results.items() for k, v in r.items()},
                "episodes": episodes,
                "frames_per_episode": length,
                "size": args.size,
                "quick": args.quick,
            }
        )
    )


if __name__ == "__main__":
    main()
