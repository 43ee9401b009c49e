"""Camera frames as bytes and back: the PNG / TIFF bytes lerobot's writer stores for `image`
features, and the one image and video decoder of stages and trainers.

RGB frames are PNG at lerobot's `add_frame` compression level; depth is the raw TIFF lerobot's
`write_image` writes (float32 metres or uint16 millimetres, `depth.py`). A frame that comes from a
source unchanged and is stored in the same form keeps its source bytes (`encoded_frames.py`), so
images are not re-encoded. Decoding gives RGB uint8 (H, W, 3) (grey (H, W, 1)) and depth float32
metres (H, W, 1); video features decode through `video.py`.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import numpy as np

from shiftkit.datasets import depth
from shiftkit.datasets.encoded_frames import PNG, EncodedFrames, source_bytes
from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import DatasetError
from shiftkit.datasets.features import Features
from shiftkit.datasets.video import decode_episode

_PNG_COMPRESS_LEVEL = 6  # what lerobot's add_frame uses for `image` features


def _png_bytes(frame: np.ndarray) -> bytes:
    import PIL.Image

    buf = io.BytesIO()
    PIL.Image.fromarray(frame).save(buf, format="PNG", compress_level=_PNG_COMPRESS_LEVEL)
    return buf.getvalue()


def _tiff_bytes(stored: np.ndarray) -> bytes:
    """One depth frame, (H, W, 1) float32 or uint16, as the raw TIFF lerobot's `write_image` writes
    for depth (PIL mode F / I;16, no compression)."""
    import PIL.Image

    buf = io.BytesIO()
    PIL.Image.fromarray(np.ascontiguousarray(stored[..., 0])).save(buf, format="TIFF", compression="raw")
    return buf.getvalue()


def image_form(ft: dict[str, Any]) -> str:
    """What the encoded bytes of an `image` feature store (`encoded_frames`): PNG RGB, or depth in
    its unit."""
    return f"depth-{depth.depth_unit(ft)}" if depth.is_depth(ft) else PNG


def frame_bytes(frames: np.ndarray, ft: dict[str, Any]) -> list[bytes]:
    """The encoded bytes of every frame of an `image` feature, a frame's source bytes where it is
    unchanged and stored in the same form (`encoded_frames`): PNG for RGB, TIFF in the stored unit
    for depth."""
    form = image_form(ft)
    if depth.is_depth(ft):
        unit = depth.depth_unit(ft)
        return [source_bytes(f, frames, form) or _tiff_bytes(depth.to_stored(f, unit)) for f in frames]
    return [source_bytes(f, frames, form) or _png_bytes(f) for f in frames]


def encode_images(episode: Episode, features: Features) -> Episode:
    """`episode` with every `image` feature as `EncodedFrames` holding each frame's encoded bytes
    (a frame's source bytes where it is unchanged), so that the writer reuses them. Pipeline
    workers call this, so that image encoding, the largest cost of writing images, runs in
    parallel rather than in the one writer."""
    keys = [k for k, ft in features.items() if ft["dtype"] == "image"]
    return episode.with_frames(
        **{
            k: EncodedFrames.wrap(
                episode.frames[k], frame_bytes(episode.frames[k], features[k]), image_form(features[k])
            )
            for k in keys
        }
    )


def decode_image(data: bytes, where: str, ft: dict[str, Any]) -> np.ndarray:
    """One frame of an `image` feature as shiftkit holds it: RGB uint8 (H, W, 3) (grey (H, W, 1) for
    a one-channel camera), depth float32 metres (H, W, 1). The one image decoder of stages and
    trainers."""
    if depth.is_depth(ft):
        return _decode_depth(data, where, ft)
    return _decode_png(data, where, grey=tuple(ft["shape"])[-1] == 1)


def decode_video(path: Path, start: float, timestamps: np.ndarray, where: str, ft: dict[str, Any]) -> np.ndarray:
    """The frames of a `video` feature at `start + timestamps` in the file at `path`, as
    `decode_image` gives them. The one video decoder of stages and trainers."""
    return decode_episode(path, start, timestamps, where, ft.get("info") if depth.is_depth(ft) else None)


def _decode_png(data: bytes, where: str, grey: bool = False) -> np.ndarray:
    import cv2

    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_COLOR)
    if img is None:
        raise DatasetError(f"{where}: undecodable image bytes")
    return img[..., None] if grey else cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _decode_depth(data: bytes, where: str, ft: dict[str, Any]) -> np.ndarray:
    """A lerobot depth image (TIFF, float32 m or uint16 mm; PNG for 16-bit writers) -> (H, W, 1) metres."""
    import PIL.Image

    try:
        with PIL.Image.open(io.BytesIO(data)) as img:
            arr = np.array(img)
    except Exception as exc:  # PIL raises several types for corrupt files
        raise DatasetError(f"{where}: undecodable depth image bytes ({type(exc).__name__})") from None
    if arr.ndim != 2 or arr.dtype not in (np.float32, np.uint16):
        raise DatasetError(f"{where}: depth image of shape {arr.shape} and dtype {arr.dtype} is not one lerobot writes")
    shape = tuple(ft["shape"])
    if arr.shape != shape[:2]:
        raise DatasetError(f"{where}: depth image has shape {arr.shape}, expected {shape[:2]}")
    return depth.clean_metres(depth.to_metres(arr, (ft.get("info") or {}).get("depth_unit")))
