"""Camera features stored as lerobot videos: one sequential PyAV decode per episode, and encoding
through lerobot's own encoder settings and file layout, for RGB and for depth.

Decoding: lerobot's loader decodes frame by frame (a seek per frame); a pipeline needs whole
episodes, so the reader seeks once to the episode's start in the (concatenated) video file and
decodes forward, matching frames to the episode's timestamps with lerobot's tolerance. PyAV is the
backend that works here (torchcodec cannot load its FFmpeg libraries on these machines). Depth
videos (12-bit `gray12le` codes) are dequantised with the parameters lerobot recorded in the
feature's `info` (`video.depth_min/max/shift/use_log`), in numpy with lerobot's formula, so that
pipeline workers need not import torch (lerobot's `dequantize_depth` does; a test compares them).

Encoding: `encode_frames` is lerobot's `encode_video_frames` (an `RGBEncoderConfig` or a
`DepthEncoderConfig`: codec, options, pixel format, lerobot's `quantize_depth`) fed from memory
instead of from PNG / TIFF files; lerobot's writer then appends the episode to the current video
file and fills the feature's `info` from the first episode (`writer.DatasetWriter`).
"""

from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import Any

import numpy as np

from shiftkit.datasets.depth import VIDEO_DEFAULTS
from shiftkit.datasets.errors import DatasetError

TOLERANCE_S = 1e-4  # lerobot's default tolerance between a frame's timestamp and the query


@functools.cache
def decoder_backend() -> str:
    """The video backend to give lerobot's `LeRobotDataset`: `torchcodec` where it loads FFmpeg
    here, else `pyav` (whose wheels bundle their own FFmpeg). Chosen up front because lerobot,
    left to choose, tries torchcodec and logs its loader's traceback (~40 lines, one per FFmpeg
    version) before falling back to PyAV itself. No FFmpeg shared library on the library path: PyAV,
    silently (nothing to fix); FFmpeg present but torchcodec still failing (a torch / torchcodec
    mismatch): PyAV, and one line that says why."""
    import ctypes.util
    import importlib.util
    import logging

    if importlib.util.find_spec("torchcodec") is None or ctypes.util.find_library("avutil") is None:
        return "pyav"
    try:
        import torchcodec  # noqa: F401 - loads its FFmpeg libraries on import
    except (ImportError, OSError, RuntimeError) as exc:
        first = next((line.strip() for line in str(exc).splitlines() if line.strip()), type(exc).__name__)
        logging.getLogger(__name__).warning("torchcodec cannot load FFmpeg here (%s); decoding videos with PyAV", first)
        return "pyav"
    return "torchcodec"


def decode_episode(
    path: Path, start: float, timestamps: np.ndarray, where: str, depth_info: dict[str, Any] | None = None
) -> np.ndarray:
    """The frames at `start + timestamps` (seconds) of the video at `path`: (T, H, W, 3) uint8 RGB,
    or, with `depth_info` (a depth feature's `info`), (T, H, W, 1) float32 metres."""
    import av

    queries = start + np.asarray(timestamps, dtype=np.float64)
    frames: list[np.ndarray | None] = [None] * len(queries)
    try:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            stream.thread_type = "AUTO"
            base = float(stream.time_base)
            container.seek(max(int(queries[0] / base) - 1, 0), stream=stream, backward=True)
            for frame in container.decode(stream):
                t = frame.pts * base
                if t > queries[-1] + TOLERANCE_S:
                    break
                j = int(np.clip(np.searchsorted(queries, t), 1, len(queries) - 1)) if len(queries) > 1 else 0
                j = j - 1 if j > 0 and abs(queries[j - 1] - t) < abs(queries[j] - t) else j
                if abs(queries[j] - t) <= TOLERANCE_S:
                    frames[j] = frame.to_ndarray(format="rgb24" if depth_info is None else "gray12le")
    except (av.error.FFmpegError, OSError) as exc:
        raise DatasetError(f"{where}: cannot decode {path} ({type(exc).__name__}: {exc})") from None
    missing = [i for i, f in enumerate(frames) if f is None]
    if missing:
        raise DatasetError(
            f"{where}: {path.name} has no frame at {queries[missing[0]]:.4f} s "
            f"({len(missing)} of {len(queries)} frames missing; tolerance {TOLERANCE_S} s)"
        )
    out = np.stack(frames)
    return out if depth_info is None else dequantize_metres(out, depth_info)[..., None]


def depth_quantiser(info: dict[str, Any] | None) -> tuple[float, float, float, bool]:
    """(depth_min, depth_max, shift, use_log) in metres from a depth video feature's `info`
    (lerobot's defaults for keys it did not record)."""
    info = info or {}
    return tuple(info.get(f"video.{k}", v) for k, v in VIDEO_DEFAULTS.items())  # type: ignore[return-value]


def dequantize_metres(codes: np.ndarray, info: dict[str, Any] | None) -> np.ndarray:
    """lerobot's `dequantize_depth(..., output_unit="m")` (numpy path) on 12-bit codes of any shape."""
    depth_min, depth_max, shift, use_log = depth_quantiser(info)
    qmax = 4095  # lerobot's DEPTH_QMAX (12 bits)
    if use_log:
        log_min, log_max = math.log(depth_min + shift), math.log(depth_max + shift)
        scale, offset = (log_max - log_min) / qmax, log_min
    else:
        scale, offset = (depth_max - depth_min) / qmax, depth_min
    buf = np.empty(codes.shape, dtype=np.float32)
    np.multiply(codes, scale, out=buf)
    np.add(buf, offset, out=buf)
    if use_log:
        np.exp(buf, out=buf)
        np.subtract(buf, shift, out=buf)
    np.clip(buf, depth_min, depth_max, out=buf)
    return buf


def encode_frames(frames: np.ndarray, path: Path, fps: int, encoder: Any, encoder_threads: int | None = None) -> None:
    """lerobot's `encode_video_frames` (same codec, options, pixel format and muxing; depth through
    its `quantize_depth`) fed from memory: it reads the PNG / TIFF files a recorder wrote, which a
    pipeline would have to write first. `encoder`: lerobot's `RGBEncoderConfig` for uint8
    (T, H, W, 3) frames or `DepthEncoderConfig` for (T, H, W, 1) depth in its stored unit."""
    import logging

    import av
    from lerobot.configs import DepthEncoderConfig

    is_depth = isinstance(encoder, DepthEncoderConfig)
    if is_depth:
        from lerobot.datasets.depth_utils import quantize_depth
    options = encoder.get_codec_options(encoder_threads, as_strings=True)
    logging.getLogger("libav").setLevel(av.logging.WARNING)
    try:
        with av.open(str(path), "w") as output:
            stream = output.add_stream(encoder.vcodec, fps, options=options)
            stream.pix_fmt = encoder.pix_fmt
            stream.height, stream.width = frames.shape[1:3]
            for frame in frames:
                if is_depth:
                    video_frame = quantize_depth(
                        np.asarray(frame)[..., 0],
                        depth_min=encoder.depth_min,
                        depth_max=encoder.depth_max,
                        shift=encoder.shift,
                        use_log=encoder.use_log,
                        pix_fmt=encoder.pix_fmt,
                        video_backend="pyav",
                    )
                else:
                    video_frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")
                packet = stream.encode(video_frame)
                if packet:
                    output.mux(packet)
            packet = stream.encode()
            if packet:
                output.mux(packet)
    finally:
        av.logging.restore_default_callback()
