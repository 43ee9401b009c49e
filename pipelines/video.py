"""Camera features stored as lerobot videos: one sequential PyAV decode per episode, and encoding
through lerobot's own encoder and file layout.

Decoding: lerobot's loader decodes frame by frame (a seek per frame); a pipeline needs whole
episodes, so the reader seeks once to the episode's start in the (concatenated) video file and
decodes forward, matching frames to the episode's timestamps with lerobot's tolerance. PyAV is the
backend that works here (torchcodec cannot load its FFmpeg libraries on these machines).

Encoding: the frames go to the PNG files lerobot's recorder writes, then
`LeRobotDataset._save_episode_video` encodes them with lerobot's settings (libsvtav1, yuv420p,
g=2, crf=30), appends them to the current video file (starting a new one at
`video_files_size_in_mb`), fills the feature's `info` from the first episode and returns the
`videos/KEY/*` episode metadata, exactly as `save_episode` does.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from shiftkit.pipelines.errors import DatasetError

TOLERANCE_S = 1e-4  # lerobot's default tolerance between a frame's timestamp and the query
_PNG_FAST = 1  # the PNGs are read once by the encoder and deleted: favour speed (lerobot's recorder uses 1 too)


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
    lerobot's own encoder; returns the `videos/KEY/...` metadata of the episode."""
    import cv2
    from lerobot.datasets.utils import DEFAULT_IMAGE_PATH

    metadata: dict[str, Any] = {}
    for key, frames in videos.items():
        folder = None
        for t, frame in enumerate(frames):
            path = Path(dataset.root) / DEFAULT_IMAGE_PATH.format(
                image_key=key, episode_index=episode_index, frame_index=t
            )
            if folder is None:
                folder = path.parent
                folder.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(path), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, _PNG_FAST])
        metadata.update(dataset._save_episode_video(key, episode_index))
    return metadata
