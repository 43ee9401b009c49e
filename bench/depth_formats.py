"""Depth in a LeRobot dataset (lerobot 0.6.1's native depth): what each representation costs on
disk, what precision it keeps, and which of lerobot's dataset tools keep it.

Records real MuJoCo depth (panda-play `lift`, `front` camera, 64x48) with `shiftkit collect`,
then stores it, beside an RGB camera, with lerobot's own writer (`LeRobotDataset.create`,
`add_frame`, `save_episode`, `finalize`) as:
  * `float32_m_image`: an (H, W, 1) `image` depth feature (`info.is_depth_map`, `depth_unit: m`),
    lossless float32 TIFF in metres (shiftkit's default, datasets/depth.py);
  * `uint16_mm_image`: the same in uint16 millimetres (`depth_unit: mm`);
  * `depth_video`: an (H, W, 1) `video` depth feature, lerobot's depth encoder (12-bit log
    quantiser, lossless HEVC gray12le, `video.depth_min/max/shift/use_log` in the feature's info);
  * `gray8_image`: what older shiftkit wrote, an (H, W, 3) uint8 `image` of grey levels
    (`legacy_grey`: 0-2.55 m in 1 cm steps), not a depth feature to lerobot.
For each: bytes per frame on disk (the depth feature alone, and the whole dataset), the maximum and
mean absolute error of the depth read back through `LeRobotDataset(..., depth_output_unit="m")`
against MuJoCo's float depth (over the pixels within 0-2.55 m, and over all pixels), whether
lerobot lists it in `meta.depth_keys`, and whether `delete_episodes`, `split_dataset`,
`aggregate_datasets`, `convert_image_to_video_dataset` and `modify_tasks` succeed, their output
reloads, and what it holds for the depth (depth key, stored as image or video, the last frame's
error). The last line printed is the JSON result (metric: the depth video's maximum error within
0-2.55 m, in mm; goal: half of lerobot's quantisation step at 2.55 m, from its encoder defaults).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import tempfile
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402

NAMES = ["height", "width", "channels"]
KEY = "observation.depth.front"
RANGE_M = 2.55  # the gray8 encoding's range, and the range the errors are reported within


def representations(h: int, w: int) -> dict[str, tuple[dict, bool]]:
    """name -> (depth feature as given to `LeRobotDataset.create`, use_videos)."""
    from shiftkit.datasets.depth import depth_feature

    return {
        "float32_m_image": (depth_feature(h, w, "image", "m"), False),
        "uint16_mm_image": (depth_feature(h, w, "image", "mm"), False),
        "depth_video": (depth_feature(h, w, "video", "m"), True),
        "gray8_image": ({"dtype": "image", "shape": (h, w, 3), "names": NAMES}, False),
    }


def to_frame(name: str, metres: np.ndarray) -> np.ndarray:
    """(H, W) float metres -> the array handed to `add_frame`."""
    from shiftkit.datasets.depth import clean_metres, legacy_grey, to_stored

    if name == "gray8_image":
        return legacy_grey(metres)
    return to_stored(clean_metres(metres), "mm" if name == "uint16_mm_image" else "m")


def to_metres(name: str, value) -> np.ndarray:
    """What `LeRobotDataset(..., depth_output_unit="m")[i][KEY]` returns -> (H, W) float metres."""
    from shiftkit.datasets.depth import legacy_depth_to_metres

    arr = value.numpy()  # (C, H, W)
    if arr.shape[0] == 3:  # grey levels as lerobot hands out an RGB image: floats in [0, 1]
        grey = np.rint(arr.transpose(1, 2, 0) * 255).astype(np.uint8)
        return legacy_depth_to_metres(grey[None])[0, ..., 0]
    return arr[0].astype(np.float32)


def write(root: Path, repo_id: str, name: str, depth: list[np.ndarray]):
    """lerobot's own recording loop; returns the dataset reopened for reading."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    h, w = depth[0].shape[1:]
    feature, videos = representations(h, w)[name]
    features = {
        "observation.state": {"dtype": "float32", "shape": (2,), "names": ["a", "b"]},
        "action": {"dtype": "float32", "shape": (2,), "names": ["a", "b"]},
        "observation.images.front": {"dtype": "image", "shape": (h, w, 3), "names": NAMES},
        KEY: feature,
    }
    rgb = np.full((h, w, 3), 128, np.uint8)
    ds = LeRobotDataset.create(repo_id, 20, features, root=root, use_videos=videos)
    for episode in depth:
        for metres in episode:
            ds.add_frame(
                {
                    "observation.state": np.zeros(2, np.float32),
                    "action": np.zeros(2, np.float32),
                    "observation.images.front": rgb,
                    KEY: to_frame(name, metres),
                    "task": "lift",
                }
            )
        ds.save_episode()
    ds.finalize()
    return load(repo_id, root)


def load(repo_id: str, root: Path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset(repo_id, root=root, video_backend="pyav", depth_output_unit="m")


def sizes(root: Path) -> tuple[int, int]:
    """(bytes of the depth feature, bytes of data and videos) of a dataset on disk: an image
    feature's share of the data parquet files is the sum of its column chunks."""
    import pyarrow.parquet as pq

    depth = sum(p.stat().st_size for p in (root / "videos" / KEY).rglob("*.mp4")) if (root / "videos").exists() else 0
    total = sum(p.stat().st_size for p in root.rglob("*.mp4"))
    for path in (root / "data").rglob("*.parquet"):
        total += path.stat().st_size
        meta = pq.ParquetFile(path).metadata
        for g in range(meta.num_row_groups):
            group = meta.row_group(g)
            for c in range(group.num_columns):
                column = group.column(c)
                if column.path_in_schema == KEY or column.path_in_schema.startswith(KEY + "."):
                    depth += column.total_compressed_size
    return depth, total


def errors_mm(read: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    error = np.abs(read.astype(np.float64) - truth) * 1000
    inside = truth <= RANGE_M
    return {
        "max_error_mm": round(float(error[inside].max()), 3),
        "mean_error_mm": round(float(error[inside].mean()), 3),
        "max_error_mm_all": round(float(error.max()), 1),
        "mean_error_mm_all": round(float(error.mean()), 2),
    }


def tool_results(name: str, ds, work: Path, last_truth: np.ndarray) -> dict[str, dict]:
    """Each of lerobot's dataset tools on `ds`; its output reloaded, the depth of its last frame
    (the source's last frame in every case) compared with MuJoCo's."""
    from lerobot.datasets import dataset_tools as tools
    from lerobot.datasets.aggregate import aggregate_datasets

    rest = list(range(1, ds.meta.total_episodes))  # the episodes after the first

    def aggregate():
        shutil.copytree(ds.root, work / "twin")
        aggregate_datasets(["b/src", "b/twin"], "b/agg", roots=[ds.root, work / "twin"], aggr_root=work / "agg")
        return work / "agg"

    def modify():  # modify_tasks rewrites its dataset in place
        shutil.copytree(ds.root, work / "tasks")
        return tools.modify_tasks(load("b/tasks", work / "tasks"), new_task="push").root

    runs = {
        "delete_episodes": lambda: tools.delete_episodes(ds, [0], output_dir=work / "del", repo_id="b/del").root,
        "split_dataset": lambda: tools.split_dataset(ds, {"a": [0], "b": rest}, output_dir=work / "split")["b"].root,
        "aggregate_datasets": aggregate,
        "convert_image_to_video_dataset": lambda: (
            tools.convert_image_to_video_dataset(ds, work / "video", repo_id="b/video", num_workers=1).root
        ),
        "modify_tasks": modify,
    }
    out = {}
    for tool, run in runs.items():
        if tool == "convert_image_to_video_dataset" and ds.meta.video_keys:
            out[tool] = {"result": "n/a (a video dataset already)"}
            continue
        try:
            loaded = load("b/out", run())
            last = to_metres(name, loaded[len(loaded) - 1][KEY])
            inside = last_truth <= RANGE_M
            out[tool] = {
                "result": "ok",
                "depth_key": KEY in loaded.meta.depth_keys,
                "stored_as": loaded.meta.features[KEY]["dtype"],
                "last_frame_max_error_mm": round(float(np.abs(last - last_truth)[inside].max() * 1000), 3),
            }
        except Exception as exc:  # the point: record what lerobot raises
            out[tool] = {"result": f"{type(exc).__name__}: {str(exc).splitlines()[0][:100] if str(exc) else ''}"}
    return out


def quantisation_step_mm(depth_m: float) -> float:
    """Width (mm) of one code of lerobot's default 12-bit log depth quantiser at `depth_m`."""
    from lerobot.configs.video import (
        DEFAULT_DEPTH_MAX,
        DEFAULT_DEPTH_MIN,
        DEFAULT_DEPTH_SHIFT,
        DEPTH_QMAX,
    )

    span = math.log(DEFAULT_DEPTH_MAX + DEFAULT_DEPTH_SHIFT) - math.log(DEFAULT_DEPTH_MIN + DEFAULT_DEPTH_SHIFT)
    return 1000 * (depth_m + DEFAULT_DEPTH_SHIFT) * span / DEPTH_QMAX


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="short run (< 1 minute)")
    parser.add_argument("--episodes", type=int, default=None)
    args = parser.parse_args()
    from shiftkit.app.collect import CollectConfig, collect

    episodes = max(2, args.episodes or (2 if args.quick else 4))  # split and delete need 2
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        raw, _ = collect(
            CollectConfig(task="lift", episodes=episodes, cameras=("front",), depth=True, out=str(tmp / "raw"))
        )
        depth = [np.load(p) for p in sorted(raw.glob("episode_*/depth/front.npy"))]
        h, w = depth[0].shape[1:]
        frames = sum(len(d) for d in depth)
        truth = np.concatenate(depth).astype(np.float64)
        for name in representations(h, w):
            root = tmp / name / "src"
            ds = write(root, "b/src", name, depth)
            read = np.stack([to_metres(name, ds[i][KEY]) for i in range(len(ds))])
            depth_bytes, total_bytes = sizes(root)
            results[name] = {
                "stored_as": ds.meta.features[KEY]["dtype"],
                "depth_key": KEY in ds.meta.depth_keys,
                "depth_bytes_per_frame": round(depth_bytes / frames),
                "dataset_bytes_per_frame": round(total_bytes / frames),
                **errors_mm(read, truth),
                "tools": tool_results(name, ds, tmp / name, truth[-1]),
            }
    from lerobot.configs.video import DEFAULT_DEPTH_MAX

    inside = float((truth <= RANGE_M).mean())
    # Where the other representations saturate: the depth video at depth_max, uint16 at 65.535 m.
    beyond = {f"{d:g}": round(float((truth > d).mean()), 4) for d in (DEFAULT_DEPTH_MAX, 65.535)}
    goal = quantisation_step_mm(RANGE_M) / 2
    print(
        f"{frames} frames of {w}x{h} MuJoCo depth ({truth.min():.3f}-{truth.max():.3f} m); "
        f"{inside:.1%} of pixels within 0-{RANGE_M} m, beyond {DEFAULT_DEPTH_MAX:g} m / 65.535 m: "
        f"{beyond[f'{DEFAULT_DEPTH_MAX:g}']:.1%} / {beyond['65.535']:.1%}; "
        f"lerobot's depth video step at {RANGE_M} m: {2 * goal:.3f} mm"
    )
    for name, r in results.items():
        ok = [t for t, v in r["tools"].items() if v["result"] == "ok"]
        print(
            f"{name:16s} depth {r['depth_bytes_per_frame']:6d} B/frame (dataset {r['dataset_bytes_per_frame']:6d})"
            f"  within {RANGE_M} m: max {r['max_error_mm']:8.3f} mean {r['mean_error_mm']:7.3f} mm"
            f"  all pixels: max {r['max_error_mm_all']:8.1f} mean {r['mean_error_mm_all']:7.2f} mm"
            f"  depth_keys: {r['depth_key']}  tools ok: {len(ok)}/{len(r['tools'])}"
        )
        for tool, v in r["tools"].items():
            print(f"    {tool:32s} {json.dumps(v)}")
    print(
        json.dumps(
            {
                "bench": "depth_formats",
                "metric": "depth_video_max_error_mm",
                "value": results["depth_video"]["max_error_mm"],
                "goal": round(goal, 3),
                "higher_is_better": False,
                "frames": frames,
                "pixels_within_range": round(inside, 4),
                "pixels_beyond_m": beyond,
                "representations": results,
                "quick": args.quick,
            }
        )
    )


if __name__ == "__main__":
    main()
