"""Fast batches from LeRobot v3.0 datasets for supervised trainers.

`lerobot`'s `__getitem__` builds one frame at a time (a dict of tensors, a task lookup, a video seek
per camera); a small BC network trains faster than that can feed it. `FrameTable` instead reads
whole batches by global frame index, straight from the dataset's memory-mapped Arrow table:

* numeric features (`observation.state`, `action`, ...): one contiguous numpy array per feature,
  gathered with numpy fancy indexing;
* image features (`dtype: image`, PNG or depth TIFF bytes inside Arrow): only the batch's rows are
  taken from Arrow and decoded, once per batch, by the pipelines' decoder (depth in metres);
* video features: every episode is decoded once, sequentially, into a frame array (random seeks
  into video per frame would dominate training time); `max_decoded_bytes` bounds it.

`Prefetcher` runs the gathering in a background thread so the training loop only waits when the
data is slower than the model. Several datasets with the same features are read as one.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from shiftkit import datasets
from shiftkit.datasets.dataset import Dataset, as_dataset
from shiftkit.datasets.errors import DatasetError
from shiftkit.datasets.features import numpy_dtype
from shiftkit.datasets.images import decode_image, decode_video


def open_datasets(refs: list[str], root: str | None = None) -> list[tuple[Dataset, object]]:
    """The datasets `refs` name (IDs or local paths; `root`: the one dataset's folder), each with its
    lerobot `LeRobotDataset` (`Dataset.lerobot`), whose Arrow table the batches read."""
    if not refs:
        raise DatasetError("no dataset given")
    opened = [datasets.open(ref, root=root) for ref in refs]
    return [(dataset, dataset.lerobot) for dataset in opened]


def example_set_origin(dataset: Dataset | str | Path) -> str | None:
    """What made `dataset` (a handle or a folder) a success-example set (frames of successful states,
    not demonstrations), as its provenance says: the `success_examples` stage or `import vpace` of
    example files; None for anything else."""
    provenance = as_dataset(dataset).provenance
    stages = [s["name"] for s in provenance.get("stages", [])]
    importer = provenance.get("importer") or {}
    if "success_examples" in stages:
        return "the success_examples stage"
    if importer.get("kind") == "examples":
        return f"`import {importer.get('name')}` of example files"
    return None


def refuse_example_sets(opened: list[tuple[Dataset, object]], trainer: str) -> None:
    """Trainers that imitate demonstrations (BC, FIRE, LfGP) refuse a success-example set: its
    frames are isolated successful states, and their actions are no demonstration."""
    for dataset, _ in opened:
        origin = example_set_origin(dataset)
        if origin is not None:
            raise DatasetError(
                f"{dataset.repo_id} is a success-example set (made by {origin}), not demonstrations: {trainer} "
                "learns from trajectories; give it to `train vpace --examples` instead"
            )


def numeric_column(ds, key: str) -> np.ndarray:
    """A numeric feature of every frame as one `(N, *shape)` float32 array."""
    column = ds.hf_dataset.with_format("numpy", columns=[key])[key]
    shape = tuple(ds.meta.features[key]["shape"])
    return np.asarray(column, dtype=np.float32).reshape(len(column), *shape)


def _decode_video_feature(ds, key: str, max_bytes: int) -> np.ndarray:
    """Every frame of a video feature, in dataset row order (RGB uint8 `(N, H, W, 3)`, depth
    float32 metres `(N, H, W, 1)`), decoded episode by episode by the pipelines' video decoder
    (random seeks per frame would dominate training time)."""
    ft = ds.meta.features[key]
    dtype = numpy_dtype(ft)
    n, shape = len(ds.hf_dataset), tuple(ft["shape"])
    size = n * int(np.prod(shape)) * dtype.itemsize
    if size > max_bytes:
        raise DatasetError(
            f"decoding video feature {key!r} of {ds.repo_id} needs {size / 2**30:.1f} GiB "
            f"(limit {max_bytes / 2**30:.1f} GiB); raise max_decoded_bytes or use a smaller image size"
        )
    cols = ds.hf_dataset.with_format("numpy", columns=["episode_index", "timestamp"])[:]
    out = np.empty((n, *shape), dtype=dtype)
    episodes = ds.meta.episodes
    for ep in np.unique(cols["episode_index"]):
        rows = np.flatnonzero(cols["episode_index"] == ep)
        path = ds.root / ds.meta.get_video_file_path(int(ep), key)
        start = float(episodes[int(ep)][f"videos/{key}/from_timestamp"])
        out[rows] = decode_video(path, start, cols["timestamp"][rows], f"{ds.repo_id} episode {ep} {key}", ft)
    return out


def _decode_image_rows(column, rows: np.ndarray, ft: dict) -> np.ndarray:
    """Decode the images at `rows` of an Arrow image column (struct of bytes/path) with the
    pipelines' image decoder."""
    import pyarrow as pa

    taken = column.take(pa.array(rows))
    images = []
    for item in taken.to_pylist():
        data = item["bytes"] if item["bytes"] is not None else Path(item["path"]).read_bytes()
        images.append(decode_image(data, f"dataset image (row {len(images)} of batch)", ft))
    return np.stack(images)


class FrameTable:
    """The frames of one or more LeRobot datasets, read in batches of global frame indices.

    Global index `i` runs over the datasets' rows in order. `episodes` lists each episode's
    `[start, end)` global row range (episodes never span datasets)."""

    def __init__(self, datasets: list, keys: list[str], max_decoded_bytes: int = 8 * 2**30) -> None:
        first = datasets[0].meta.features
        for ds in datasets:
            for key in keys:
                if key not in ds.meta.features:
                    raise DatasetError(f"dataset {ds.repo_id} has no feature {key!r}")
                if tuple(ds.meta.features[key]["shape"]) != tuple(first[key]["shape"]):
                    raise DatasetError(
                        f"feature {key!r} has shape {ds.meta.features[key]['shape']} in {ds.repo_id} "
                        f"but {first[key]['shape']} in {datasets[0].repo_id}"
                    )
        self.keys = keys
        self.features = {key: first[key] for key in keys}
        self._arrays: dict[str, np.ndarray] = {}
        self._png_columns: dict[str, list] = {}
        offsets = np.cumsum([0] + [len(ds.hf_dataset) for ds in datasets])
        self._offsets = offsets
        self.num_frames = int(offsets[-1])
        self.episodes: list[tuple[int, int]] = []
        for ds, offset in zip(datasets, offsets[:-1], strict=True):
            ep = ds.hf_dataset.with_format("numpy", columns=["episode_index"])["episode_index"]
            cuts = np.flatnonzero(np.diff(ep)) + 1
            starts, ends = np.r_[0, cuts], np.r_[cuts, len(ep)]
            self.episodes += [(int(offset + s), int(offset + e)) for s, e in zip(starts, ends, strict=True)]
        for key in keys:
            dtype = first[key]["dtype"]
            if dtype == "image":
                self._png_columns[key] = [ds.hf_dataset.data.column(key) for ds in datasets]
            elif dtype == "video":
                self._arrays[key] = np.concatenate(
                    [_decode_video_feature(ds, key, max_decoded_bytes) for ds in datasets]
                )
            else:
                self._arrays[key] = np.concatenate([numeric_column(ds, key) for ds in datasets])

    def gather(self, rows: np.ndarray) -> dict[str, np.ndarray]:
        """Feature arrays for the frames at global indices `rows`: numeric as float32, RGB images as
        uint8 `(B, H, W, 3)`, depth as float32 metres `(B, H, W, 1)`."""
        batch = {key: arr[rows] for key, arr in self._arrays.items()}
        for key, columns in self._png_columns.items():
            ft = self.features[key]
            which = np.searchsorted(self._offsets, rows, side="right") - 1
            out = np.empty((len(rows), *ft["shape"]), dtype=numpy_dtype(ft))
            for d in np.unique(which):
                sel = np.flatnonzero(which == d)
                out[sel] = _decode_image_rows(columns[d], rows[sel] - self._offsets[d], ft)
            batch[key] = out
        return batch

    def split_episodes(self, val_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """Global frame indices of training and held-out episodes; a seeded `val_fraction` of the
        episodes (at least one when the fraction is positive) is held out."""
        n_ep = len(self.episodes)
        n_val = int(round(val_fraction * n_ep)) if val_fraction > 0 else 0
        n_val = max(n_val, 1) if val_fraction > 0 else 0
        if n_val >= n_ep:
            raise DatasetError(f"cannot hold out {val_fraction:.0%} of {n_ep} episode(s) and still train")
        held = set(np.random.default_rng([seed, 0x5E1]).permutation(n_ep)[:n_val].tolist())

        def frames(eps: list[int]) -> np.ndarray:
            ranges = [np.arange(*self.episodes[e]) for e in eps]
            return np.concatenate(ranges) if ranges else np.zeros(0, dtype=np.int64)

        return frames([e for e in range(n_ep) if e not in held]), frames(sorted(held))


def epoch_batches(n: int, batch_size: int, seed: int, stream: int, epoch: int) -> list[np.ndarray]:
    """Positions `0..n-1` shuffled for one epoch of one sample stream (e.g. one ensemble member), in
    batches; the order depends only on (seed, stream, epoch), so a resumed run replays it exactly."""
    perm = np.random.default_rng([seed, stream, epoch]).permutation(n)
    per_epoch = max(1, n // batch_size)
    return [perm[i * batch_size : (i + 1) * batch_size] for i in range(per_epoch)]


def batches_per_epoch(n: int, batch_size: int) -> int:
    """How many batches `epoch_batches` yields per epoch (the last partial batch is dropped)."""
    return max(1, n // batch_size)


class Prefetcher:
    """Gathers batches in a background thread: iterate it to get dicts of torch tensors.

    `rows` yields arrays of global frame indices; batches come out in the same order."""

    _END = object()

    def __init__(self, table: FrameTable, rows: Iterator[np.ndarray], depth: int = 4, pin: bool = False) -> None:
        self._table, self._rows, self._pin = table, rows, pin
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._work, name="shiftkit-prefetch", daemon=True)
        self._thread.start()

    def _work(self) -> None:
        try:
            for rows in self._rows:
                if self._stop.is_set():
                    return
                batch = {k: torch.from_numpy(v) for k, v in self._table.gather(rows).items()}
                if self._pin:
                    batch = {k: v.pin_memory() for k, v in batch.items()}
                self._put(batch)
        except BaseException as exc:  # surfaced in the consumer thread
            self._put(exc)
            return
        self._put(self._END)

    def _put(self, item: object) -> None:
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.1)
                return
            except queue.Full:
                continue

    def __iter__(self) -> Iterator[dict[str, torch.Tensor]]:
        while True:
            item = self._queue.get()
            if item is self._END:
                return
            if isinstance(item, BaseException):
                raise item
            yield item

    def close(self) -> None:
        """Stop the worker thread (safe to call twice)."""
        self._stop.set()
        self._thread.join(timeout=5)

    def __enter__(self) -> Prefetcher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
