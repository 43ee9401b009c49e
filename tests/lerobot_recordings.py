"""Datasets written the way users' data is: by lerobot 0.6.1's own writer.

`write_recording(root, Recording(...))` records episodes with `LeRobotDataset.create` /
`add_frame` / `save_episode` / `finalize` (float32 timestamps `frame_index / fps`, PNG or video
cameras, depth as float32 metres or uint16 millimetres as lerobot stores each), adds lerobot's
language columns with its own annotation writer (`LanguageColumnsWriter`: persistent subtask rows,
event rows on their frames) and, optionally, shiftkit's `meta/cameras.json` (intrinsics per camera,
shared by its RGB and depth features, and extrinsics). `recording(spec)` caches one dataset per
spec for a test session; `recordings()` is a hypothesis strategy over specs. Small images and few
frames keep a dataset to about a second to write.

Every frame's values are a function of (seed, episode, frame), so a test can tell frames apart:
a frame's state, images and depth differ from every other frame's.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

STATE_NAMES = ["ee_x", "ee_y", "ee_z", "gripper"]  # the synthetic recordings' names: stage examples apply
GOAL_NAMES = ["goal_x", "goal_y", "goal_z"]
ACTION_NAMES = ["dx", "dy", "dz", "gripper"]
IMAGE_NAMES = ["height", "width", "channels"]


@dataclass(frozen=True)
class Recording:
    """What a lerobot-written test dataset holds."""

    fps: int = 10
    lengths: tuple[int, ...] = (12, 9)
    cameras: tuple[str, ...] = ("front",)
    """RGB cameras (`observation.images.NAME`)."""
    depth: tuple[str, ...] = ("front",)
    """Depth cameras (`observation.depth.NAME`); a name also in `cameras` shares its metadata."""
    depth_unit: Literal["m", "mm"] = "m"
    """How the depth is handed to lerobot: float32 metres or uint16 millimetres."""
    video: bool = False
    """Cameras as lerobot videos (RGB AV1, depth 12-bit HEVC) instead of PNG / TIFF images."""
    size: tuple[int, int] = (6, 8)
    """Image (height, width); lerobot's video encoders here need at least 16x32."""
    tasks: tuple[str, ...] = ("reach",)
    """Each episode is split into consecutive task segments, one per task (per-frame `task`)."""
    language: bool = True
    """lerobot's language columns: a persistent subtask row per task segment, event rows on some frames."""
    camera_meta: bool = True
    """Write `meta/cameras.json` (intrinsics matching `size`, extrinsics)."""
    final_success: float = 0.8
    """Chance that an episode's last frame is flagged `next.success` (other frames: 0.15 each)."""
    seed: int = 0

    def segments(self, n: int) -> list[tuple[str, int, int]]:
        """The (task, start, end) segments of an n-frame episode."""
        bounds = np.linspace(0, n, len(self.tasks) + 1).round().astype(int)
        return [(t, int(a), int(b)) for t, a, b in zip(self.tasks, bounds[:-1], bounds[1:], strict=True) if b > a]


@dataclass
class Frames:
    """The values `write_recording` hands lerobot for one episode."""

    columns: dict[str, np.ndarray] = field(default_factory=dict)
    tasks: list[str] = field(default_factory=list)


def features(rec: Recording) -> dict[str, dict]:
    """The feature dict a user declares to `LeRobotDataset.create` for `rec`."""
    h, w = rec.size
    camera = "video" if rec.video else "image"
    out = {
        "observation.state": {"dtype": "float32", "shape": (4,), "names": STATE_NAMES},
        "observation.environment_state": {"dtype": "float32", "shape": (3,), "names": GOAL_NAMES},
        "action": {"dtype": "float32", "shape": (4,), "names": ACTION_NAMES},
        "observation.mode": {"dtype": "int64", "shape": (1,), "names": ["mode"]},
        "next.success": {"dtype": "bool", "shape": (1,), "names": None},
        "next.done": {"dtype": "bool", "shape": (1,), "names": None},
        "intervention": {"dtype": "bool", "shape": (1,), "names": None},
    }
    for cam in rec.cameras:
        out[f"observation.images.{cam}"] = {"dtype": camera, "shape": (h, w, 3), "names": IMAGE_NAMES}
    for cam in rec.depth:
        out[f"observation.depth.{cam}"] = {
            "dtype": camera,
            "shape": (h, w, 1),
            "names": IMAGE_NAMES,
            "info": {"is_depth_map": True},  # lerobot records the unit from the first frame's dtype
        }
    return out


def depth_metres(rec: Recording, e: int, t: int, cam: int) -> np.ndarray:
    """The true depth of a frame: a tilted plane 0.4-2.8 m moving with t, a near box; (H, W, 1) metres."""
    h, w = rec.size
    ramp = np.linspace(0.4, 2.4, w, dtype=np.float32)[None, :, None] * np.ones((h, 1, 1), np.float32)
    d = ramp + np.float32(0.013 * t + 0.1 * e + 0.05 * cam)
    d[h // 4 : h // 2 + 1, w // 4 : w // 2 + 1] = np.float32(0.35 + 0.01 * t)
    return d.astype(np.float32)


def episode_frames(rec: Recording, e: int) -> Frames:
    """Episode e's values: seeded, different at every frame."""
    n = rec.lengths[e]
    rng = np.random.default_rng([rec.seed, e])
    h, w = rec.size
    state = np.cumsum(rng.normal(0, 0.01, (n, 4)), axis=0).astype(np.float32)
    state[:, 3] = np.arange(n) % 2  # gripper toggles: a held value differs from an interpolated one
    goal = np.repeat(rng.uniform(-0.1, 0.1, (1, 3)).astype(np.float32), n, axis=0)
    success = rng.random(n) < 0.15
    success[-1] = rng.random() < rec.final_success
    intervention = np.zeros(n, bool)
    if n > 3:
        a = int(rng.integers(0, n - 2))
        intervention[a : a + int(rng.integers(1, 4))] = True
    cols = {
        "observation.state": state,
        "observation.environment_state": goal,
        "action": (np.diff(state, axis=0, append=state[-1:]) + rng.normal(0, 1e-3, (n, 4))).astype(np.float32),
        "observation.mode": (np.arange(n) // 3).astype(np.int64)[:, None],
        "next.success": success[:, None],
        "next.done": (np.arange(n) == n - 1)[:, None],
        "intervention": intervention[:, None],
    }
    for c, cam in enumerate(rec.cameras):
        base = rng.integers(0, 200, (1, h, w, 3), dtype=np.uint8)
        # a different picture per frame (video coding keeps smooth ramps better than noise)
        ramp = (np.arange(n)[:, None, None, None] * 7 + c * 40) % 50
        cols[f"observation.images.{cam}"] = (base + ramp).astype(np.uint8)
    for c, cam in enumerate(rec.depth):
        d = np.stack([depth_metres(rec, e, t, c) for t in range(n)])
        cols[f"observation.depth.{cam}"] = np.rint(d * 1000).astype(np.uint16) if rec.depth_unit == "mm" else d
    tasks = [task for task, a, b in rec.segments(n) for _ in range(a, b)]
    return Frames(cols, tasks)


def write_recording(root: Path, rec: Recording) -> Path:
    """`rec` written by lerobot's writer at `root` (repo id `test/recording`)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset.create("test/recording", rec.fps, features(rec), root=root, use_videos=rec.video)
    for e in range(len(rec.lengths)):
        values = episode_frames(rec, e)
        for t in range(rec.lengths[e]):
            frame = {k: v[t] for k, v in values.columns.items()}
            ds.add_frame({**frame, "task": values.tasks[t]})
        ds.save_episode()
    ds.finalize()
    if rec.language:
        _annotate(root, rec)
    if rec.camera_meta:
        from shiftkit.datasets.camera_meta import write_cameras_file

        write_cameras_file(root, {e: camera_metadata(rec) for e in range(len(rec.lengths))})
    return root


def camera_metadata(rec: Recording) -> dict[str, dict]:
    """Each camera's metadata: intrinsics describing `size`, a pose in the base frame."""
    h, w = rec.size
    out = {}
    for c, cam in enumerate(dict.fromkeys([*rec.cameras, *rec.depth])):
        out[cam] = {
            "intrinsics": {
                "fx": 40.0 + c,
                "fy": 41.0 + c,
                "cx": (w - 1) / 2,
                "cy": (h - 1) / 2,
                "width": w,
                "height": h,
            },
            "extrinsics": {
                "frame": "base",
                "position": [0.5 + c, 0.0, 0.6],
                "rotation": [[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]],
            },
        }
    return out


def _annotate(root: Path, rec: Recording) -> None:
    """lerobot's annotation writer: per episode, a persistent `subtask` row at each task segment's
    first frame and `interjection` event rows on some frames (at those frames' timestamps)."""
    from lerobot.annotations.steerable_pipeline.executor import Executor
    from lerobot.annotations.steerable_pipeline.reader import iter_episodes
    from lerobot.annotations.steerable_pipeline.staging import EpisodeStaging
    from lerobot.annotations.steerable_pipeline.writer import LanguageColumnsWriter

    staging = Path(tempfile.mkdtemp(prefix="annotations-", dir=root.parent))
    records = list(iter_episodes(root))
    for record in records:
        ts = record.frame_timestamps
        rng = np.random.default_rng([rec.seed, record.episode_index, 7])
        persistent = [
            {"role": "assistant", "content": f"now {task}", "style": "subtask", "timestamp": float(ts[a])}
            for task, a, _ in rec.segments(len(ts))
        ]
        events = [
            {"role": "user", "content": f"careful at {t}", "style": "interjection", "timestamp": float(ts[t])}
            for t in sorted(set(rng.integers(0, len(ts), max(1, len(ts) // 4)).tolist()))
        ]
        EpisodeStaging(staging, record.episode_index).write("plan", persistent)
        EpisodeStaging(staging, record.episode_index).write("interjections", events)
    LanguageColumnsWriter().write_all(records, staging, root)
    Executor._ensure_annotation_metadata_in_info(root)


_CACHE: dict[Recording, Path] = {}


def recording(rec: Recording) -> Path:
    """`rec` written once per test session (in a temporary folder); treat it as read-only. lerobot's
    encoder leaves this thread real-time where it runs as root (`video.scheduling_kept` undoes it)."""
    from shiftkit.datasets.video import scheduling_kept

    if rec not in _CACHE:
        with scheduling_kept():
            _CACHE[rec] = write_recording(Path(tempfile.mkdtemp(prefix="recording-")) / "ds", rec)
    return _CACHE[rec]


def recordings():
    """A hypothesis strategy over small recordings: fps, episode lengths (1 frame up), one or two
    RGB cameras, depth in both units on a shared or a camera of its own, image or video storage,
    one to three task segments, language columns."""
    from hypothesis import strategies as st

    @st.composite
    def draw(draw) -> Recording:
        video = draw(st.sampled_from([False, False, False, True]))
        cameras = draw(st.sampled_from([(), ("front",), ("front", "wrist")]))
        depth = draw(st.sampled_from([(), ("front",), ("side",)]))
        # lerobot's video writer fails now and then on 1-frame episodes at these sizes (PyAV's
        # PatchWelcomeError when appending one): video episodes have 4 frames or more
        shortest = 4 if video else 1
        return Recording(
            fps=draw(st.sampled_from([5, 10, 15, 20, 30])),
            lengths=tuple(draw(st.lists(st.integers(shortest, 40), min_size=1, max_size=3))),
            cameras=cameras,
            depth=depth,
            depth_unit=draw(st.sampled_from(["m", "mm"])),
            video=video and bool(cameras or depth),
            size=(16, 32) if video else (6, 8),
            tasks=draw(st.sampled_from([("reach",), ("reach", "grasp"), ("reach", "grasp", "lift")])),
            language=draw(st.booleans()),
            camera_meta=draw(st.booleans()),
            seed=draw(st.integers(0, 3)),
        )

    return draw()
