"""`shiftkit import lerobot-v2.1`: a LeRobot v2.1 dataset (written here in the v2.1 layout that
lerobot's converter reads) becomes a v3.0 dataset in a new directory through lerobot's own
converter; the source stays byte-identical and in place."""

from __future__ import annotations

import hashlib
import io
import json

import numpy as np
import pytest
from PIL import Image

from shiftkit.app.cli import main
from shiftkit.app.importing import import_dataset
from shiftkit.datasets.reader import open_lerobot_dataset

FPS = 10
EPISODES = [("pick", 3), ("place", 4)]
FEATURES = {
    "observation.state": {"dtype": "float32", "shape": (3,), "names": ["x", "y", "z"]},
    "action": {"dtype": "float32", "shape": (2,), "names": ["dx", "dy"]},
    "observation.images.front": {"dtype": "image", "shape": (4, 5, 3), "names": ["height", "width", "channel"]},
    "timestamp": {"dtype": "float32", "shape": (1,), "names": None},
    "frame_index": {"dtype": "int64", "shape": (1,), "names": None},
    "episode_index": {"dtype": "int64", "shape": (1,), "names": None},
    "index": {"dtype": "int64", "shape": (1,), "names": None},
    "task_index": {"dtype": "int64", "shape": (1,), "names": None},
}


def _episode(e: int, n: int, start: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(e)
    return {
        "observation.state": rng.normal(size=(n, 3)).astype(np.float32),
        "action": rng.normal(size=(n, 2)).astype(np.float32),
        "observation.images.front": rng.integers(0, 256, (n, 4, 5, 3), dtype=np.uint8),
        "timestamp": (np.arange(n) / FPS).astype(np.float32),
        "frame_index": np.arange(n, dtype=np.int64),
        "episode_index": np.full(n, e, dtype=np.int64),
        "index": np.arange(start, start + n, dtype=np.int64),
        "task_index": np.full(n, e, dtype=np.int64),
    }


def _stats(key: str, values: np.ndarray) -> dict[str, list]:
    if key == "observation.images.front":  # v2.1: per channel, (3, 1, 1), scaled to [0, 1]
        v = values.reshape(-1, 3).astype(np.float64) / 255.0
        s = {
            k: f(v, axis=0).reshape(3, 1, 1)
            for k, f in (("min", np.min), ("max", np.max), ("mean", np.mean), ("std", np.std))
        }
    else:
        v = values.reshape(len(values), -1).astype(np.float64)
        s = {k: f(v, axis=0) for k, f in (("min", np.min), ("max", np.max), ("mean", np.mean), ("std", np.std))}
    return {**{k: a.tolist() for k, a in s.items()}, "count": [len(values)]}


def _png(frame: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(frame).save(buf, format="PNG")
    return buf.getvalue()


VIDEO_KEY = "observation.images.front"
VIDEO = {"dtype": "video", "shape": (64, 64, 3), "names": ["height", "width", "channel"]}


def _video_frames(e: int, n: int) -> np.ndarray:
    """Flat frames (lossy AV1 keeps flat colours within a few levels)."""
    return np.stack([np.full((64, 64, 3), (40 * t + 60 * e, 100, 200 - 30 * t), np.uint8) for t in range(n)])


def _write_v21(root, video=False):
    """meta/{info.json, episodes.jsonl, tasks.jsonl, episodes_stats.jsonl} + data/chunk-000/episode_*.parquet,
    the data written as lerobot v2.1 did (a `datasets.Dataset` with lerobot's HF features, to_parquet);
    with `video`, the camera is an AV1 video per episode (videos/chunk-000/<key>/episode_*.mp4) encoded
    with lerobot's own encoder."""
    from lerobot.datasets.feature_utils import get_hf_features_from_features
    from lerobot.datasets.video_utils import encode_video_frames

    from datasets import Dataset

    features = {**FEATURES, "observation.images.front": VIDEO} if video else FEATURES
    (root / "meta").mkdir(parents=True)
    (root / "data" / "chunk-000").mkdir(parents=True)
    hf_features = get_hf_features_from_features(features)
    start = 0
    episodes, stats = [], []
    for e, (task, n) in enumerate(EPISODES):
        data = _episode(e, n, start)
        columns = {k: list(v) if v.ndim > 1 else v for k, v in data.items()}
        if video:
            data["observation.images.front"] = _video_frames(e, n)
            del columns["observation.images.front"]
            frames_dir = root.parent / f"frames_{e}"
            frames_dir.mkdir()
            for t, frame in enumerate(data["observation.images.front"]):
                Image.fromarray(frame).save(frames_dir / f"frame-{t:06d}.png")
            encode_video_frames(frames_dir, root / "videos" / "chunk-000" / VIDEO_KEY / f"episode_{e:06d}.mp4", FPS)
        else:
            columns[VIDEO_KEY] = [{"bytes": _png(f), "path": None} for f in data[VIDEO_KEY]]
        Dataset.from_dict(columns, features=hf_features).to_parquet(
            root / "data" / "chunk-000" / f"episode_{e:06d}.parquet"
        )
        episodes.append({"episode_index": e, "tasks": [task], "length": n})
        stats.append({"episode_index": e, "stats": {k: _stats(k, v) for k, v in data.items()}})
        start += n
    info = {
        "codebase_version": "v2.1",
        "robot_type": "test_arm",
        "total_episodes": len(EPISODES),
        "total_frames": start,
        "total_tasks": len(EPISODES),
        "total_videos": len(EPISODES) if video else 0,
        "total_chunks": 1,
        "chunks_size": 1000,
        "fps": FPS,
        "splits": {"train": f"0:{len(EPISODES)}"},
        "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet",
        "video_path": "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4" if video else None,
        "features": {k: {**v, "shape": list(v["shape"])} for k, v in features.items()},
    }
    (root / "meta" / "info.json").write_text(json.dumps(info, indent=4))
    jsonl = {
        "episodes.jsonl": episodes,
        "tasks.jsonl": [{"task_index": e, "task": t} for e, (t, _) in enumerate(EPISODES)],
        "episodes_stats.jsonl": stats,
    }
    for name, rows in jsonl.items():
        (root / "meta" / name).write_text("".join(json.dumps(r) + "\n" for r in rows))
    return root


def _tree(root):
    """Every file under root with its bytes' hash (names and contents)."""
    return {
        p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def test_v21_dataset_converts_into_a_new_directory(tmp_path, capsys):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    src = _write_v21(tmp_path / "src" / "old_ds")
    before = _tree(src)
    args = ["import", "lerobot-v2.1", str(src), "--repo-id", "me/new_ds", "--root", str(tmp_path / "out")]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "old_ds: converted" in out and "wrote 2 episodes, 7 frames at 10 fps" in out
    assert _tree(src) == before, "the source must stay byte-identical"
    assert sorted(p.name for p in (tmp_path / "src").iterdir()) == ["old_ds"], "nothing renamed or added beside it"

    ds = LeRobotDataset("me/new_ds", root=tmp_path / "out")
    assert ds.meta.info.codebase_version == "v3.0"
    assert (ds.num_episodes, len(ds), ds.fps) == (2, 7, FPS)
    assert ds.meta.robot_type == "test_arm"
    assert ds.meta.tasks.index.tolist() == ["pick", "place"]
    item = ds[4]  # episode 1, frame 1
    expected = _episode(1, 4, 3)
    np.testing.assert_array_equal(item["observation.state"].numpy(), expected["observation.state"][1])
    assert item["task"] == "place"
    front = (item["observation.images.front"].numpy() * 255).round().astype(np.uint8)  # lerobot gives CHW floats
    np.testing.assert_array_equal(front.transpose(1, 2, 0), expected["observation.images.front"][1])

    # shiftkit reads it too (pipelines can run on it), with its provenance naming the source
    eps = list(open_lerobot_dataset(tmp_path / "out").iter_episodes())
    np.testing.assert_array_equal(eps[0].frames["action"], _episode(0, 3, 0)["action"])
    provenance = json.loads((tmp_path / "out" / "meta" / "shiftkit_provenance.json").read_text())
    assert provenance["sources"][0]["kind"] == "lerobot-v2.1" and provenance["sources"][0]["path"] == str(src)

    assert main(args) == 2  # the destination now exists
    assert "destination already exists" in capsys.readouterr().err
    assert _tree(src) == before


def test_v21_video_dataset_converts(tmp_path):
    """Most Hub datasets keep cameras as videos: the converter concatenates them per camera."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    src = _write_v21(tmp_path / "src" / "vid", video=True)
    before = _tree(src)
    dataset = import_dataset("lerobot-v2.1", {"source": str(src)}, "me/vid", tmp_path / "out")
    assert (dataset.num_episodes, dataset.info["total_frames"]) == (2, 7)
    assert _tree(src) == before
    assert sorted(p.relative_to(tmp_path / "out").as_posix() for p in (tmp_path / "out").glob("videos/**/*.mp4")) == [
        "videos/observation.images.front/chunk-000/file-000.mp4"
    ]
    ds = LeRobotDataset("me/vid", root=tmp_path / "out", video_backend="pyav")
    assert ds.meta.features["observation.images.front"]["dtype"] == "video"
    for index, episode, frame in ((0, 0, 0), (2, 0, 2), (6, 1, 3)):  # episode 0 frames 0 and 2, episode 1 frame 3
        decoded = ds[index][VIDEO_KEY].numpy().transpose(1, 2, 0) * 255
        expected = _video_frames(episode, frame + 1)[frame]
        assert np.abs(decoded - expected).mean() < 4, index  # neighbouring frames differ by ~23


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda r: (r / "meta" / "episodes_stats.jsonl").unlink(), "missing ['meta/episodes_stats.jsonl']"),
        (
            lambda r: (r / "meta" / "info.json").write_text(
                (r / "meta" / "info.json").read_text().replace('"v2.1"', '"v3.0"')
            ),
            "codebase_version 'v3.0', this importer converts v2.1",
        ),
        (lambda r: (r / "meta" / "info.json").write_text("{"), "invalid JSON"),
        (
            lambda r: (r / "data" / "chunk-000" / "episode_000001.parquet").write_bytes(b"not parquet"),
            "lerobot's v2.1 -> v3.0 converter failed",
        ),
    ],
)
def test_bad_sources_are_one_line_errors(tmp_path, capsys, damage, message):
    src = _write_v21(tmp_path / "src")
    damage(src)
    before = _tree(src)
    capsys.readouterr()
    assert main(["import", "lerobot-v2.1", str(src), "--repo-id", "a/b", "--root", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    # lerobot's converter may have drawn progress bars before it failed; the error is one line
    last = err.strip().splitlines()[-1]
    assert last.startswith("shiftkit import: error:") and message in last and "Traceback" not in err, err
    assert _tree(src) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src"], "no destination, no partial directory"


def test_destination_inside_source_is_refused(tmp_path):
    src = _write_v21(tmp_path / "src")
    from shiftkit.datasets.errors import ShiftkitError

    with pytest.raises(ShiftkitError, match="lies inside the input source"):
        import_dataset("lerobot-v2.1", {"source": str(src)}, "a/b", src / "converted")
    assert not (src / "converted").exists()
