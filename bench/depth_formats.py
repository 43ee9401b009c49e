"""Depth representations in a LeRobot dataset: which of lerobot's dataset tools accept them, what
they cost on disk and what precision they keep.

Records real MuJoCo depth (panda-play `lift`, `front` camera, 64x48) with `shiftkit collect`,
then stores it, beside an RGB camera, with lerobot's own writer (`add_frame`/`save_episode`) as:
  * `float32_hw1`: float32 (H, W, 1) metres (what shiftkit wrote before);
  * `uint16_mm_hw1`: uint16 (H, W, 1) millimetres;
  * `float32_flat`: float32 (H*W,) metres, a plain vector;
  * `gray8_image`: the chosen encoding (pipelines/depth.py), an `image` (H, W, 3);
  * `gray8_video`: the same as a lerobot video (AV1, lerobot's encoder settings).
For each: the bytes per frame, the error of the depth read back through `LeRobotDataset` against
the rendered metres (pixels inside the encoding's range), and whether `delete_episodes`,
`split_dataset`, `aggregate_datasets`, `convert_image_to_video_dataset` and `modify_tasks`
succeed and their output loads. The last line printed is the JSON result (metric: the worst
error of the chosen image encoding, goal: half a grey level).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402

NAMES = ["height", "width", "channels"]


def representations(h: int, w: int) -> dict[str, tuple[dict, bool]]:
    """name -> (feature, use_videos)."""
    return {
        "float32_hw1": ({"dtype": "float32", "shape": (h, w, 1), "names": NAMES}, False),
        "uint16_mm_hw1": ({"dtype": "uint16", "shape": (h, w, 1), "names": NAMES}, False),
        "float32_flat": ({"dtype": "float32", "shape": (h * w,), "names": None}, False),
        "gray8_image": ({"dtype": "image", "shape": (h, w, 3), "names": NAMES}, False),
        "gray8_video": ({"dtype": "video", "shape": (h, w, 3), "names": NAMES}, True),
    }


def to_feature(name: str, metres: np.ndarray) -> np.ndarray:
    from shiftkit.pipelines.depth import encode_depth

    if name == "float32_hw1":
        return metres[..., None].astype(np.float32)
    if name == "uint16_mm_hw1":
        return np.clip(np.rint(metres * 1000), 0, 65535).astype(np.uint16)[..., None]
    if name == "float32_flat":
        return metres.reshape(-1).astype(np.float32)
    return encode_depth(metres)


def from_item(name: str, value, h: int, w: int) -> np.ndarray:
    from shiftkit.pipelines.depth import decode_depth

    arr = value.numpy()
    if name == "float32_hw1":
        return arr.reshape(h, w)
    if name == "uint16_mm_hw1":
        return arr.reshape(h, w).astype(np.float32) / 1000
    if name == "float32_flat":
        return arr.reshape(h, w)
    return decode_depth(np.rint(arr.transpose(1, 2, 0) * 255).astype(np.uint8))


def write(root: Path, repo_id: str, name: str, depth: list[np.ndarray], state_dim: int = 2):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    h, w = depth[0].shape[1:]
    feature, videos = representations(h, w)[name]
    features = {
        "observation.state": {"dtype": "float32", "shape": (state_dim,), "names": ["a", "b"]},
        "action": {"dtype": "float32", "shape": (state_dim,), "names": ["a", "b"]},
        "observation.images.front": {"dtype": "image", "shape": (h, w, 3), "names": NAMES},
        "observation.depth.front": feature,
    }
    rgb = np.full((h, w, 3), 128, np.uint8)
    ds = LeRobotDataset.create(repo_id, 20, features, root=root, use_videos=videos)
    for episode in depth:
        for metres in episode:
            ds.add_frame(
                {
                    "observation.state": np.zeros(state_dim, np.float32),
                    "action": np.zeros(state_dim, np.float32),
                    "observation.images.front": rgb,
                    "observation.depth.front": to_feature(name, metres),
                    "task": "lift",
                }
            )
        ds.save_episode()
    ds.finalize()
    return LeRobotDataset(repo_id, root=root, video_backend="pyav")


def tool_results(ds, work: Path) -> dict[str, str]:
    from lerobot.datasets import dataset_tools as tools
    from lerobot.datasets.aggregate import aggregate_datasets
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    def aggregate():
        shutil.copytree(ds.root, work / "twin")
        aggregate_datasets(["b/src", "b/twin"], "b/agg", roots=[ds.root, work / "twin"], aggr_root=work / "agg")
        return work / "agg"

    def modify():
        shutil.copytree(ds.root, work / "tasks")
        return tools.modify_tasks(LeRobotDataset("b/tasks", root=work / "tasks"), new_task="push").root

    runs = {
        "delete_episodes": lambda: tools.delete_episodes(ds, [0], output_dir=work / "del", repo_id="b/del").root,
        "split_dataset": lambda: tools.split_dataset(ds, {"a": [0], "b": [1]}, output_dir=work / "split")["b"].root,
        "aggregate_datasets": aggregate,
        "convert_image_to_video_dataset": lambda: (
            tools.convert_image_to_video_dataset(ds, work / "video", repo_id="b/video", num_workers=1).root
        ),
        "modify_tasks": modify,
    }
    out = {}
    for tool, run in runs.items():
        try:
            root = run()
            loaded = LeRobotDataset("b/out", root=root, video_backend="pyav")
            loaded[len(loaded) - 1]
            out[tool] = "ok"
        except Exception as exc:  # the point: record what lerobot raises
            out[tool] = f"{type(exc).__name__}: {str(exc).splitlines()[0][:80] if str(exc) else ''}"
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="short run (< 1 minute)")
    parser.add_argument("--episodes", type=int, default=None)
    args = parser.parse_args()
    from shiftkit.pipelines.depth import DEFAULT_ENCODING
    from shiftkit.pipelines.sources.simulator import CollectConfig, collect

    episodes = args.episodes or (2 if args.quick else 4)
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        raw, _ = collect(
            CollectConfig(task="lift", episodes=episodes, cameras=("front",), depth=True, out=str(tmp / "raw"))
        )
        depth = [np.load(p) for p in sorted(raw.glob("episode_*/depth/front.npy"))]
        h, w = depth[0].shape[1:]
        frames = sum(len(d) for d in depth)
        truth = np.concatenate(depth)
        inside = truth <= DEFAULT_ENCODING["far"]
        for name in representations(h, w):
            root = tmp / name / "src"
            ds = write(root, "b/src", name, depth)
            size = sum(p.stat().st_size for p in root.rglob("*") if p.suffix in (".parquet", ".mp4"))
            size -= sum(p.stat().st_size for p in (root / "meta").rglob("*.parquet"))
            read = np.stack([from_item(name, ds[i]["observation.depth.front"], h, w) for i in range(len(ds))])
            error_mm = np.abs(read - truth)[inside] * 1000
            results[name] = {
                "bytes_per_frame": round(size / frames),
                "max_error_mm": round(float(error_mm.max()), 2),
                "mean_error_mm": round(float(error_mm.mean()), 3),
                "tools": tool_results(ds, tmp / name),
            }
    print(f"{frames} frames of {w}x{h} depth; errors over the {inside.mean():.0%} of pixels within 0-2.55 m")
    for name, r in results.items():
        ok = [t for t, v in r["tools"].items() if v == "ok"]
        print(
            f"{name:14s} {r['bytes_per_frame']:6d} B/frame  max err {r['max_error_mm']:8.2f} mm  "
            f"mean {r['mean_error_mm']:7.3f} mm  tools ok: {len(ok)}/{len(r['tools'])}"
        )
        for tool, v in r["tools"].items():
            if v != "ok":
                print(f"    {tool}: {v}")
    print(
        json.dumps(
            {
                "bench": "depth_formats",
                "metric": "gray8_image_max_error_mm",
                "value": results["gray8_image"]["max_error_mm"],
                "goal": round(1000 * (DEFAULT_ENCODING["far"] - DEFAULT_ENCODING["near"]) / 255 / 2, 2),
                "higher_is_better": False,
                "frames": frames,
                "representations": results,
                "quick": args.quick,
            }
        )
    )


if __name__ == "__main__":
    main()
