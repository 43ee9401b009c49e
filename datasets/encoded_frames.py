"""Decoded camera frames that remember the bytes they came from (PNG for RGB, TIFF for depth), so
an unchanged frame is not encoded again when it is written.

PNG encoding at lerobot's compression level (PIL, level 6) is the largest cost of writing an image
dataset (~10 ms per 96x96 frame here, more than reading, statistics and parquet together). Most
stages pass frames through unchanged (filter, trim, subsample, rename, ...). The reader returns
image features as `EncodedFrames`: a plain uint8 array plus a map from each frame's content (a
CRC-32 key, confirmed by comparing the pixels with a copy of the decoded frame) to its source
bytes. The writer reuses the bytes only when a frame's pixels equal the decoded ones, so a frame
that a stage changed, in place or not, is always encoded afresh. The map survives slicing, pickling
(the runner's parts) and `Episode.select`; arrays built anew by a stage are plain arrays, which the
pipeline's workers encode and wrap before they store a part (`images.encode_images`), so the one
writer only copies bytes. PNG and TIFF decoding are lossless, so the written pixels are the same either way;
for sources written by lerobot or shiftkit (PIL at level 6, deterministic) the bytes are the same
too.

Bytes are also tagged with their *form*, what their decoded values are stored as ("png" for RGB,
"depth-m" / "depth-mm" for float32-metre / uint16-millimetre depth): a depth frame held in metres
decodes the same from either, so only the form says whether the bytes can be written under the
destination feature's unit (reusing millimetre bytes under a metre feature would store 1000x the
depth).
"""

from __future__ import annotations

import zlib
from typing import Any

import numpy as np


def _key(frame: np.ndarray) -> tuple[tuple[int, ...], int]:
    """A cheap lookup key (shape, CRC-32 of the pixels); a hit is confirmed by comparing pixels."""
    return frame.shape, zlib.crc32(np.ascontiguousarray(frame).data)


PNG = "png"


class EncodedFrames(np.ndarray):
    """(T, H, W, C) frames with `encoded`: {key: (a copy of the frame as decoded, its source bytes)},
    all in the stored form `form`."""

    encoded: dict[tuple, tuple[np.ndarray, bytes]] | None
    form: str | None

    @classmethod
    def wrap(cls, frames: np.ndarray, encoded: list[bytes], form: str = PNG) -> EncodedFrames:
        """`frames` as `EncodedFrames`, each frame remembering `encoded`, its source bytes (one per
        frame), stored in `form`."""
        out = np.asarray(frames).view(cls)
        out.encoded = {_key(f): (np.array(f), b) for f, b in zip(frames, encoded, strict=True)}
        out.form = form
        return out

    def __array_finalize__(self, obj: Any) -> None:
        self.encoded = getattr(obj, "encoded", None)
        self.form = getattr(obj, "form", None)

    def __reduce__(self) -> tuple:
        # Only the bytes of this array's own frames travel, checked now; the decoded copies that
        # confirm a hit are the frames themselves again after unpickling (a part holds no second
        # copy of the pixels).
        constructor, args, state = super().__reduce__()
        encoded = [source_bytes(f, self) for f in self] if self.encoded and self.ndim == 4 else None
        return constructor, args, (state, encoded, self.form)

    def __setstate__(self, state: tuple) -> None:
        array_state, encoded, self.form = state
        super().__setstate__(array_state)
        self.encoded = None
        if encoded is not None:
            self.encoded = {_key(f): (np.array(f), b) for f, b in zip(self, encoded, strict=True) if b is not None}


def source_bytes(frame: np.ndarray, frames: np.ndarray, form: str = PNG) -> bytes | None:
    """The bytes `frame` (one of `frames`) was read from, if its pixels are unchanged and they are
    stored in `form`; else None."""
    encoded = getattr(frames, "encoded", None) if getattr(frames, "form", None) == form else None
    hit = encoded.get(_key(frame)) if encoded else None
    return hit[1] if hit is not None and np.array_equal(hit[0], frame) else None
