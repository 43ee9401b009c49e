"""Pipeline throughput and streaming memory.

Measures, in one run, on the same synthetic state-only LeRobot dataset (>= 200 episodes):
  * frames/s of a pass-through shiftkit pipeline (LeRobot source -> LeRobot destination; the
    median of 3 runs);
  * frames/s of lerobot's own copy loop (`LeRobotDataset` read + `add_frame`/`save_episode`);
  * the I/O floor: pyarrow alone reading and rewriting the same parquet files (data and episode
    metadata), and the share of the pipeline's time it accounts for;
and the peak RSS of the pipeline on 1x and 4x the episodes (each in a fresh process).
A second source, raw episodes with an RGB camera (one PNG file per frame), measures the same
pass-through against its own floor: reading the PNG files' bytes and the arrays, and writing
them as parquet with pyarrow. Its frames travel as their files' bytes (no PNG is encoded again),
so the pipeline's time is mostly that floor plus decoding.
Goals: speed-up >= 10x; RSS(4x) <= 1.2 x RSS(1x). The last line printed is the JSON result.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np  # noqa: E402


def make_source(root: Path, episodes: int, length: int, seed: int = 0) -> Path:
    from shiftkit.datasets.episode import Episode
    from shiftkit.datasets.writer import DatasetWriter

    rng = np.random.default_rng(seed)
    features = {
        "observation.state": {"dtype": "float32", "shape": (8,), "names": [f"s{i}" for i in range(8)]},
        "observation.environment_state": {"dtype": "float32", "shape": (14,), "names": [f"e{i}" for i in range(14)]},
        "action": {"dtype": "float32", "shape": (4,), "names": ["dx", "dy", "dz", "grip"]},
        "next.success": {"dtype": "bool", "shape": (1,), "names": None},
    }
    with DatasetWriter("bench/source", root, 20, features) as w:
        for _ in range(episodes):
            w.add_episode(
                Episode(
                    {
                        "observation.state": rng.normal(size=(length, 8)).astype(np.float32),
                        "observation.environment_state": rng.normal(size=(length, 14)).astype(np.float32),
                        "action": rng.uniform(-1, 1, size=(length, 4)).astype(np.float32),
                        "next.success": (np.arange(length) >= length - 5).reshape(-1, 1),
                        "timestamp": np.arange(length) / 20.0,
                        "task": np.array(["lift"] * length),
                    }
                )
            )
    return root


def lerobot_copy(src: Path, dst: Path) -> float:
    """lerobot's own loop; returns seconds."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    t0 = time.perf_counter()
    ds = LeRobotDataset("bench/source", root=src)
    features = {
        k: v
        for k, v in ds.features.items()
        if k not in ("timestamp", "frame_index", "episode_index", "index", "task_index")
    }
    out = LeRobotDataset.create("bench/copy", ds.fps, features, root=dst, use_videos=False)
    current = 0
    for i in range(len(ds)):
        item = ds[i]
        if int(item["episode_index"]) != current:
            out.save_episode()
            current = int(item["episode_index"])
        frame = {k: item[k].numpy().astype(features[k]["dtype"]).reshape(features[k]["shape"]) for k in features}
        frame["task"] = item["task"]
        out.add_frame(frame)
    out.save_episode()
    out.finalize()
    return time.perf_counter() - t0


def io_floor(src: Path, dst: Path) -> float:
    """pyarrow alone: read every parquet file of the dataset and write it again; returns seconds."""
    import pyarrow.parquet as pq

    t0 = time.perf_counter()
    for path in sorted(src.rglob("*.parquet")):
        out = dst / path.relative_to(src)
        out.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pq.read_table(path), out, compression="snappy")
    return time.perf_counter() - t0


def raw_camera_floor(src: Path, dst: Path) -> float:
    """pyarrow alone on a raw camera source: every episode's arrays and PNG bytes read and written
    as one parquet file per episode; returns seconds."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    dst.mkdir(parents=True)
    t0 = time.perf_counter()
    for k, ep in enumerate(sorted(src.glob("episode_*"))):
        columns = {p.stem: list(np.load(p)) for p in sorted((ep / "arrays").glob("*.npy"))}
        for cam in sorted((ep / "images").iterdir()):
            columns[cam.name] = [f.read_bytes() for f in sorted(cam.glob("frame_*.png"))]
        pq.write_table(pa.table(columns), dst / f"episode_{k:06d}.parquet", compression="snappy")
    return time.perf_counter() - t0


def shiftkit_copy(src: Path, dst: Path, workers: int = 1) -> float:
    from shiftkit.datasets.sources import SourceConfig
    from shiftkit.pipelines.config import DestinationConfig, PipelineConfig
    from shiftkit.pipelines.runner import run_pipeline

    t0 = time.perf_counter()
    run_pipeline(
        PipelineConfig(sources=[SourceConfig(path=str(src))], destination=DestinationConfig(root=str(dst))),
        workers=workers,
        progress=False,
    )
    return time.perf_counter() - t0


def print_profile(src: Path, dst: Path, top: int) -> None:
    """cProfile of one more pass-through run (profiling slows it, so it is not the timed one)."""
    import cProfile
    import pstats

    profile = cProfile.Profile()
    profile.runcall(shiftkit_copy, src, dst)
    for order in ("cumulative", "tottime"):
        pstats.Stats(profile, stream=sys.stdout).strip_dirs().sort_stats(order).print_stats(top)


def peak_rss_mb(src: Path, dst: Path) -> float:
    """Peak RSS of a fresh process that runs the pass-through pipeline."""
    code = (
        f"import resource, sys; from pathlib import Path; sys.path.insert(0, {str(Path(__file__).parent)!r});"
        f"from pipeline_throughput import shiftkit_copy; shiftkit_copy(Path({str(src)!r}), Path({str(dst)!r}));"
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return float(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="short run (< 1 minute)")
    parser.add_argument("--episodes", type=int, default=None)
    parser.add_argument("--length", type=int, default=None)
    parser.add_argument(
        "--profile",
        type=int,
        default=0,
        metavar="N",
        help="also profile one more pipeline run; print its top N entries",
    )
    args = parser.parse_args()
    episodes = args.episodes or 200
    length = args.length or (40 if args.quick else 100)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        src = make_source(tmp / "src", episodes, length)
        frames = episodes * length
        t_lerobot = lerobot_copy(src, tmp / "lerobot_copy")
        # The pipeline's run is short, so one load spike of the shared machine can double it: the
        # median of 3 runs (lerobot's loop, 10x longer, averages the load over its own run).
        t_runs = [shiftkit_copy(src, tmp / f"shiftkit_copy{k}") for k in range(3)]
        t_shiftkit = sorted(t_runs)[1]
        t_floor = min(io_floor(src, tmp / f"floor{k}") for k in range(3))  # best of 3: it is short
        if args.profile:
            print_profile(src, tmp / "profiled_copy", args.profile)
        fps_lerobot, fps_shiftkit = frames / t_lerobot, frames / t_shiftkit
        from shiftkit.datasets.synthetic import write_synthetic_raw

        cam_episodes = 20 if args.quick else 50
        raw_cam = write_synthetic_raw(tmp / "raw_cam", episodes=cam_episodes, length=length, seed=3, camera=(96, 96))
        t_cam = sorted(shiftkit_copy(raw_cam, tmp / f"raw_cam_copy{k}") for k in range(3))[1]
        t_cam_floor = min(raw_camera_floor(raw_cam, tmp / f"raw_cam_floor{k}") for k in range(3))
        rss_episodes = 50 if args.quick else episodes
        small = make_source(tmp / "small", rss_episodes, length, seed=1)
        large = make_source(tmp / "large", 4 * rss_episodes, length, seed=2)
        rss_1x = peak_rss_mb(small, tmp / "small_out")
        rss_4x = peak_rss_mb(large, tmp / "large_out")
    speedup = fps_shiftkit / fps_lerobot
    print(f"lerobot copy loop : {fps_lerobot:9.0f} frames/s ({frames} frames, {episodes} episodes)")
    print(f"shiftkit pipeline : {fps_shiftkit:9.0f} frames/s  -> speed-up {speedup:.1f}x")
    print(f"I/O floor (pyarrow read + write): {t_floor:.3f} s = {t_floor / t_shiftkit:.1%} of the pipeline's time")
    print(
        f"raw camera source: {cam_episodes * length / t_cam:.0f} frames/s; its I/O floor {t_cam_floor:.3f} s = "
        f"{t_cam_floor / t_cam:.1%} of the pipeline's time"
    )
    print(f"peak RSS 1x ({rss_episodes} eps): {rss_1x:.0f} MB, 4x: {rss_4x:.0f} MB -> ratio {rss_4x / rss_1x:.2f}")
    print(
        json.dumps(
            {
                "bench": "pipeline_throughput",
                "metric": "speedup_vs_lerobot_copy_loop",
                "value": round(speedup, 2),
                "goal": 10.0,
                "higher_is_better": True,
                "frames_per_s_shiftkit": round(fps_shiftkit, 1),
                "frames_per_s_lerobot": round(fps_lerobot, 1),
                "seconds_shiftkit": round(t_shiftkit, 3),
                "seconds_shiftkit_runs": [round(t, 3) for t in t_runs],
                "seconds_lerobot": round(t_lerobot, 3),
                "io_floor_s": round(t_floor, 3),
                "io_floor_fraction_of_pipeline": round(t_floor / t_shiftkit, 4),
                "raw_camera_frames_per_s": round(cam_episodes * length / t_cam, 1),
                "raw_camera_episodes": cam_episodes,
                "raw_camera_io_floor_s": round(t_cam_floor, 3),
                "raw_camera_io_floor_fraction_of_pipeline": round(t_cam_floor / t_cam, 4),
                "episodes": episodes,
                "frames_per_episode": length,
                "rss_mb_1x": round(rss_1x, 1),
                "rss_mb_4x": round(rss_4x, 1),
                "rss_ratio_4x_over_1x": round(rss_4x / rss_1x, 3),
                "rss_goal": 1.2,
                "rss_ok": rss_4x <= 1.2 * rss_1x,
                "quick": args.quick,
                "loadavg_1min": round(os.getloadavg()[0], 2),
            }
        )
    )


if __name__ == "__main__":
    main()
