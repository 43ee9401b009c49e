"""Camera metadata (intrinsics, extrinsics, base pose per view) kept outside lerobot's feature dicts.

In an episode, `meta["cameras"] = {camera: {"intrinsics": {...}, "extrinsics": {...},
"base_pose": {...}}}`. A LeRobot dataset stores it in `meta/cameras.json`, factored so that a
fixed camera is written once::

    {"format": "shiftkit-cameras", "version": 1,
     "cameras": {camera: {entry: value, ...}},                     # the same in every episode
     "episodes": {"<episode_index>": {camera: {entry: value}}}}    # what differs per episode

An entry (`intrinsics`, `extrinsics`, `base_pose`, ...) of a camera is constant when every episode
has it with the same value. Reading puts the two parts back together per episode. The format is
documented in docs/camera_metadata.md.

A camera's entries describe every feature of that camera (`observation.images.CAM` and
`observation.depth.CAM`). Where its features differ (the depth map resized, the RGB not), the
camera's `features` entry holds, per feature, the entries that describe only that feature:
`{"front": {"extrinsics": {...}, "features": {"observation.images.front": {"intrinsics": {...}},
"observation.depth.front": {"intrinsics": {...}}}}}`. `feature_entries` reads a feature's
entries, `cameras_for_features` writes them back (stages that rescale or rename camera features).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from shiftkit.datasets.errors import DatasetError
from shiftkit.datasets.jsonutil import dumps, read_json_file

CAMERAS_PATH = "meta/cameras.json"
CAMERA_PREFIXES = ("observation.images.", "observation.depth.")
FEATURES = "features"  # a camera's per-feature entries
FORMAT = "shiftkit-cameras"
VERSION = 1
INTRINSIC_KEYS = ("fx", "fy", "cx", "cy", "width", "height")
FRAMES = ("base", "world")

Cameras = dict[str, dict[str, Any]]
_MISSING = object()


def check_cameras(cameras: Any, where: str) -> Cameras:
    """Validate one episode's camera dict (the shared contract); returns it."""
    if not isinstance(cameras, Mapping):
        raise DatasetError(f"{where}: 'cameras' must map camera names to objects")
    for name, cam in cameras.items():
        if not isinstance(cam, Mapping):
            raise DatasetError(f"{where}: cameras[{name!r}] must be an object")
        per_feature = cam.get(FEATURES, {})
        if not isinstance(per_feature, Mapping) or not all(isinstance(v, Mapping) for v in per_feature.values()):
            raise DatasetError(f"{where}: cameras[{name!r}].{FEATURES} must map feature names to objects")
        for key, entries in per_feature.items():
            check_cameras({f"{name}/{key}": entries}, where)
        intr = cam.get("intrinsics")
        if intr is not None:
            missing = [k for k in INTRINSIC_KEYS if not isinstance(intr.get(k), int | float)]
            if missing:
                raise DatasetError(f"{where}: cameras[{name!r}].intrinsics lacks numeric {missing}")
        extr = cam.get("extrinsics")
        if extr is not None:
            rot = extr.get("rotation")
            if (
                extr.get("frame") not in FRAMES
                or not _is_vector(extr.get("position"), 3)
                or not (isinstance(rot, list) and len(rot) == 3 and all(_is_vector(r, 3) for r in rot))
            ):
                raise DatasetError(
                    f"{where}: cameras[{name!r}].extrinsics needs frame 'base'|'world', position [x, y, z] "
                    "and a 3x3 rotation"
                )
    return dict(cameras)


def camera_of(key: str) -> str:
    """The camera a feature belongs to: `observation.images.front` and `observation.depth.front` are
    the camera `front`; another camera feature is a camera of its own name."""
    for prefix in CAMERA_PREFIXES:
        if key.startswith(prefix):
            return key.removeprefix(prefix)
    return key


def feature_entries(cameras: Mapping[str, Any] | None, key: str) -> dict[str, Any]:
    """The entries describing camera feature `key`: its camera's, overlaid with its own."""
    cam = dict((cameras or {}).get(camera_of(key)) or {})
    own = (cam.pop(FEATURES, None) or {}).get(key) or {}
    return {**cam, **own}


def cameras_for_features(
    cameras: Mapping[str, Any] | None, before: list[str], after: Mapping[str, dict[str, Any]]
) -> Cameras:
    """`cameras` with the camera features `before` (the input's) replaced by `after` (output feature
    -> the entries describing it): per camera, an entry every one of its features has with the same
    value is the camera's, the others go under its `features`. Cameras of no feature in `before`
    (e.g. a mobile base's pose only) are kept as they are."""
    out: Cameras = {name: dict(cam) for name, cam in (cameras or {}).items()}
    for name in {camera_of(k) for k in before}:
        out.pop(name, None)
    groups: dict[str, dict[str, dict[str, Any]]] = {}
    for key, entries in after.items():
        if entries:
            groups.setdefault(camera_of(key), {})[key] = entries
    for name, per_feature in groups.items():
        names = list(dict.fromkeys(e for entries in per_feature.values() for e in entries))
        shared = {
            e: next(iter(per_feature.values()))[e]
            for e in names
            if all(e in entries for entries in per_feature.values())
            and len({dumps(entries[e]) for entries in per_feature.values()}) == 1
        }
        own = {
            key: {e: v for e, v in entries.items() if e not in shared}
            for key, entries in per_feature.items()
            if any(e not in shared for e in entries)
        }
        out[name] = {**shared, **({FEATURES: own} if own else {})}
    return out


def _is_vector(value: Any, n: int) -> bool:
    return isinstance(value, list) and len(value) == n and all(isinstance(x, int | float) for x in value)


def merge_cameras(dataset_level: Mapping[str, Any] | None, episode: Mapping[str, Any] | None) -> Cameras:
    """A raw episode's cameras: the dataset-level entries (dataset.json info "cameras") overlaid with
    the episode's own (meta.json "cameras"). A dataset-level value that is a bare intrinsics dict
    (what collect wrote before this contract) counts as `{"intrinsics": value}`."""
    merged: Cameras = {}
    for name, cam in (dataset_level or {}).items():
        merged[name] = {"intrinsics": dict(cam)} if isinstance(cam, Mapping) and "fx" in cam else dict(cam)
    for name, cam in (episode or {}).items():
        merged[name] = {**merged.get(name, {}), **(cam if isinstance(cam, Mapping) else {})}
    return merged


def cameras_from_feature_info(features: Mapping[str, Any]) -> Cameras:
    """Intrinsics that shiftkit datasets written before `meta/cameras.json` kept in the `info` of
    `observation.images.CAM` features, in the episode-metadata form."""
    out: Cameras = {}
    for key, ft in features.items():
        info = ft.get("info") or {}
        if key.startswith("observation.images.") and all(k in info for k in INTRINSIC_KEYS):
            out[key.removeprefix("observation.images.")] = {"intrinsics": {k: info[k] for k in INTRINSIC_KEYS}}
    return out


def factor_cameras(per_episode: Mapping[int, Cameras]) -> dict[str, Any]:
    """The `meta/cameras.json` document of a dataset whose episode `i` has cameras `per_episode[i]`
    (episodes without cameras are left out of the mapping)."""
    constant: Cameras = {}
    episodes = sorted(per_episode)
    names = sorted({name for cams in per_episode.values() for name in cams})
    for name in names:
        entries = sorted({e for cams in per_episode.values() for e in cams.get(name, {})})
        for entry in entries:
            values = [per_episode[i].get(name, {}).get(entry, _MISSING) for i in episodes]
            if all(v is not _MISSING for v in values) and len({dumps(v) for v in values}) == 1:
                constant.setdefault(name, {})[entry] = values[0]
    varying: dict[str, Cameras] = {}
    for i in episodes:
        for name, cam in per_episode[i].items():
            for entry, value in cam.items():
                if entry not in constant.get(name, {}):
                    varying.setdefault(str(i), {}).setdefault(name, {})[entry] = value
    return {"format": FORMAT, "version": VERSION, "cameras": constant, "episodes": varying}


def episode_cameras(doc: Mapping[str, Any], episode_index: int) -> Cameras:
    """One episode's cameras from a `meta/cameras.json` document (empty when it has none)."""
    out: Cameras = {name: dict(cam) for name, cam in doc.get("cameras", {}).items()}
    for name, cam in doc.get("episodes", {}).get(str(episode_index), {}).items():
        out[name] = {**out.get(name, {}), **cam}
    return out


def write_cameras_file(root: Path, per_episode: Mapping[int, Cameras]) -> dict[str, Any] | None:
    """Write `root/meta/cameras.json` when any episode has cameras; returns the document."""
    if not per_episode:
        return None
    doc = factor_cameras(per_episode)
    (root / CAMERAS_PATH).write_text(dumps(doc, indent=2))
    return doc


def read_cameras_file(root: Path) -> dict[str, Any]:
    """`root/meta/cameras.json` checked, or an empty document when the dataset has none."""
    path = Path(root) / CAMERAS_PATH
    if not path.exists():
        return {"format": FORMAT, "version": VERSION, "cameras": {}, "episodes": {}}
    doc = read_json_file(path, "camera metadata")
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise DatasetError(f"{path}: format is not {FORMAT!r}")
    if doc.get("version") != VERSION:
        raise DatasetError(f"{path}: version {doc.get('version')!r} is not supported (this is v{VERSION})")
    check_cameras(doc.get("cameras", {}), str(path))
    episodes = doc.get("episodes", {})
    if not isinstance(episodes, Mapping) or not all(str(k).isdigit() for k in episodes):
        raise DatasetError(f"{path}: 'episodes' must map episode indices to camera objects")
    for index, cams in episodes.items():
        check_cameras(cams, f"{path} episode {index}")
    return doc


def provenance_entry(doc: Mapping[str, Any] | None) -> dict[str, Any] | None:
    """What the provenance records: the constant values and which entries vary per episode."""
    if not doc:
        return None
    varying: dict[str, set[str]] = {}
    for cams in doc["episodes"].values():
        for name, cam in cams.items():
            varying.setdefault(name, set()).update(cam)
    return {
        "file": CAMERAS_PATH,
        "cameras": doc["cameras"],
        "per_episode": {name: sorted(entries) for name, entries in sorted(varying.items())},
    }
