"""Import robomimic HDF5 datasets (robomimic's documented layout, also written by robosuite,
MimicGen and Isaac Lab's recorders) as LeRobot datasets.

What maps where (docs/importers.md has the table):

* `data/demo_N` -> one episode each, in N order (files without `obs`, as robosuite's converted
  `demo.hdf5`, give episodes of actions and simulator states); `mask/<filter key>` (`--filter-key train`)
  selects the demos of a split.
* `actions` -> `action`; `rewards` -> `next.reward`; `dones` -> `next.done`.
* `obs/<key>`: RGB images (uint8 (T, H, W, 3), robomimic names them `<camera>_image`) ->
  `observation.images.<camera>`; the object-state key `object` -> `observation.environment_state`;
  every other low-dimensional key -> `observation.state`, concatenated in key order, one name per
  dimension (`robot0_eef_pos_0`, ...). `next_obs/*` repeats `obs/*` one step later and is not kept.
* `states` (flattened MuJoCo state, robosuite: [time, qpos, qvel]) -> `sim.state`, float64, for
  re-rendering; each episode's meta names the sha256 of its `model_file` attribute (the MJCF).
* per-demo attributes: `ep_meta` (JSON) `lang`, a language instruction, becomes that episode's task;
  `camera_info` (JSON: K and camera pose per camera) becomes the episode's camera metadata.
* `data` attribute `env_args` (JSON): `env_name` is the task text otherwise (`--task` overrides) and
  `env_kwargs.control_freq` the fps (`--fps` overrides; required when absent); `env_kwargs.robots`
  the robot type. `total` must equal the number of samples in the file.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from shiftkit.datasets import loaders
from shiftkit.datasets.dataclass_config import option
from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import DatasetError
from shiftkit.datasets.features import Features, flag_array, image_feature, vector_feature
from shiftkit.datasets.importers import Importer, register_importer

IMAGE_SUFFIX = "_image"
ENVIRONMENT_STATE_KEY = "object"  # robomimic's low-dim key for privileged object state
_DEMO = re.compile(r"^demo_(\d+)$")


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _open(path: Path):
    import h5py

    if not path.is_file():
        raise DatasetError(f"{path}: no such file")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise DatasetError(f"{path}: not an HDF5 file ({exc})") from None


def _json_attr(path: Path, group, where: str, attr: str) -> dict[str, Any]:
    """A JSON-object attribute (`env_args`, `ep_meta`, `camera_info`); {} when absent."""
    raw = group.attrs.get(attr)
    if raw is None:
        return {}
    try:
        value = json.loads(raw.decode() if isinstance(raw, bytes) else str(raw))
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{path}: {where} attribute {attr} is not JSON ({exc.msg})") from None
    if not isinstance(value, dict):
        raise DatasetError(f"{path}: {where} attribute {attr} is not a JSON object")
    return value


def _cameras(path: Path, demo, name: str, features: Features) -> dict[str, Any]:
    """robomimic's per-demo `camera_info` (K 3x3, camera pose 4x4) in shiftkit's camera metadata form.
    Eye-in-hand poses are relative to the end effector there, a frame the contract has no name for:
    those cameras keep their intrinsics only."""
    cameras = {}
    for camera, values in _json_attr(path, demo, f"data/{name}", "camera_info").items():
        key = f"observation.images.{camera}"
        if key not in features or not isinstance(values, dict) or "intrinsics" not in values:
            continue
        try:
            k = np.asarray(values["intrinsics"], dtype=np.float64).reshape(3, 3)
            height, width = features[key]["shape"][:2]
            entry: dict[str, Any] = {
                "intrinsics": {
                    "fx": float(k[0, 0]),
                    "fy": float(k[1, 1]),
                    "cx": float(k[0, 2]),
                    "cy": float(k[1, 2]),
                    "width": int(width),
                    "height": int(height),
                }
            }
            if "extrinsics" in values and "eye_in_hand" not in camera:
                pose = np.asarray(values["extrinsics"], dtype=np.float64).reshape(4, 4)
                entry["extrinsics"] = {
                    "frame": "world",
                    "position": pose[:3, 3].tolist(),
                    "rotation": pose[:3, :3].tolist(),
                }
        except (TypeError, ValueError):
            raise DatasetError(f"{path}: data/{name} camera_info of {camera!r} is not a 3x3 K and 4x4 pose") from None
        cameras[camera] = entry
    return cameras


def _demo_names(path: Path, f, filter_key: str | None) -> list[str]:
    data = f["data"]
    names = sorted((k for k in data if _DEMO.match(k)), key=lambda k: int(k[5:]))
    if not names:
        raise DatasetError(f"{path}: the data group holds no demo_N groups")
    if filter_key is None:
        return names
    masks = loaders.h5_item(f, "mask", f"{path}: mask", group=True) if "mask" in f else None
    if masks is None or filter_key not in masks:
        known = sorted(masks) if masks is not None else []
        raise DatasetError(f"{path}: no filter key {filter_key!r} under mask/ (known: {known or 'none'})")
    listed = loaders.h5_item(masks, filter_key, f"{path}: mask/{filter_key}", group=False)[()]
    if np.ndim(listed) != 1:
        raise DatasetError(f"{path}: mask/{filter_key} must be a list of demo names")
    chosen = [n.decode(errors="replace") if isinstance(n, bytes) else str(n) for n in listed]
    missing = sorted(set(chosen) - set(names))
    if missing:
        raise DatasetError(f"{path}: mask/{filter_key} names demos that do not exist: {missing[:5]}")
    return sorted(chosen, key=lambda k: int(k[5:]))


def _width(ds) -> int:
    """Values per sample of a (T,) or (T, d) dataset."""
    return 1 if ds.ndim == 1 else int(np.prod(ds.shape[1:]))


def _is_image(ds) -> bool:
    return ds.dtype == np.uint8 and ds.ndim == 4 and ds.shape[-1] == 3


def _schema(path: Path, demo, demo_name: str, obs_keys: list[str] | None) -> tuple[Features, dict[str, list[str]]]:
    """Features of the dataset from its first demo, and which obs keys feed which feature."""
    if "actions" not in demo:
        raise DatasetError(f"{path}: data/{demo_name} has no 'actions'")
    # robosuite's converted demo.hdf5 has states and actions only (observations are extracted later)
    obs = loaders.h5_item(demo, "obs", f"{path}: data/{demo_name}/obs", group=True) if "obs" in demo else {}
    keys = sorted(obs) if obs_keys is None else obs_keys
    unknown = [k for k in keys if k not in obs]
    if unknown:
        raise DatasetError(f"{path}: data/{demo_name}/obs has no key(s) {unknown} (has {sorted(obs)})")
    groups: dict[str, list[str]] = {"observation.state": [], "observation.environment_state": []}
    features: Features = {}
    names: dict[str, list[str]] = {"observation.state": [], "observation.environment_state": []}
    for key in keys:
        ds = loaders.h5_item(obs, key, f"{path}: data/{demo_name}/obs/{key}", group=False)
        if _is_image(ds):
            camera = key.removesuffix(IMAGE_SUFFIX)
            features[f"observation.images.{camera}"] = image_feature(tuple(int(n) for n in ds.shape[1:]))
            groups[f"observation.images.{camera}"] = [key]
        elif ds.ndim in (1, 2) and ds.dtype.kind in "fiub":
            target = "observation.environment_state" if key == ENVIRONMENT_STATE_KEY else "observation.state"
            groups[target].append(key)
            names[target] += [key] if ds.ndim == 1 else [f"{key}_{i}" for i in range(_width(ds))]
        else:
            raise DatasetError(
                f"{path}: data/{demo_name}/obs/{key} has shape {ds.shape} ({ds.dtype}): neither low-dim (T, d) nor "
                "an RGB image (T, H, W, 3) uint8; leave it out with --obs-keys"
            )
    for target in ("observation.state", "observation.environment_state"):
        if groups[target]:
            features[target] = vector_feature("float32", names[target])
        else:
            del groups[target]
    for key in ("rewards", "dones", "states"):
        if key in demo:
            loaders.h5_item(demo, key, f"{path}: data/{demo_name}/{key}", group=False)
    features["action"] = vector_feature("float32", [f"action_{i}" for i in range(_width(demo["actions"]))])
    if "rewards" in demo:
        features["next.reward"] = vector_feature("float32", ["reward"])
    if "dones" in demo:
        features["next.done"] = vector_feature("bool", ["done"])
    if "states" in demo:
        features["sim.state"] = vector_feature("float64", [f"state_{i}" for i in range(_width(demo["states"]))])
    return features, groups


def _read_demo(
    path: Path,
    demo,
    name: str,
    features: Features,
    groups: dict[str, list[str]],
    fps: int,
    task: str | None,
    default_task: str | None,
) -> Episode:
    # --task, else the demo's language instruction (robocasa-style ep_meta "lang"), else env_name
    ep_meta = _json_attr(path, demo, f"data/{name}", "ep_meta")
    ep_meta = loaders.check_value(
        ep_meta, loaders.obj(lang=loaders.opt(loaders.nullable(loaders.string))), f"{path}: data/{name} ep_meta"
    )
    task = task or ep_meta.get("lang") or default_task
    if not task:
        raise DatasetError(f"{path}: data/{name}: no env_args env_name or ep_meta lang names the task; give --task")
    n = int(demo["actions"].shape[0])
    if n == 0:
        raise DatasetError(f"{path}: data/{name} has no samples")
    frames: dict[str, np.ndarray] = {}

    def read(rel: str) -> np.ndarray:
        if rel not in demo:
            raise DatasetError(f"{path}: data/{name} has no {rel!r} (the first demo has it)")
        arr = loaders.h5_item(demo, rel, f"{path}: data/{name}/{rel}", group=False)[()]
        if np.ndim(arr) == 0 or arr.dtype.kind not in "fiub":
            raise DatasetError(f"{path}: data/{name}/{rel} must be a numeric array with a frame axis")
        if arr.shape[0] != n:
            raise DatasetError(f"{path}: data/{name}/{rel} has {arr.shape[0]} samples, actions have {n}")
        if arr.dtype.kind == "f" and not np.isfinite(arr).all():
            raise DatasetError(f"{path}: data/{name}/{rel} contains NaN/inf")
        return arr

    for feature, keys in groups.items():
        if feature.startswith("observation.images."):
            frames[feature] = np.ascontiguousarray(read(f"obs/{keys[0]}"))
        else:
            parts = [read(f"obs/{k}").reshape(n, -1) for k in keys]
            frames[feature] = np.concatenate(parts, axis=1).astype(np.float32)
    frames["action"] = read("actions").reshape(n, -1).astype(np.float32)
    if "next.reward" in features:
        frames["next.reward"] = read("rewards").reshape(n, 1).astype(np.float32)
    if "next.done" in features:
        frames["next.done"] = flag_array(read("dones").reshape(n, 1), f"{path}: data/{name}/dones")
    if "sim.state" in features:
        frames["sim.state"] = read("states").reshape(n, -1).astype(np.float64)
    for key, ft in features.items():
        if frames[key].shape[1:] != tuple(ft["shape"]):
            raise DatasetError(
                f"{path}: data/{name}: {key} has per-frame shape {frames[key].shape[1:]}, "
                f"the first demo has {tuple(ft['shape'])}"
            )
    frames["timestamp"] = np.arange(n, dtype=np.float64) / fps
    frames["task"] = np.array([task] * n)
    meta: dict[str, Any] = {"task": task, "source": {"file": path.name, "demo": name}}
    model = demo.attrs.get("model_file")
    if model is not None:
        text = model.encode() if isinstance(model, str) else bytes(model)
        meta["sim"] = {"model_file_sha256": hashlib.sha256(text).hexdigest()}
    cameras = _cameras(path, demo, name, features)
    if cameras:
        meta["cameras"] = cameras
    return Episode(frames, meta)


@dataclass
class RobomimicOptions:
    """Options of the robomimic importer (`shiftkit import robomimic FILE`)."""

    file: str
    """robomimic HDF5 file (data/demo_N groups)."""
    filter_key: str | None = None
    """Import only the demos listed in mask/<KEY> (e.g. train, valid)."""
    fps: int | None = option(None, rule="positive_int")
    """Frame rate (default: env_args env_kwargs.control_freq)."""
    task: str | None = None
    """Task text of every episode (default: the demo's ep_meta lang, else env_args env_name)."""
    obs_keys: list[str] | None = None
    """The obs keys to keep (default: all); images become cameras, the rest state."""


class RobomimicSource:
    """The demos of one robomimic HDF5 file as a pipeline source (one group: the file)."""

    def __init__(self, options: RobomimicOptions) -> None:
        self.options = options
        path = self.path = Path(options.file)
        self.inputs = [path]
        self._fps_from = "--fps" if options.fps is not None else "env_args env_kwargs.control_freq"
        with _open(path) as f:
            if "data" not in f or not hasattr(f["data"], "keys"):
                raise DatasetError(f"{path}: no 'data' group (not a robomimic dataset)")
            data = f["data"]
            self._env_args = loaders.check_value(
                _json_attr(path, data, "data", "env_args"),
                loaders.obj(
                    env_name=loaders.opt(loaders.nullable(loaders.string)),
                    env_kwargs=loaders.opt(loaders.nullable(loaders.map_of(loaders.ANY))),
                ),
                f"{path}: data attribute env_args",
            )
            env_kwargs = self._env_args.get("env_kwargs") or {}
            all_demos = _demo_names(path, f, None)
            for d in all_demos:  # named here, before the counts that depend on them
                actions = loaders.h5_item(data, d, f"{path}: data/{d}", group=True).get("actions")
                if not hasattr(actions, "shape") or len(actions.shape) not in (1, 2) or actions.dtype.kind not in "fiu":
                    found = "missing" if actions is None else f"shape {getattr(actions, 'shape', None)}"
                    raise DatasetError(f"{path}: data/{d}/actions must be a numeric (frames[, dims]) array ({found})")
            if "total" in data.attrs:
                samples = sum(int(data[d]["actions"].shape[0]) for d in all_demos)
                total = data.attrs["total"]
                if np.ndim(total) != 0 or np.asarray(total).dtype.kind not in "iu":
                    raise DatasetError(f"{path}: data attribute total must be an integer, got {total!r:.40}")
                if int(total) != samples:
                    raise DatasetError(f"{path}: data attribute total is {int(total)}, the demos hold {samples}")
            self.demos = _demo_names(path, f, options.filter_key)
            control_freq = env_kwargs.get("control_freq")
            fps = options.fps
            if fps is None:
                numeric = isinstance(control_freq, (int, float)) and not isinstance(control_freq, bool)
                if (
                    not numeric
                    or not math.isfinite(control_freq)
                    or control_freq != int(control_freq)
                    or control_freq < 1
                ):
                    raise DatasetError(
                        f"{path}: env_args has no integer env_kwargs.control_freq ({control_freq}); give --fps"
                    )
                fps = int(control_freq)
            self.fps = fps
            robots = env_kwargs.get("robots")
            self.robot_type = "+".join(robots) if isinstance(robots, list) else (str(robots) if robots else None)
            self.features, self._groups = _schema(path, data[self.demos[0]], self.demos[0], options.obs_keys)
            self.lengths = [int(data[d]["actions"].shape[0]) for d in self.demos]
        self.num_episodes = len(self.demos)
        self._sha256 = _sha256(path)

    def episode_groups(self) -> list[list[int]]:
        """Every demo in one group (one file)."""
        return [list(range(self.num_episodes))]

    def iter_episodes(self, indices: list[int]) -> Iterator[Episode]:
        """The demos at `indices`, read from the file in that order."""
        with _open(self.path) as f:
            for i in indices:
                name = self.demos[i]
                episode = _read_demo(
                    self.path,
                    f["data"][name],
                    name,
                    self.features,
                    self._groups,
                    self.fps,
                    self.options.task,
                    self._env_args.get("env_name"),
                )
                episode.meta["source_episode_index"] = i
                yield episode

    def describe(self) -> dict[str, Any]:
        """The provenance entry: the file (with its sha256), the demos and the import's settings."""
        return {
            "kind": "robomimic",
            "path": str(self.path.resolve()),
            "sha256": self._sha256,
            "demos": self.demos,
            "lengths": self.lengths,
            "importer": {
                "name": "robomimic",
                "filter_key": self.options.filter_key,
                "fps": self.fps,
                "fps_from": self._fps_from,
                "env_args": self._env_args,
                "obs_keys": self._groups,
                "not_kept": "next_obs (obs one step later)",
            },
        }


def _report(source: dict[str, Any]) -> list[str]:
    filter_key = source["importer"]["filter_key"]
    return [
        f"{Path(source['path']).name}: {len(source['demos'])} demos" + (f" (mask/{filter_key})" if filter_key else "")
    ]


IMPORTER = register_importer(
    Importer(
        name="robomimic",
        help="robomimic HDF5 datasets (data/demo_N with actions, obs, states; mask/ filter keys)",
        Options=RobomimicOptions,
        inputs=("file",),
        open=RobomimicSource,
        report=_report,
    )
)
