"""Camera features stored as lerobot videos: one sequential PyAV decode per episode, and encoding
through lerobot's own encoder and file layout.

Decoding: lerobot's loader decodes frame by frame (a seek per frame); a pipeline needs whole
episodes, so the reader seeks once to the episode's start in the (concatenated) video file and
decodes forward, matching frames to the episode's timestamps with lerobot's tolerance. PyAV is the
backend that works here (torchcodec cannot load its FFmpeg libraries on these machines).

Encoding: `encode_frames` is lerobot's `encode_video_frames` (libsvtav1, yuv420p, g=2, crf=30)
fed from memory instead of from PNG files; `LeRobotDataset._save_episode_video` then appends the
episode to the current video file (starting a new one at `video_files_size_in_mb`), fills the
feature's `info` from the first episode and returns the `videos/KEY/*` episode metadata, exactly
as `save_episode` does.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from shiftkit.pipelines.errors import DatasetError

TOLERANCE_S = 1e-4  # lerobot's default tolerance between a frame's timestamp and the query


def decode_episode(path: Path, start: float, timestamps: np.ndarray, where: str) -> np.ndarray:
    """The frames at `start + timestamps` (seconds) of the video at `path`, (T, H, W, 3) uint8 RGB."""
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
                    frames[j] = frame.to_ndarray(format="rgb24")
    except (av.error.FFmpegError, OSError) as exc:
        raise DatasetError(f"{where}: cannot decode {path} ({type(exc).__name__}: {exc})") from None
    missing = [i for i, f in enumerate(frames) if f is None]
    if missing:
        raise DatasetError(
            f"{where}: {path.name} has no frame at {queries[missing[0]]:.4f} s "
            f"({len(missing)} of {len(queries)} frames missing; tolerance {TOLERANCE_S} s)"
        )
    return np.stack(frames)


def save_episode_videos(dataset: Any, episode_index: int, videos: dict[str, np.ndarray]) -> dict[str, Any]:
    """Encode one episode's video features into `dataset` (a `LeRobotDataset` being written) with
    lerobot's own encoder settings and file handling; returns the `videos/KEY/...` metadata."""
    import tempfile

    metadata: dict[str, Any] = {}
    for key, frames in videos.items():
        # lerobot's layout: a temporary folder in the dataset root, removed by _save_episode_video.
        path = Path(tempfile.mkdtemp(dir=dataset.root)) / f"{key}_{episode_index:03d}.mp4"
        encode_frames(frames, path, dataset.fps, dataset.vcodec, dataset._encoder_threads)
        metadata.update(dataset._save_episode_video(key, episode_index, temp_path=path))
    return metadata


def encode_frames(
    frames: np.ndarray, path: Path, fps: int, vcodec: str = "libsvtav1", encoder_threads: int | None = None
) -> None:
    """lerobot's `encode_video_frames` (same codec, options, pixel format and muxing) fed from
    memory: it reads PNG files a recorder wrote, which a pipeline would have to write first."""
    import logging

    import av
    from lerobot.datasets.video_utils import _get_codec_options, resolve_vcodec

    vcodec = resolve_vcodec(vcodec)
    options = _get_codec_options(vcodec, 2, 30, None)  # encode_video_frames' defaults: g=2, crf=30
    if encoder_threads is not None:
        if vcodec == "libsvtav1":
            options["svtav1-params"] = f"lp={encoder_threads}"
        else:
            options["threads"] = str(encoder_threads)
    logging.getLogger("libav").setLevel(logging.WARNING)
    try:
        with av.open(str(path), "w") as output:
            stream = output.add_stream(vcodec, fps, options=options)
            stream.pix_fmt = "yuv420p"
            stream.height, stream.width = frames.shape[1:3]
            for frame in frames:
                packet = stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24"))
                if packet:
                    output.mux(packet)
            packet = stream.encode()
            if packet:
                output.mux(packet)
    finally:
        av.logging.restore_default_callback()
