"""Episode statistics with lerobot's values, computed without lerobot's per-dimension loops.

lerobot 0.6.1 (`lerobot.datasets.compute_stats`) estimates quantiles from a 5000-bin histogram per
dimension: one `np.histogram` (a sort) and, per quantile, a `cumsum` over all 5000 bins. Only a few
bins matter: the one holding each quantile's target count and its left neighbour. Here each column
is sorted once (all columns of a dtype together) and those bins' cumulative counts are found by
binary search in the sorted column, which gives the histogram's counts exactly, so every value
(and dtype) equals `compute_episode_stats` / `get_feature_stats`. Mean, mean of squares, min and
max use lerobot's own numpy expressions on the same arrays, so their rounding is the same too.

Since 0.6.1 lerobot's `RunningQuantileStats.update` first promotes every batch to
`np.result_type(dtype, np.float32)` (bool, uint8, uint16, int8/16 and float16 to float32; int32,
int64 to float64), so every statistic of a column with two rows or more, min and max included, is
float32 or float64, and the mean of a float32 batch (RGB pixels too) is summed in float32. The
special case of fewer than two rows (`_compute_basic_stats`) is not promoted. Both are mirrored
here (`_promoted`, `_basic_stats`).

Camera features (`image_stats`): RGB statistics are divided by 255; depth maps (lerobot 0.6.1's
`is_depth_map` features) are not, and stay in their stored unit (float32 metres or uint16
millimetres), as `compute_episode_stats` gives them.

`episode_stats` gives an episode's statistics as lerobot's writer computes them, in the worker that
made the episode. Nothing here imports lerobot: its module loads torch (and, since 0.6.1,
lerobot.processor), seconds and hundreds of MB in every pipeline worker.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from shiftkit.datasets import depth
from shiftkit.datasets.episode import Episode
from shiftkit.datasets.features import CAMERA_DTYPES, TEXT_DTYPES, Features

# lerobot 0.6.1's DEFAULT_QUANTILES and RunningQuantileStats' bin count (tests/test_stats.py checks).
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)
QUANTILE_KEYS = tuple(f"q{int(q * 100):02d}" for q in QUANTILES)
NUM_BINS = 5000
_PAD = 1e-10  # lerobot widens the histogram range by this much on both sides

Stats = dict[str, np.ndarray]


def _promoted(dtype: np.dtype) -> np.dtype:
    """The dtype lerobot 0.6.1's `RunningQuantileStats.update` computes a batch in
    (`batch.astype(np.result_type(batch.dtype, np.float32))`): float32 or float64. It is also the
    dtype of its bin edges (`np.linspace(min - 1e-10, ...)` on a float32 or float64 min, NEP 50)."""
    return np.result_type(dtype, np.float32)


def _basic_stats(rows: np.ndarray, count: int) -> Stats:
    """lerobot's `_compute_basic_stats`, its statistics of fewer than two rows (on the rows as
    given: this path does not promote them), quantiles set to the mean."""
    mean = np.mean(rows, axis=0)
    stats = {
        "min": np.min(rows, axis=0),
        "max": np.max(rows, axis=0),
        "mean": mean,
        "std": np.std(rows, axis=0),
        "count": np.array([count]),
    }
    stats.update({key: mean.copy() for key in QUANTILE_KEYS})
    return stats


def _moments(rows: np.ndarray, count: int, extremes: bool = True) -> Stats:
    """min, max, mean, std and `count` exactly as RunningQuantileStats computes them from one batch
    (`rows` already promoted, laid out in memory as lerobot's: float32 means depend on it).
    `extremes=False` leaves min and max (None) to the caller."""
    mean = np.mean(rows, axis=0)
    mean_sq = np.mean(rows**2, axis=0)
    # (lerobot's running update then adds (batch_mean - mean) * 1, a no-op: np.mean never returns -0.0.)
    return {
        "min": np.min(rows, axis=0) if extremes else None,
        "max": np.max(rows, axis=0) if extremes else None,
        "mean": mean,
        "std": np.sqrt(np.maximum(0, mean_sq - mean**2)),
        "count": np.array([count]),
    }


def _edge_at(j: np.ndarray, start: np.ndarray, stop: np.ndarray) -> np.ndarray:
    """Bin edges number `j` (cols, k) of each column, equal to `np.linspace(start, stop, NUM_BINS + 1)[j]`
    column by column (same arithmetic: arange * step + start, the last edge set to stop), without
    materialising all NUM_BINS + 1 edges. (linspace's other path, for a step that underflows to
    zero, cannot occur: the 1e-10 padding makes the range either 0 or far above 5000 denormals.)"""
    step = (stop - start)[:, None] / NUM_BINS
    edges = j.astype(start.dtype) * step + start[:, None]
    return np.where(j == NUM_BINS, stop[:, None], edges)


def _count_below(ordered: np.ndarray, x: np.ndarray) -> np.ndarray:
    """#(ordered[c] < x[c, k]) for sorted rows `ordered` (cols, rows) and values `x` (cols, k)."""
    if ordered.shape[1] <= 512:
        return (ordered[:, None, :] < x[:, :, None]).sum(axis=2)
    return np.stack([np.searchsorted(row, xs) for row, xs in zip(ordered, x, strict=True)])


def _edges_at_most(v: np.ndarray, start: np.ndarray, stop: np.ndarray) -> np.ndarray:
    """#(edges <= v) per column: the index of v's bin plus one (bins [e_i, e_i+1), the last closed)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        guess = np.floor(
            (v - start[:, None]).astype(np.float64) / ((stop - start) / NUM_BINS)[:, None].astype(np.float64)
        )
    m = np.clip(np.nan_to_num(guess, nan=NUM_BINS, posinf=NUM_BINS), 0, NUM_BINS).astype(np.int64) + 1
    while True:  # the guess is off by rounding only: each pass moves it one edge closer, if at all
        down = (m > 0) & (_edge_at(np.maximum(m - 1, 0), start, stop) > v)
        up = (m <= NUM_BINS) & (_edge_at(np.minimum(m, NUM_BINS), start, stop) <= v)
        if not (down.any() or up.any()):
            return m
        m = m - down + up


def _sorted(columns: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """Each column of `columns` (rows, cols) sorted and promoted to `dtype`: (cols, rows).

    Promotion is monotonic (non-decreasing), so integers and bools are sorted before it, in their
    own, narrower dtype (radix sort for 8 and 16 bits), which gives the same array."""
    if columns.dtype.kind in "biu":
        kind = "stable" if columns.dtype.itemsize <= 2 else None  # numpy's radix sort
        return np.sort(columns.T, axis=1, kind=kind).astype(dtype)
    return np.sort(columns.T.astype(dtype, copy=False), axis=1)


def _quantiles(columns: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """lerobot's histogram quantiles of each column of `columns` (rows, cols), computed (as lerobot
    does) in the promoted dtype, which is also the edges' dtype.

    Returns the values (len(QUANTILES), cols), float64; a mask of the entries that lerobot
    returns as a bare bin edge (the first bin), which keep the edge dtype; and each column's
    (promoted) minimum and maximum, (2, cols).
    """
    rows = columns.shape[0]
    ordered = _sorted(columns, _promoted(columns.dtype))  # (cols, rows)
    start, stop = ordered[:, 0] - _PAD, ordered[:, -1] + _PAD
    targets = np.array([q * rows for q in QUANTILES])
    # The first bin whose cumulative count reaches a target holds the value of rank ceil(target)
    # (histogram counts are integers).
    at_rank = ordered[:, [math.ceil(t) - 1 for t in targets]]  # (cols, quantiles)
    idx = np.minimum(_edges_at_most(at_rank, start, stop) - 1, NUM_BINS - 1)
    lo, hi = _edge_at(idx, start, stop), _edge_at(idx + 1, start, stop)
    below = _count_below(ordered, lo)  # the histogram's cumsum[idx - 1]
    through = np.where(idx < NUM_BINS - 1, _count_below(ordered, hi), rows)  # cumsum[idx]
    first = idx == 0
    with np.errstate(divide="ignore", invalid="ignore"):
        fraction = (targets[None, :] - below) / (through - below)
    values = lo.astype(np.float64) + fraction * (hi - lo).astype(np.float64)
    values[first] = lo[first]
    return values.T, first.T, ordered[:, [0, -1]].T.copy()


def _batch_stats(batches: list[np.ndarray], counts: list[int]) -> list[Stats]:
    """`get_feature_stats`' statistics of each 2-D batch of two rows or more (RunningQuantileStats
    over its rows), reporting `counts` as the sample counts, in lerobot's key order.

    Batches with the same dtype and row count share one sort. The min and max of integers and
    bools are read from it (np.min / np.max over axis 0 of a narrow array are slow loops); those of
    floats come from np.min / np.max, which decide between -0.0 and 0.0 as lerobot's do.
    """
    out = [
        _moments(b.astype(_promoted(b.dtype), copy=False), n, extremes=b.dtype.kind not in "biu")
        for b, n in zip(batches, counts, strict=True)
    ]
    groups: dict[tuple[np.dtype, int], list[int]] = {}
    for i, b in enumerate(batches):
        groups.setdefault((b.dtype, b.shape[0]), []).append(i)
    for (raw, _), members in groups.items():
        dtype = _promoted(raw)
        values, first, extremes = _quantiles(np.concatenate([batches[i] for i in members], axis=1))
        start = 0
        for i in members:
            width = batches[i].shape[1]
            v, f = values[:, start : start + width], first[:, start : start + width]
            if out[i]["min"] is None:
                out[i]["min"], out[i]["max"] = extremes[:, start : start + width]
            start += width
            for k, key in enumerate(QUANTILE_KEYS):
                # lerobot builds each quantile with np.array(list of scalars): float32 only when
                # every entry is a bare float32 edge.
                out[i][key] = v[k].astype(np.float32) if dtype == np.float32 and f[k].all() else v[k]
    return out


def feature_stats(data: np.ndarray) -> Stats:
    """lerobot's `get_feature_stats(data, axis=0, keepdims=data.ndim == 1)` (one numeric column)."""
    return numeric_stats({"x": data})["x"]


def numeric_stats(columns: dict[str, np.ndarray]) -> dict[str, Stats]:
    """lerobot's `compute_episode_stats` for numeric per-frame columns (1-D or (frames, ...))."""
    stats: dict[str, Stats] = {}
    keys, batches = [], []
    for key, data in columns.items():
        if data.shape[0] < 2:  # lerobot's own special case (no histogram, no promotion)
            # (keepdims for 1-D data reshapes the (1,) statistics to (1,): a no-op)
            stats[key] = _basic_stats(data.reshape(-1, 1) if data.ndim == 1 else data, data.shape[0])
            continue
        keys.append(key)
        batches.append(data.reshape(-1, 1) if data.ndim == 1 else data.reshape(-1, data.shape[-1]))
    for key, batch_stats in zip(keys, _batch_stats(batches, [columns[k].shape[0] for k in keys]), strict=True):
        stats[key] = batch_stats
    return {key: stats[key] for key in columns}


def image_sample_indices(length: int) -> np.ndarray:
    """The frames of an episode of `length` frames that lerobot's `sample_images` reads for image
    statistics: up to `length ** 0.75` (at least 100 or all, at most 10 000), evenly spaced, in
    increasing order (`estimate_num_samples`, `sample_indices`)."""
    count = max(min(100, length), min(int(length**0.75), 10_000))
    return np.round(np.linspace(0, length - 1, count)).astype(int)


def _downscaled(frames: np.ndarray) -> np.ndarray:
    """Frames of 300 pixels or more on their longer side downscaled by striding, towards 150 on that
    side (lerobot's `auto_downsample_height_width`)."""
    height, width = frames.shape[1:3]
    step = 1 if max(height, width) < 300 else int(max(height, width) / 150)
    return frames[:, ::step, ::step]


def _image_samples(frames: np.ndarray) -> np.ndarray:
    """The frames lerobot's `sample_images` reads for image statistics, (samples, H', W', C): the
    frames `image_sample_indices` picks, downscaled (`_downscaled`). Written here in numpy because
    importing lerobot's module loads torch: seconds, and hundreds of MB, in every worker."""
    return _downscaled(frames[image_sample_indices(len(frames))])


DEPTH_DTYPES = (np.dtype(np.float32), np.dtype(np.uint16))  # lerobot's depth images: 'm' and 'mm'


def image_stats(frames: np.ndarray, depth: bool = False, sampled: bool = False) -> Stats:
    """lerobot 0.6.1's `compute_episode_stats` statistics of one camera feature (`image` or
    `video`) from its frames held in memory, (T, H, W, C): sampled and downscaled as `sample_images`
    does, then `get_feature_stats` over (0, 2, 3), values of shape (C, 1, 1) and `count` (1,).

    * `depth=False` (RGB): `frames` uint8 (T, H, W, 3), the pixels lerobot reads back from its PNG
      frames; statistics divided by 255 (in [0, 1]).
    * `depth=True`: a depth map, a feature whose `info` has `is_depth_map: True`. `frames` float32
      metres (`depth_unit` 'm') or uint16 millimetres ('mm'), (T, H, W, 1) or (T, H, W): the
      values lerobot writes to and reads back from its TIFF frames in their native dtype. Not
      divided (lerobot divides by 1.0): statistics stay in the stored unit. With two pixels
      sampled or more, min, max, mean and std are float32 for both units (lerobot promotes uint16
      to float32), quantiles float64 (float32 where all are a bin's lower edge); for a single
      sampled pixel (lerobot's unpromoted special case) everything is float32 for metres, float64
      for millimetres. Values must be finite (lerobot's histogram of a NaN is no statistic).

    `sampled=True`: `frames` are already the episode's frames at `image_sample_indices` (a video
    decoded only there), downscaled here.

    `depth_stats(frames)` is `image_stats(frames, depth=True)`.
    """
    frames = np.asarray(frames)
    if depth:
        if frames.ndim == 3:
            frames = frames[..., None]
        if frames.ndim != 4 or frames.shape[-1] != 1 or frames.dtype not in DEPTH_DTYPES:
            raise ValueError(
                f"depth frames must be float32 metres or uint16 millimetres, (T, H, W, 1) or (T, H, W); "
                f"got {frames.dtype} {frames.shape}"
            )
    elif frames.ndim != 4:
        raise ValueError(f"image frames must be (T, H, W, C); got shape {frames.shape}")
    samples = _downscaled(frames) if sampled else _image_samples(frames)
    pixels = samples.reshape(-1, samples.shape[-1])  # lerobot's (samples * H' * W', C) rows
    if pixels.shape[0] < 2:
        stats = _basic_stats(pixels, samples.shape[0])
    else:
        stats = _batch_stats([pixels], [samples.shape[0]])[0]
    factor = 1.0 if depth else 255.0
    return {k: v if k == "count" else np.squeeze(v.reshape(1, -1, 1, 1) / factor, axis=0) for k, v in stats.items()}


def depth_stats(frames: np.ndarray) -> Stats:
    """`image_stats(frames, depth=True)`: a depth feature's statistics, float32 metres or uint16
    millimetres (T, H, W, 1), in the stored unit, as lerobot 0.6.1's `compute_episode_stats`."""
    return image_stats(frames, depth=True)


class RunningStats:
    """Dataset statistics updated episode by episode exactly as lerobot's writer does
    (`stats = aggregate_stats([stats, episode_stats])` after each episode), each step's arithmetic
    done once over the values of all features laid end to end instead of feature by feature.

    It is `aggregate_feature_stats`' arithmetic for two inputs, in the same order and precision
    (float32 statistics are squared before being widened, as numpy does there), so the values are
    lerobot's. Every episode must have the same features (the writer's do).
    """

    def __init__(self) -> None:
        self._first: dict[str, Stats] | None = None  # the statistics while there is one episode
        self._keys: list[str] = []
        self._shapes: list[tuple[int, ...]] = []
        self._sizes = np.zeros(0, dtype=np.int64)  # values per feature
        self._count = np.zeros(0, dtype=np.int64)  # samples per feature
        # mean, std, var (what lerobot's next `std ** 2` evaluates to) and quantiles, float64
        self._flat: dict[str, np.ndarray] = {}
        self._min: list[np.ndarray] = []
        self._max: list[np.ndarray] = []

    def add(self, stats: dict[str, Stats]) -> None:
        """Fold in one episode's statistics (the same features every time)."""
        if self._first is None and not self._keys:
            self._first = stats
            return
        if self._first is not None:
            self._start(self._first)
            self._first = None
        if list(stats) != self._keys:
            raise ValueError(f"episode statistics have features {list(stats)}, earlier ones {self._keys}")
        old, new = self._flat, self._flatten(stats)
        count = np.array([int(stats[k]["count"][0]) for k in self._keys])
        total = self._count + count
        c0, c1, t = (np.repeat(c, self._sizes) for c in (self._count, count, total))
        mean = (old["mean"] * c0 + new["mean"] * c1) / t
        var = ((old["var"] + (old["mean"] - mean) ** 2) * c0 + (new["var"] + (new["mean"] - mean) ** 2) * c1) / t
        std = np.sqrt(var)
        self._flat = {"mean": mean, "std": std, "var": std**2}
        self._flat.update({q: (old[q] * c0 + new[q] * c1) / t for q in QUANTILE_KEYS})
        self._count = total
        for i, key in enumerate(self._keys):
            self._min[i] = np.minimum(self._min[i], stats[key]["min"])
            self._max[i] = np.maximum(self._max[i], stats[key]["max"])

    def _start(self, first: dict[str, Stats]) -> None:
        self._keys = list(first)
        self._shapes = [np.shape(first[k]["mean"]) for k in self._keys]
        self._sizes = np.array([int(np.prod(shape)) for shape in self._shapes], dtype=np.int64)
        self._count = np.array([int(first[k]["count"][0]) for k in self._keys])
        self._flat = self._flatten(first)
        self._min = [first[k]["min"] for k in self._keys]
        self._max = [first[k]["max"] for k in self._keys]

    def _flatten(self, stats: dict[str, Stats]) -> dict[str, np.ndarray]:
        def cat(values: list[np.ndarray]) -> np.ndarray:
            return np.concatenate([np.asarray(v, dtype=np.float64).reshape(-1) for v in values])

        flat = {"mean": cat([stats[k]["mean"] for k in self._keys])}
        flat["var"] = cat([stats[k]["std"] ** 2 for k in self._keys])  # squared in the stats' own dtype
        flat.update({q: cat([stats[k][q] for k in self._keys]) for q in QUANTILE_KEYS})
        return flat

    def result(self) -> dict[str, Stats] | None:
        """The statistics so far in lerobot's layout (None before the first episode)."""
        if not self._keys:
            return self._first
        bounds = np.concatenate([[0], np.cumsum(self._sizes)])
        out: dict[str, Stats] = {}
        for i, key in enumerate(self._keys):
            part = {name: v[bounds[i] : bounds[i + 1]].reshape(self._shapes[i]) for name, v in self._flat.items()}
            out[key] = {
                "min": self._min[i],
                "max": self._max[i],
                "mean": part["mean"],
                "std": part["std"],
                "count": self._count[i : i + 1].copy(),
                **{q: part[q] for q in QUANTILE_KEYS},
            }
        return out


# Statistics that depend on where an episode lands in the dataset; all others are a function of
# the episode alone and can be computed in parallel workers (`episode_stats`).
POSITION_KEYS = ("episode_index", "index", "task_index")


def episode_columns(episode: Episode, features: Features) -> dict[str, Any]:
    """Per-frame columns as lerobot's writer buffers them (scalar features flattened)."""
    n = len(episode)
    columns: dict[str, Any] = {}
    for key, ft in features.items():
        arr = episode.frames[key]
        columns[key] = arr.reshape(n) if tuple(ft["shape"]) == (1,) and ft["dtype"] not in CAMERA_DTYPES else arr
    columns["timestamp"] = episode.frames["timestamp"].astype(
        np.float64
    )  # stored as float32; stats in float64 as lerobot
    columns["frame_index"] = np.arange(n, dtype=np.int64)
    return columns


def episode_stats(episode: Episode, features: Features) -> dict[str, dict[str, np.ndarray]]:
    """lerobot's per-episode statistics of every position-independent column of `episode`
    (`compute_episode_stats`' values, computed by `shiftkit.datasets.stats`)."""
    columns = episode_columns(episode, features)
    # Camera features, image or video: lerobot computes both from the frames before encoding
    # (EncodedFrames carry decoded pixels: statistics read a plain array). Depth statistics are
    # in the stored unit, not scaled to [0, 1].
    # A camera copied from a source video (`VideoRef`) keeps the statistics its source recorded for
    # these frames, as lerobot's merge keeps a source's.
    cameras = {k: columns.pop(k) for k, ft in features.items() if ft["dtype"] in CAMERA_DTYPES}
    stats = numeric_stats(
        {k: v for k, v in columns.items() if k not in features or features[k]["dtype"] not in TEXT_DTYPES}
    )
    for key, frames in cameras.items():
        if getattr(frames, "stats", None) is not None:
            stats[key] = frames.stats
            continue
        # only the frames lerobot's statistics read: a camera still encoded (`VideoRef`) decodes those alone
        picked = np.asarray(frames[image_sample_indices(len(frames))])
        ft = features[key]
        if depth.is_depth(ft):
            stats[key] = image_stats(depth.to_stored(picked, depth.depth_unit(ft)), depth=True, sampled=True)
        else:
            stats[key] = image_stats(picked, sampled=True)
    return stats
