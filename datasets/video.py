"""Camera features stored as lerobot videos: one forward PyAV decode per episode, and encoding
through lerobot's own encoder settings and file layout, for RGB and for depth.

Decoding: lerobot's loader decodes frame by frame (a seek per frame); a pipeline needs whole
episodes, so the reader seeks once to the episode's start in the (concatenated) video file and
decodes forward, matching frames to the episode's timestamps with lerobot's tolerance (in an AV1
stream, only the packets the asked frames need: `decoded_pictures`); the file
stays open for the next episode (lerobot puts many episodes in one file), so a process opens each
file once, not once per episode and camera. PyAV is the
backend that works here (torchcodec cannot load its FFmpeg libraries on these machines). Depth
videos (12-bit `gray12le` codes) are dequantised with the parameters lerobot recorded in the
feature's `info` (`video.depth_min/max/shift/use_log`), in numpy with lerobot's formula, so that
pipeline workers need not import torch (lerobot's `dequantize_depth` does; a test compares them).

Encoding: `encode_frames` is lerobot's `encode_video_frames` (an `RGBEncoderConfig` or a
`DepthEncoderConfig`: codec, options, pixel format, lerobot's `quantize_depth`) fed from memory
instead of from PNG / TIFF files; lerobot's writer then appends the episode to the current video
file and fills the feature's `info` from the first episode (`writer.DatasetWriter`). `encoder_for`
picks the encoder of a feature (the source's recorded settings, else lerobot's defaults) for the
writer and for pipeline workers alike: a worker encodes each episode's cameras into a file of its
own (`encode_episode_video` -> `EncodedVideo`), so encoding runs in parallel across workers and a
run's work folder holds encoded video rather than pixels; the writer appends those files. An RGB
camera's encoder reaches workers as plain data (`Codec`, `codec_for`), resolved with lerobot's code
in the main process (`resolve`, `answers`): importing lerobot imports torch (3-6 s and ~0.7 GB per
process here), which a worker that copies, cuts or encodes RGB video does not need.
"""

from __future__ import annotations

import bisect
import collections
import contextlib
import dataclasses
import functools
import logging
import math
import os
from collections.abc import Callable, Iterable, Iterator
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from shiftkit.datasets import depth
from shiftkit.datasets.depth import VIDEO_DEFAULTS
from shiftkit.datasets.errors import DatasetError
from shiftkit.datasets.jsonutil import dumps

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


# The video files this process read last, open: episodes of one file (lerobot puts many in each)
# are decoded with one container and decoder, not one per episode and camera. Keyed by the
# file's size and time (a rewritten file is opened anew) and the process (a forked worker does not
# share its parent's file offsets).
_OPEN: collections.OrderedDict[tuple, Any] = collections.OrderedDict()
_KEEP_OPEN = 8


def _opened(path: Path) -> tuple[tuple, Any]:
    """(cache key, an open PyAV container of `path`), from `_OPEN` where it is there."""
    import av

    st = path.stat()
    key = (str(path), st.st_size, st.st_mtime_ns, os.getpid())
    container = _OPEN.pop(key, None)
    if container is None:
        container = av.open(str(path))
        container.streams.video[0].thread_type = "AUTO"
    _OPEN[key] = container
    while len(_OPEN) > _KEEP_OPEN:
        _, old = _OPEN.popitem(last=False)
        old.close()
    return key, container


def decode_episode(
    path: Path, start: float, timestamps: np.ndarray, where: str, depth_info: dict[str, Any] | None = None
) -> np.ndarray:
    """The frames at `start + timestamps` (seconds) of the video at `path`: (T, H, W, 3) uint8 RGB,
    or, with `depth_info` (a depth feature's `info`), (T, H, W, 1) float32 metres."""
    pictures = decoded_pictures(path, start, timestamps, where)
    out = np.stack([p.to_ndarray(format="rgb24" if depth_info is None else "gray12le") for p in pictures])
    return out if depth_info is None else dequantize_metres(out, depth_info)[..., None]


def decoded_pictures(path: Path, start: float, timestamps: np.ndarray, where: str) -> list[Any]:
    """The pictures at `start + timestamps` (seconds) of the video at `path`, in the decoder's own
    pixel format (PyAV frames), one per timestamp, matched with lerobot's tolerance. Where the stream
    is in presentation order (lerobot's AV1), only the packets the asked frames need are decoded,
    each from the keyframe before it (`decode_pictures`): every other frame of lerobot's `g=2`
    stream (a `subsample`) decodes half the episode."""
    import av

    queries = start + np.asarray(timestamps, dtype=np.float64)
    found: list[Any] = [None] * len(queries)
    key = None
    try:
        key, container = _opened(Path(path))
        stream = container.streams.video[0]
        base = float(stream.time_base)
        container.seek(max(int(queries[0] / base) - 1, 0), stream=stream, backward=True)
        stream.codec_context.flush_buffers()  # nothing left of the episode decoded before
        packets = []  # the episode's, to the last asked frame (a packet's dts is at or before its pts)
        for packet in container.demux(stream):
            if packet.dts is None:  # the demuxer's flush packet
                continue
            if packet.dts * base > queries[-1] + TOLERANCE_S:
                break
            packets.append(packet)
        pts = [p.pts for p in packets]
        if packets and packets[0].is_keyframe and None not in pts and bool(np.all(np.diff(pts) > 0)):
            wanted = {int(k) for k in _nearest(np.asarray(pts) * base, queries) if k >= 0}
            pictures = decode_pictures(stream.codec_context, packets, {pts[k] for k in wanted}).values()
        else:  # frames reordered (B-frames): decoded in full
            pictures = [f for p in packets for f in p.decode()] + list(stream.codec_context.decode(None))
        for picture in pictures:
            j = _nearest(queries, np.array([picture.pts * base]))[0]
            if j >= 0:
                found[j] = picture
    except (av.error.FFmpegError, OSError) as exc:
        _OPEN.pop(key, None)
        raise DatasetError(f"{where}: cannot decode {path} ({type(exc).__name__}: {exc})") from None
    missing = [i for i, f in enumerate(found) if f is None]
    if missing:
        raise DatasetError(
            f"{where}: {path.name} has no frame at {queries[missing[0]]:.4f} s "
            f"({len(missing)} of {len(queries)} frames missing; tolerance {TOLERANCE_S} s)"
        )
    return found


def _nearest(times: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """Per query, the index of the nearest of the increasing `times` within lerobot's tolerance, else -1."""
    j = (
        np.clip(np.searchsorted(times, queries), 1, max(len(times) - 1, 1))
        if len(times) > 1
        else np.zeros(len(queries), int)
    )
    j = np.where((j > 0) & (np.abs(times[j - 1] - queries) < np.abs(times[j] - queries)), j - 1, j)
    return np.where(np.abs(times[j] - queries) <= TOLERANCE_S, j, -1)


def decode_pictures(decoder: Any, packets: list[Any], wanted: set[int]) -> dict[int, Any]:
    """The pictures with pts in `wanted`, each decoded from the keyframe at or before it, in the
    decoder's own pixel format; `packets` in presentation order from a keyframe. Packets that no
    wanted picture needs are not decoded. An AV1 decoder is fed the needed runs one after the other
    (a sync sample of AV1 in MP4 is a key frame that refreshes every reference, so nothing left out
    is referred to); another codec's is drained and reset before each run."""
    need = [k for k, p in enumerate(packets) if p.pts in wanted]
    keys = [k for k, p in enumerate(packets) if p.is_keyframe]
    spans: list[list[int]] = []  # [first, last] packets to decode, each from a keyframe
    for k in need:
        first = keys[bisect.bisect_right(keys, k) - 1]
        if spans and first <= spans[-1][1] + 1:
            spans[-1][1] = k
        else:
            spans.append([first, k])
    av1 = decoder.codec.canonical_name == "av1"
    pictures = {}
    for i, (first, last) in enumerate(spans):
        for packet in packets[first : last + 1]:
            pictures.update((f.pts, f) for f in packet.decode() if f.pts in wanted)
        if not av1 or i == len(spans) - 1:
            pictures.update((f.pts, f) for f in decoder.decode(None) if f.pts in wanted)  # the decoder's delay
            decoder.flush_buffers()
    return pictures


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


@contextlib.contextmanager
def scheduling_kept() -> Iterator[None]:
    """The calling thread's scheduling policy as it was before the block, after it. SVT-AV1
    (lerobot's default encoder), run as root, makes the thread that opens it real-time (SCHED_FIFO,
    priority 99; measured here through PyAV), and every process that thread starts inherits that:
    a pipeline's workers, a trainer, a cluster node. On a small machine a busy real-time process
    starves the others, its parent's timeouts included. Wrapped around every encoder shiftkit opens."""
    try:
        policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    except (AttributeError, OSError):  # not Linux: no such policy change to undo
        yield
        return
    try:
        yield
    finally:
        if os.sched_getscheduler(0) != policy:
            os.sched_setscheduler(0, policy, param)


def encode_frames(frames: np.ndarray, path: Path, fps: int, encoder: Any) -> None:
    """lerobot's `encode_video_frames` (same codec, options, pixel format and muxing; depth through
    its `quantize_depth`) fed from memory: it reads the PNG / TIFF files a recorder wrote, which a
    pipeline would have to write first. `encoder`: a `Codec` or lerobot's `RGBEncoderConfig` for
    uint8 (T, H, W, 3) frames, lerobot's `DepthEncoderConfig` for (T, H, W, 1) depth in its stored
    unit."""
    import av

    if not isinstance(encoder, Codec) and _is_depth_encoder(encoder):
        from lerobot.datasets.depth_utils import quantize_depth

        def picture(frame: np.ndarray) -> Any:
            return quantize_depth(
                np.asarray(frame)[..., 0],
                depth_min=encoder.depth_min,
                depth_max=encoder.depth_max,
                shift=encoder.shift,
                use_log=encoder.use_log,
                pix_fmt=encoder.pix_fmt,
                video_backend="pyav",
            )
    else:

        def picture(frame: np.ndarray) -> Any:
            return av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")

    encode_pictures((picture(f) for f in frames), len(frames), frames.shape[1:3], path, fps, encoder)


def _is_depth_encoder(encoder: Any) -> bool:
    from lerobot.configs import DepthEncoderConfig

    return isinstance(encoder, DepthEncoderConfig)


def encode_pictures(
    pictures: Iterable[Any], count: int, size: tuple[int, int], path: Path, fps: int, encoder: Any
) -> None:
    """`count` pictures (PyAV frames) of `size` (height, width) encoded into `path` at `fps` as
    lerobot's `encode_video_frames` encodes, each handed to the encoder in its own pixel format
    (PyAV converts it to the encoder's where it differs). `encoder`: a `Codec` or one of lerobot's
    encoder configs."""
    import logging

    import av

    codec = Codec.of(encoder)
    check_frame_size(codec.vcodec, *size)
    logging.getLogger("libav").setLevel(av.logging.WARNING)
    try:
        with scheduling_kept(), av.open(str(path), "w") as output:
            stream = output.add_stream(codec.vcodec, fps, options=dict(codec.options))
            stream.pix_fmt = codec.pix_fmt
            stream.height, stream.width = size
            for picture in pictures:
                for packet in stream.encode(picture):
                    output.mux(_with_sane_dts(packet, count))
            for packet in stream.encode():
                output.mux(_with_sane_dts(packet, count))
    finally:
        av.logging.restore_default_callback()


# SVT-AV1 3.0 (lerobot's default codec, through PyAV) stops the whole process with a floating-point
# exception on frames narrower than this (measured: 24 px and less crash, 25 px and more encode).
SVT_AV1_MIN_WIDTH = 25


def check_frame_size(vcodec: str, height: int, width: int) -> None:
    """DatasetError, in one line, for a frame size the encoder would crash on instead of refusing."""
    if vcodec in ("libsvtav1", "av1") and width < SVT_AV1_MIN_WIDTH:
        raise DatasetError(
            f"{vcodec} cannot encode frames {width} px wide (SVT-AV1 needs at least {SVT_AV1_MIN_WIDTH}): "
            'store this camera as images, make it wider, or encode it with another codec (vcodec = "h264")'
        )


def _with_sane_dts(packet: Any, frames: int) -> Any:
    """`packet` with a decode time the muxer takes: libx265 (through PyAV) leaves it unset or
    uninitialised (e.g. -1.4e14) on the packet of a one-frame stream, which the MP4 muxer refuses
    ("Not yet implemented in FFmpeg"), so that lerobot's writer fails on most one-frame depth
    episodes (a success example is one). A decode time can only lie up to the stream's frame count
    before the presentation time, and never after it; outside that it is the presentation time."""
    if packet.pts is not None and (packet.dts is None or not packet.pts - frames <= packet.dts <= packet.pts):
        packet.dts = packet.pts
    return packet


@functools.cache
def default_encoders() -> dict[str, Any]:
    """lerobot's default encoders: "rgb" and "depth" (one object each per process)."""
    from lerobot.configs import depth_encoder_defaults, rgb_encoder_defaults

    return {"rgb": rgb_encoder_defaults(), "depth": depth_encoder_defaults()}


def encoder_for(ft: dict[str, Any]) -> Any:
    """The encoder of a video feature: for RGB, the settings its source recorded in the feature's
    `info` (codec, pixel format, g, crf, preset: lerobot's `encoder_config_from_video_info`, as its
    `delete_episodes` re-encodes), so an edit keeps the source's codec; lerobot's defaults for a
    feature without them (a camera that was no video, or resized), for a codec this machine cannot
    encode (a warning says so) and for depth."""
    info = ft.get("info") or {}
    if depth.is_depth(ft) or "video.codec" not in info:
        return default_encoders()["depth" if depth.is_depth(ft) else "rgb"]
    return _recorded_encoder(dumps({k: v for k, v in info.items() if k.startswith("video.")}))


@functools.cache
def _recorded_encoder(settings: str) -> Any:
    """One encoder per recorded settings: lerobot's config probes PyAV's codecs."""
    import json

    from lerobot.configs.video import encoder_config_from_video_info

    try:
        return encoder_config_from_video_info(json.loads(settings))
    except ValueError as exc:  # e.g. a hardware encoder this machine lacks: lerobot's defaults
        logging.getLogger(__name__).warning("encoding with lerobot's defaults instead of %s (%s)", settings, exc)
        return default_encoders()["rgb"]


@dataclasses.dataclass(frozen=True)
class Codec:
    """What PyAV needs to encode as one of lerobot's encoder configs says, as plain data (a worker
    gets it from the main process and need not import lerobot)."""

    vcodec: str
    """The encoder (FFmpeg's name, e.g. `libsvtav1`)."""
    pix_fmt: str
    """The pixel format it encodes in."""
    options: tuple[tuple[str, str], ...]
    """Its options as lerobot's `get_codec_options(as_strings=True)` gives them, in that order."""

    @classmethod
    def of(cls, encoder: Any) -> Codec:
        """`encoder` (a Codec, or lerobot's encoder config) as a Codec."""
        if isinstance(encoder, Codec):
            return encoder
        options = encoder.get_codec_options(None, as_strings=True)
        return cls(encoder.vcodec, encoder.pix_fmt, tuple(options.items()))


def codec_for(ft: dict[str, Any]) -> Codec:
    """`encoder_for(ft)` as a `Codec`: resolved once per recorded settings, in a worker from the
    answers its main process gave it (`answers`). Depth is encoded with lerobot's config itself
    (its `quantize_depth`); its Codec names the codec."""
    info = {k: v for k, v in (ft.get("info") or {}).items() if k.startswith("video.")}
    return resolve("codec", lambda: Codec.of(encoder_for(ft)), info, depth.is_depth(ft))


# lerobot's answers to questions about encoders, by question (`resolve`); see the module docstring.
_ANSWERS: dict[str, Any] = {}


def resolve(question: str, compute: Callable[[], Any], *about: Any) -> Any:
    """The answer to `question` about `about` (JSON data): `compute()` the first time it is asked in
    this process unless the main process's answers (`take_answers`) hold it."""
    key = dumps([question, *about])
    if key not in _ANSWERS:
        _ANSWERS[key] = compute()
    return _ANSWERS[key]


def answers() -> dict[str, Any]:
    """The answers this process resolved (`resolve`), to hand to its workers."""
    return dict(_ANSWERS)


def take_answers(given: dict[str, Any]) -> None:
    """Answers resolved by the main process (`answers`), used before computing any here."""
    _ANSWERS.update(given)


class EncodedVideo:
    """One camera's frames of one output episode, encoded into a file of their own by a pipeline
    worker with the encoder the writer would use (`encoder_for`); the writer appends the file to the
    dataset's video as lerobot's writer appends its own encodes."""

    def __init__(self, path: str | Path, shape: tuple[int, ...] | list[int], dtype: str) -> None:
        self.path = Path(path)
        """The episode's video file (in the run's work folder)."""
        self.shape = tuple(int(d) for d in shape)
        """(frames, height, width, channels) of the frames it holds, as decoded."""
        self.dtype = np.dtype(dtype)
        """Their dtype, as decoded (uint8 RGB, float32 depth in metres)."""

    @property
    def ndim(self) -> int:
        """4."""
        return len(self.shape)

    def __len__(self) -> int:
        return self.shape[0]

    def state(self) -> dict[str, Any]:
        """What `data_tree` stores of it (a run's parts hold the file's name, not the pixels)."""
        return {"path": str(self.path), "shape": list(self.shape), "dtype": self.dtype.name}


def encode_episode_video(frames: np.ndarray, ft: dict[str, Any], fps: int, path: Path) -> EncodedVideo:
    """`frames` of video feature `ft` (RGB uint8, or depth float32 metres) encoded into `path` with
    the writer's encoder for it, written under another name and renamed (a killed worker leaves no
    partial file under `path`)."""
    frames = np.asarray(frames)
    stored = depth.to_stored(frames, depth.depth_unit(ft)) if depth.is_depth(ft) else frames
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}-{os.getpid()}{path.suffix}")  # PyAV picks the muxer by suffix
    try:
        encode_frames(stored, tmp, fps, encoder_for(ft) if depth.is_depth(ft) else codec_for(ft))
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return EncodedVideo(path, frames.shape, frames.dtype.name)


def transcode_episode(
    source: Path, start: float, timestamps: np.ndarray, ft: dict[str, Any], fps: int, path: Path
) -> EncodedVideo:
    """The RGB frames at `start + timestamps` of the video `source`, which pass a pipeline unchanged
    but are not copied (the destination asks for other encoder settings, or the streams of a merge
    differ), encoded into `path` as `encode_episode_video` encodes: decoded in the decoder's own
    pixel format and handed to the encoder in it, without a round trip through RGB (which alone
    costs ~45 dB of PSNR), each frame decoded once."""
    import av

    pictures = decoded_pictures(source, start, timestamps, str(source))
    for i, picture in enumerate(pictures):  # the output's clock; the encoder chooses the keyframes
        picture.pts, picture.time_base = i, Fraction(1, fps)
        picture.pict_type = av.video.frame.PictureType.NONE
    size = (pictures[0].height, pictures[0].width)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}-{os.getpid()}{path.suffix}")
    try:
        encode_pictures(pictures, len(pictures), size, tmp, fps, codec_for(ft))
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return EncodedVideo(path, (len(pictures), *size, 3), "uint8")
