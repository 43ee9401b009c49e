"""Raw episode format v1: what a teleop recorder, a kinesthetic-teaching logger or `shiftkit collect`
writes before any stage runs. Documented in docs/raw_format.md.

Layout::

    DIR/dataset.json                    {"format": "shiftkit-raw", "version": 1, fps, robot, env,
                                         names, episodes: [{"name", "length", "task"}]}
    DIR/episode_000000/meta.json        task, outcome, seed, segments, labels, sim_model, ...
    DIR/episode_000000/arrays/NAME.npy  per-frame arrays, first axis = frame
    DIR/episode_000000/images/CAM/frame_000000.png   RGB frames (one PNG per frame)
    DIR/episode_000000/depth/CAM.npy    (T, H, W) float32 metres (read as lerobot's native depth
                                        feature, see datasets/depth.py)

Every array and image is checked on read (lengths, dtypes, NaNs, missing frames) and a problem is
reported as one line naming the file. `.npy` and PNG bytes are deterministic, so the same
recording gives the same files.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from shiftkit.datasets.camera_meta import check_cameras, merge_cameras
from shiftkit.datasets.depth import clean_metres, depth_feature
from shiftkit.datasets.encoded_frames import EncodedFrames
from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import DatasetError
from shiftkit.datasets.features import Features, flag_array, image_feature, vector_feature
from shiftkit.datasets.jsonutil import dumps, read_json_file
from shiftkit.datasets.staging import publish, remove_dead_staging, staging_path

FORMAT = "shiftkit-raw"
VERSION = 1

# Standard raw arrays and the LeRobot feature each becomes. Any other array keeps its own name.
FEATURE_OF_ARRAY = {
    "action": "action",
    "state": "observation.state",
    "environment_state": "observation.environment_state",
    "ee_pose": "observation.ee_pose",
    "joint_positions": "observation.joint_positions",
    "gripper": "observation.gripper",
    "wrench_raw": "observation.wrench",
    "success": "next.success",
    "sim_qpos": "sim.qpos",
    "sim_qvel": "sim.qvel",
    "sim_act": "sim.act",
}
DEFAULT_NAMES = {
    "ee_pose": ["x", "y", "z", "qx", "qy", "qz", "qw"],
    "wrench_raw": ["Fx", "Fy", "Fz", "tau_z"],
}
REQUIRED_ARRAYS = ("timestamp", "action")
ALLOWED_DTYPES = {"float32", "float64", "int64", "int32", "bool", "uint8"}


def _camera_feature(name: str) -> str:
    return f"observation.images.{name}"


def _depth_feature(name: str) -> str:
    return f"observation.depth.{name}"


def _check_name(name: str, what: str) -> None:
    if not name or "/" in name or name.startswith(".") or not name.replace("_", "a").replace(".", "a").isalnum():
        raise DatasetError(f"invalid {what} name {name!r}: use letters, digits, '_' and '.'")


class RawDatasetWriter:
    """Writes raw episodes; use as a context manager.

    The dataset is built in a temporary sibling directory and renamed to `out_dir` when the `with`
    block ends without an error, so a crashed recorder leaves nothing half-written at `out_dir`.
    """

    def __init__(
        self,
        out_dir: str | Path,
        fps: int,
        robot: str = "",
        env: str = "",
        names: dict[str, list[str]] | None = None,
        info: dict[str, Any] | None = None,
    ) -> None:
        self.out_dir = Path(out_dir)
        if self.out_dir.exists():
            raise DatasetError(f"output directory already exists: {self.out_dir}")
        if not isinstance(fps, int) or fps <= 0:
            raise DatasetError(f"fps must be a positive integer, got {fps!r}")
        self.fps = fps
        self.robot = robot
        self.env = env
        self.names = {k: list(v) for k, v in (names or {}).items()}
        self.info = dict(info or {})
        self._tmp = staging_path(self.out_dir)
        self._episodes: list[dict[str, Any]] = []
        self._layout: dict[str, Any] | None = None

    def __enter__(self) -> RawDatasetWriter:
        remove_dead_staging(self.out_dir)
        self._tmp.mkdir(parents=True)
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None and self._episodes:
            try:
                self._write_index()
            except BaseException:
                shutil.rmtree(self._tmp, ignore_errors=True)
                raise
            publish(self._tmp, self.out_dir)
        else:
            shutil.rmtree(self._tmp, ignore_errors=True)
            if exc_type is None:
                raise DatasetError(f"no episodes were added to {self.out_dir}")

    def add_episode(
        self,
        arrays: dict[str, np.ndarray],
        images: dict[str, np.ndarray] | None = None,
        depth: dict[str, np.ndarray] | None = None,
        meta: dict[str, Any] | None = None,
    ) -> None:
        """Add one episode. `arrays` needs `timestamp` (T,) and `action` (T, A); `images[cam]` is
        (T, H, W, 3) uint8 RGB, `depth[cam]` (T, H, W) float32; `meta` needs `task`."""
        if not self._tmp.exists():
            raise RuntimeError("RawDatasetWriter.add_episode outside its `with` block")
        images, depth, meta = images or {}, depth or {}, dict(meta or {})
        index = len(self._episodes)
        where = f"episode {index}"
        if not isinstance(meta.get("task"), str) or not meta["task"]:
            raise DatasetError(f"{where}: meta['task'] must be a non-empty string")
        if "cameras" in meta:
            check_cameras(meta["cameras"], f"{where}: meta")
        arrays = {k: np.asarray(v) for k, v in arrays.items()}
        validate_arrays(arrays, where)
        length = len(arrays["timestamp"])
        layout = {
            "arrays": {k: [str(v.dtype), list(v.shape[1:])] for k, v in sorted(arrays.items())},
            "images": {k: list(np.shape(v)[1:]) for k, v in sorted(images.items())},
            "depth": {k: list(np.shape(v)[1:]) for k, v in sorted(depth.items())},
        }
        if self._layout is None:
            self._layout = layout
        elif layout != self._layout:
            raise DatasetError(f"{where}: arrays/cameras differ from episode 0 ({layout} vs {self._layout})")

        ep_dir = self._tmp / f"episode_{index:06d}"
        (ep_dir / "arrays").mkdir(parents=True)
        for name, arr in arrays.items():
            _check_name(name, "array")
            np.save(ep_dir / "arrays" / f"{name}.npy", arr, allow_pickle=False)
        for cam, frames in images.items():
            _check_name(cam, "camera")
            frames = np.asarray(frames)
            if frames.dtype != np.uint8 or frames.ndim != 4 or frames.shape[-1] != 3 or len(frames) != length:
                raise DatasetError(
                    f"{where}: images[{cam!r}] must be ({length}, H, W, 3) uint8, got {frames.shape} {frames.dtype}"
                )
            cam_dir = ep_dir / "images" / cam
            cam_dir.mkdir(parents=True)
            for t, frame in enumerate(frames):
                _write_png(cam_dir / f"frame_{t:06d}.png", frame)
        for cam, d in depth.items():
            _check_name(cam, "camera")
            d = np.asarray(d, dtype=np.float32)
            if d.ndim != 3 or len(d) != length:
                raise DatasetError(f"{where}: depth[{cam!r}] must be ({length}, H, W), got {d.shape}")
            (ep_dir / "depth").mkdir(exist_ok=True)
            np.save(ep_dir / "depth" / f"{cam}.npy", d, allow_pickle=False)
        meta["length"] = length
        (ep_dir / "meta.json").write_text(dumps(meta, indent=1))
        self._episodes.append({"name": ep_dir.name, "length": length, "task": meta["task"]})

    def _write_index(self) -> None:
        index = {
            "format": FORMAT,
            "version": VERSION,
            "fps": self.fps,
            "robot": self.robot,
            "env": self.env,
            "names": self.names,
            "info": self.info,
            "episodes": self._episodes,
        }
        (self._tmp / "dataset.json").write_text(dumps(index, indent=1))


def validate_arrays(arrays: dict[str, np.ndarray], where: str) -> None:
    """Check one episode's arrays (required ones present, equal lengths, allowed dtypes, finite, at
    most 2-D); a DatasetError names the first problem."""
    for name in REQUIRED_ARRAYS:
        if name not in arrays:
            raise DatasetError(f"{where}: required array {name!r} is missing")
    if np.ndim(arrays["timestamp"]) != 1:
        raise DatasetError(f"{where}: 'timestamp' must be a 1-D float array of seconds")
    length = len(arrays["timestamp"])
    if length == 0:
        raise DatasetError(f"{where}: episode has no frames")
    for name, arr in arrays.items():
        if arr.ndim == 0 or len(arr) != length:
            raise DatasetError(
                f"{where}: array {name!r} has {len(arr) if arr.ndim else 0} frames, 'timestamp' has {length}"
            )
        if str(arr.dtype) not in ALLOWED_DTYPES:
            raise DatasetError(f"{where}: array {name!r} has unsupported dtype {arr.dtype}")
        if arr.ndim > 2:
            raise DatasetError(f"{where}: array {name!r} must be (T,) or (T, D), got {arr.shape}")
        if arr.dtype.kind == "f" and not np.isfinite(arr).all():
            raise DatasetError(f"{where}: array {name!r} contains NaN/inf")
    ts = arrays["timestamp"]
    if ts.ndim != 1 or ts.dtype.kind != "f":
        raise DatasetError(f"{where}: 'timestamp' must be a 1-D float array of seconds")
    if length > 1 and not (np.diff(ts) > 0).all():
        raise DatasetError(f"{where}: timestamps are not strictly increasing")


@dataclass
class RawDataset:
    """A validated raw dataset on disk; episodes are read one at a time."""

    root: Path
    index: dict[str, Any]

    @property
    def fps(self) -> int:
        """Frames per second."""
        return int(self.index["fps"])

    @property
    def num_episodes(self) -> int:
        """Number of episodes."""
        return len(self.index["episodes"])

    def episode_dir(self, i: int) -> Path:
        """Folder of episode `i`."""
        return self.root / self.index["episodes"][i]["name"]

    def features(self) -> Features:
        """The dataset's features, from the first episode's files."""
        ep = self.episode_dir(0)
        arrays = {p.stem: _load_npy(p, mmap=True) for p in sorted((ep / "arrays").glob("*.npy"))}
        images = {d.name: _read_png(d / "frame_000000.png")[None] for d in _children(ep / "images")}
        depth = {p.stem: _load_npy(p, mmap=True) for p in sorted((ep / "depth").glob("*.npy"))}
        return raw_features(arrays, images, depth, self.index.get("names", {}), f"{self.root}/dataset.json")

    def read_episode(self, i: int) -> Episode:
        """Episode `i`, validated."""
        ep = self.episode_dir(i)
        where = f"{ep}"
        meta = read_json_file(ep / "meta.json", "episode metadata")
        if not isinstance(meta, dict):
            raise DatasetError(f"{ep}/meta.json: expected an object")
        arrays = {path.stem: _load_npy(path) for path in sorted((ep / "arrays").glob("*.npy"))}
        validate_arrays(arrays, where)
        length = len(arrays["timestamp"])
        if meta.get("length", length) != length:
            raise DatasetError(f"{where}: meta.json says {meta['length']} frames, arrays have {length}")
        images = {}
        for cam_dir in _children(ep / "images"):
            files = sorted(cam_dir.glob("frame_*.png"))
            if len(files) != length:
                raise DatasetError(f"{cam_dir}: {len(files)} image files for {length} frames")
            images[cam_dir.name] = _read_camera(files)
        depth = {path.stem: _load_npy(path) for path in sorted((ep / "depth").glob("*.npy"))}
        for name, d in depth.items():
            if d.ndim != 3 or len(d) != length:
                raise DatasetError(f"{ep / 'depth' / name}.npy: {len(d)} depth frames for {length} frames")
        return raw_episode(arrays, images, depth, meta, i, self.index.get("info", {}).get("cameras"), where)

    def iter_episodes(self, indices: list[int] | None = None) -> Iterator[Episode]:
        """The episodes at `indices` (default: all), read one at a time."""
        for i in range(self.num_episodes) if indices is None else indices:
            yield self.read_episode(i)


def raw_features(
    arrays: dict[str, np.ndarray],
    images: dict[str, np.ndarray],
    depth: dict[str, np.ndarray],
    names: dict[str, list[str]],
    where: str,
) -> Features:
    """The LeRobot features of a raw episode's arrays, camera frames (T, H, W, 3) and depth
    (T, H, W): those of a raw dataset on disk and of episodes recorded straight into LeRobot."""
    features: Features = {}
    for name, arr in sorted(arrays.items()):
        if name == "timestamp":
            continue
        dim = arr.shape[1] if arr.ndim == 2 else 1
        dims = (
            names.get(name)
            or DEFAULT_NAMES.get(name)
            or ([name] if arr.ndim == 1 else [f"{name}_{i}" for i in range(dim)])
        )
        if len(dims) != dim:
            raise DatasetError(f"{where}: names[{name!r}] has {len(dims)} entries for {dim} dims")
        features[FEATURE_OF_ARRAY.get(name, name)] = vector_feature(str(arr.dtype), dims)
    for cam, frames in sorted(images.items()):
        features[_camera_feature(cam)] = image_feature(np.shape(frames)[1:])
    for cam, d in sorted(depth.items()):
        if np.ndim(d) != 3:
            raise DatasetError(f"{where}: depth {cam!r} must be (T, H, W), got {np.shape(d)}")
        features[_depth_feature(cam)] = depth_feature(d.shape[1], d.shape[2])  # metres, lerobot's native depth
    return features


def raw_episode(
    arrays: dict[str, np.ndarray],
    images: dict[str, np.ndarray],
    depth: dict[str, np.ndarray],
    meta: dict[str, Any],
    index: int,
    dataset_cameras: dict[str, Any] | None,
    where: str,
) -> Episode:
    """A raw episode (validated arrays, camera frames, depth in metres, JSON metadata) as the
    pipeline's `Episode`: the one conversion for episodes read from disk and recorded in memory."""
    if not isinstance(meta.get("task"), str):
        raise DatasetError(f"{where}/meta.json: 'task' must be a string")
    length = len(arrays["timestamp"])
    ts = arrays["timestamp"].astype(np.float64)
    frames: dict[str, np.ndarray] = {"timestamp": ts - ts[0]}
    for name, arr in arrays.items():
        if name != "timestamp":
            frames[FEATURE_OF_ARRAY.get(name, name)] = arr if arr.ndim == 2 else arr.reshape(-1, 1)
    if "next.success" in frames:
        frames["next.success"] = flag_array(frames["next.success"], f"{where}/arrays/success.npy")
    for cam, cam_frames in sorted(images.items()):
        frames[_camera_feature(cam)] = cam_frames
    cameras = check_cameras(merge_cameras(dataset_cameras, meta.get("cameras")), f"{where}/meta.json")
    for cam, d in sorted(depth.items()):
        frames[_depth_feature(cam)] = clean_metres(np.asarray(d, dtype=np.float32))
    frames["task"] = _frame_tasks(meta, length, where)
    episode_meta = {k: v for k, v in meta.items() if k != "length"}
    episode_meta["source_episode_index"] = index
    if cameras:
        episode_meta["cameras"] = cameras
    return Episode(frames, episode_meta)


def _children(folder: Path) -> list[Path]:
    return sorted(folder.glob("*")) if folder.exists() else []


def _load_npy(path: Path, mmap: bool = False) -> np.ndarray:
    try:
        return np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise DatasetError(
            f"{path}: unreadable array ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})"
        ) from None


def _frame_tasks(meta: dict[str, Any], length: int, where: str) -> np.ndarray:
    """Per-frame task: the segment's task inside a labelled segment, else the episode's task."""
    tasks = np.full(length, meta["task"], dtype=object)
    for seg in meta.get("segments") or []:
        try:
            start, end, task = int(seg["start"]), int(seg["end"]), str(seg["task"])
        except (KeyError, TypeError, ValueError):
            raise DatasetError(f"{where}/meta.json: each segment needs 'task', 'start' and 'end'") from None
        if not 0 <= start < end <= length:
            raise DatasetError(f"{where}/meta.json: segment [{start}, {end}) is outside the {length} frames")
        tasks[start:end] = task
    return tasks.astype(str)


def _write_png(path: Path, rgb: np.ndarray) -> None:
    # Encoded in memory and written by Python: cv2's own file IO crashes on non-UTF-8 paths.
    ok, data = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise DatasetError(f"{path}: cannot encode image")
    path.write_bytes(data.tobytes())


def _read_camera(files: list[Path]) -> np.ndarray:
    """One camera's frames, decoded, keeping each file's bytes where a LeRobot reader decodes them
    to the same pixels (8-bit RGB, not interlaced): a stage that leaves the pixels alone then
    costs no PNG encoding when the episode is written (`datasets/encoded_frames.py`)."""
    decoded, encoded = [], []
    for path in files:
        data = _read_bytes(path)
        decoded.append(_decode_png(data, path))
        encoded.append(data if _is_plain_rgb_png(data) else None)
    frames = np.stack(decoded)
    if all(b is not None for b in encoded):
        return EncodedFrames.wrap(frames, encoded)
    return frames


def _is_plain_rgb_png(data: bytes) -> bool:
    # IHDR is the first chunk: bytes 24-28 are bit depth, colour type, compression, filter, interlace.
    return data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR" and data[24:29] == b"\x08\x02\x00\x00\x00"


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as exc:
        raise DatasetError(f"{path}: missing or unreadable image ({exc.strerror})") from None


def _read_png(path: Path) -> np.ndarray:
    return _decode_png(_read_bytes(path), path)


def _decode_png(raw: bytes, path: Path) -> np.ndarray:
    data = np.frombuffer(raw, dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR) if data.size else None
    if img is None:
        raise DatasetError(f"{path}: missing or unreadable image")
    if img.dtype != np.uint8:
        # Squashing 16-bit data to 8 bits would silently destroy it (12-bit frames turn black).
        raise DatasetError(
            f"{path}: {img.dtype.itemsize * 8}-bit image; raw camera frames must be 8-bit RGB PNGs "
            "(store other data, e.g. 16-bit depth, as a .npy array)"
        )
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def open_raw_dataset(root: str | Path) -> RawDataset:
    """Open and validate a raw dataset's index (episodes are validated as they are read)."""
    root = Path(root)
    index_path = root / "dataset.json"
    if not root.is_dir():
        raise DatasetError(f"raw dataset not found: {root}")
    index = read_json_file(index_path, "not a shiftkit raw dataset")
    if not isinstance(index, dict):
        raise DatasetError(f"{index_path}: expected an object")
    if index.get("format") != FORMAT:
        raise DatasetError(f"{index_path}: format is {index.get('format')!r}, expected {FORMAT!r}")
    if index.get("version") != VERSION:
        raise DatasetError(
            f"{index_path}: raw format version {index.get('version')!r} is not supported (this is v{VERSION})"
        )
    if not isinstance(index.get("fps"), int) or index["fps"] <= 0:
        raise DatasetError(f"{index_path}: 'fps' must be a positive integer")
    episodes = index.get("episodes")
    if not isinstance(episodes, list) or not episodes:
        raise DatasetError(f"{index_path}: no episodes listed")
    _check_index_types(index, index_path)
    for ep in episodes:
        if not (root / str(ep.get("name", ""))).is_dir():
            raise DatasetError(f"{index_path}: episode directory {ep.get('name')!r} is missing")
    return RawDataset(root, index)


def _check_index_types(index: dict[str, Any], where: Path) -> None:
    """The shapes of dataset.json values the reader relies on (a hand-edited index may be off)."""
    for key, kind in (("names", dict), ("info", dict)):
        if not isinstance(index.get(key, {}), kind):
            raise DatasetError(f"{where}: {key!r} must be an object")
    if not all(isinstance(v, list) for v in index.get("names", {}).values()):
        raise DatasetError(f"{where}: every 'names' entry must be a list of dimension names")
    if not isinstance(index.get("info", {}).get("cameras", {}), dict):
        raise DatasetError(f"{where}: info 'cameras' must be an object")
    for i, ep in enumerate(index["episodes"]):
        if not isinstance(ep, dict) or not isinstance(ep.get("name"), str) or not ep["name"]:
            raise DatasetError(f"{where}: episodes[{i}] must be an object with a 'name'")


def is_raw_dataset(path: str | Path) -> bool:
    """Whether `path` holds a raw dataset (a dataset.json)."""
    return (Path(path) / "dataset.json").is_file()


class RawSource:
    """A raw dataset as a pipeline source."""

    def __init__(self, root: Path) -> None:
        self._raw = open_raw_dataset(root)
        self.root = root
        self.features = self._raw.features()
        self.fps = self._raw.fps
        self.robot_type = self._raw.index.get("robot") or None
        self.num_episodes = self._raw.num_episodes

    def episode_groups(self) -> list[list[int]]:
        """One group per episode (each episode is its own folder)."""
        return [[i] for i in range(self.num_episodes)]  # one directory per episode

    def iter_episodes(self, indices: list[int]) -> Iterator[Episode]:
        """The episodes at `indices`, read in that order."""
        return self._raw.iter_episodes(indices)

    def describe(self) -> dict[str, Any]:
        """The source fields of the provenance (path, episodes, env, format version)."""
        return {
            "kind": "raw",
            "path": str(self.root),
            "num_episodes": self.num_episodes,
            "env": self._raw.index.get("env", ""),
            "format_version": self._raw.index.get("version"),
        }
