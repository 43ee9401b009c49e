"""LeRobot feature schemas (`{"dtype", "shape", "names", "info"}` per key) and episode checks."""

from __future__ import annotations

import copy
from typing import Any

import numpy as np

from shiftkit.datasets.depth import depth_unit, is_depth
from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import DatasetError

Features = dict[str, dict[str, Any]]

# Features every LeRobot dataset has; the writer fills them, stages never declare them.
DEFAULT_KEYS = ("timestamp", "frame_index", "episode_index", "index", "task_index")
NUMERIC_DTYPES = {"float32", "float64", "int64", "int32", "int16", "int8", "uint8", "bool"}
CAMERA_DTYPES = {"image", "video"}
# Per-frame values without statistics: strings, and lerobot 0.6's language columns
# (`language_persistent` / `language_events`: a list of message rows per frame, held as objects).
TEXT_DTYPES = {"string", "language"}
IMAGE_NAMES = ["height", "width", "channels"]


def numpy_dtype(feature: dict[str, Any]) -> np.dtype:
    """The numpy dtype an Episode array of a feature holds: RGB cameras uint8 (H, W, 3), depth
    cameras float32 metres (H, W, 1) (`datasets.depth`), language columns objects, others their
    own dtype."""
    dtype = feature["dtype"]
    if dtype == "language":
        return np.dtype(object)
    if dtype in CAMERA_DTYPES:
        return np.dtype("float32") if is_depth(feature) else np.dtype("uint8")
    return np.dtype(dtype)


def object_column(values: list[Any]) -> np.ndarray:
    """One Python value per frame (e.g. a language column's list of messages) as a 1-D object
    array; `np.array` alone would turn equal-length lists into a 2-D array."""
    out = np.empty(len(values), dtype=object)
    for i, value in enumerate(values):
        out[i] = value
    return out


def flag_array(arr: np.ndarray, where: str) -> np.ndarray:
    """A success or done flag as bool. Only 0 and 1 (or bools) are flags: a 0.5 would otherwise
    be cast to True and count as a success (docs/raw_format.md)."""
    arr = np.asarray(arr)
    if arr.dtype == bool:
        return arr
    if arr.dtype.kind not in "iuf":
        raise DatasetError(f"{where}: a flag holds only 0 and 1 (or bools), found dtype {arr.dtype}")
    odd = np.flatnonzero((arr != 0) & (arr != 1))
    if odd.size:
        frame = odd[0] // max(1, arr.size // max(1, len(arr)))
        value = arr.reshape(-1)[odd[0]].item()
        raise DatasetError(f"{where}: a flag holds only 0 and 1 (or bools), found {value!r} at frame {frame}")
    return arr.astype(bool)


def vector_feature(dtype: str, names: list[str], **info: Any) -> dict[str, Any]:
    """A 1-D feature of `dtype` with one entry per name (`info` kept under "info")."""
    feature: dict[str, Any] = {"dtype": dtype, "shape": (len(names),), "names": list(names)}
    if info:
        feature["info"] = info
    return feature


def image_feature(shape: tuple[int, int, int]) -> dict[str, Any]:
    """An RGB camera feature, exactly as lerobot declares one (camera intrinsics/extrinsics live in
    the episode metadata and `meta/cameras.json`, see `camera_meta`)."""
    return {"dtype": "image", "shape": tuple(shape), "names": list(IMAGE_NAMES)}


def _lerobot_info(feature: dict[str, Any], keep_video: bool) -> dict[str, Any]:
    """What lerobot itself keeps in a camera feature's `info`: the depth marker and unit, and while
    it stays a video, the `video.*` / `audio.*` keys its video writer records (codec, size,
    encoder settings, the depth quantiser), which a re-encode rewrites."""
    info = feature.get("info") or {}
    out = {"is_depth_map": True, "depth_unit": depth_unit(feature)} if is_depth(feature) else {}
    if keep_video:
        out = {
            **{
                k: v
                for k, v in info.items()
                if k.startswith(("video.", "audio.")) or k in ("has_audio", "is_depth_map")
            },
            **out,
        }
    return out


def plain_camera_features(features: Features, dtype: str | None = None) -> Features:
    """`features` with every camera feature reduced to the keys lerobot itself declares (anything
    else in a feature, e.g. intrinsics of older shiftkit datasets, stops `aggregate_datasets` from
    merging with datasets recorded elsewhere): dtype, shape, names and lerobot's own `info` keys
    (depth markers; a video's `video.*` keys while it stays a video). `dtype` ("image" or "video")
    stores every camera, RGB and depth, in that form; None keeps each camera's own."""
    out: Features = {}
    for key, ft in features.items():
        if ft.get("dtype") not in CAMERA_DTYPES:
            out[key] = ft
            continue
        new_dtype = dtype or ft["dtype"]
        plain = {"dtype": new_dtype, "shape": tuple(ft["shape"]), "names": ft.get("names")}
        info = _lerobot_info(ft, keep_video=new_dtype == ft["dtype"] == "video")
        if info:
            plain["info"] = info
        out[key] = plain
    return out


def user_features(features: Features) -> Features:
    """The schema without the writer-derived default columns, shapes as tuples."""
    out = {}
    for key, ft in features.items():
        if key in DEFAULT_KEYS:
            continue
        ft = copy.deepcopy(ft)
        ft["shape"] = tuple(ft["shape"])
        out[key] = ft
    return out


def check_features(features: Features, where: str = "features") -> None:
    """Raise a DatasetError for a schema lerobot would reject or that shiftkit cannot write."""
    for key, ft in features.items():
        if "/" in key:
            raise DatasetError(f"{where}: feature name {key!r} contains '/' (not allowed in LeRobot datasets)")
        dtype = ft.get("dtype")
        if dtype not in NUMERIC_DTYPES | CAMERA_DTYPES | TEXT_DTYPES:
            raise DatasetError(f"{where}: feature {key!r} has unsupported dtype {dtype!r}")
        shape = tuple(ft.get("shape", ()))
        if not shape or any((not isinstance(n, int)) or n <= 0 for n in shape):
            raise DatasetError(f"{where}: feature {key!r} has invalid shape {ft.get('shape')!r}")
        names = ft.get("names")
        if dtype in NUMERIC_DTYPES and len(shape) == 1 and isinstance(names, list) and len(names) != shape[0]:
            raise DatasetError(f"{where}: feature {key!r} has {len(names)} names for {shape[0]} dims")


def check_episode(episode: Episode, features: Features, fps: int, where: str) -> None:
    """Validate one episode against the schema: keys, shapes, dtypes, NaNs, timestamps at `fps`."""
    n = len(episode)
    if n == 0:
        raise DatasetError(f"{where}: episode has no frames")
    expected = set(features) | {"timestamp", "task"}
    missing = expected - set(episode.frames)
    extra = set(episode.frames) - expected
    if missing:
        raise DatasetError(f"{where}: missing feature(s) {sorted(missing)}")
    if extra:
        raise DatasetError(f"{where}: feature(s) {sorted(extra)} not declared in the schema")
    for key, ft in features.items():
        arr = episode.frames[key]
        if len(arr) != n:
            raise DatasetError(f"{where}: feature {key!r} has {len(arr)} frames, expected {n}")
        shape = tuple(ft["shape"])
        got = arr.shape[1:]
        if got != shape and not (shape == (1,) and got == ()):
            raise DatasetError(f"{where}: feature {key!r} has per-frame shape {got}, expected {shape}")
        if arr.dtype != numpy_dtype(ft):
            raise DatasetError(f"{where}: feature {key!r} has dtype {arr.dtype}, expected {numpy_dtype(ft)}")
        # frames still encoded (a copied depth video) are the source's: not decoded to be checked
        if arr.dtype.kind == "f" and isinstance(arr, np.ndarray) and not np.isfinite(arr).all():
            bad = int(np.argwhere(~np.isfinite(arr.reshape(n, -1)).all(axis=1))[0][0])
            raise DatasetError(f"{where}: feature {key!r} has NaN/inf values (first at frame {bad})")
    ts = np.asarray(episode.frames["timestamp"], dtype=np.float64)
    if not np.isfinite(ts).all():
        raise DatasetError(f"{where}: timestamps contain NaN/inf")
    # LeRobot checks consecutive timestamps against 1/fps with this tolerance when it loads.
    deviation = float(np.abs(np.diff(ts) - 1.0 / fps).max()) if n > 1 else 0.0
    if deviation > 1e-4:
        raise DatasetError(
            f"{where}: timestamps are not sampled at {fps} fps (deviation {deviation:.4f} s); add a `resample` stage"
        )
