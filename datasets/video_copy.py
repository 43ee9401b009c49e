"""Video frames that pass a pipeline unchanged are copied, not decoded and encoded again.

A pipeline whose stages keep a camera's frames one for one (filter, rename, drop, map_tasks,
labels: `Plan.video_copies`) does not need that camera's pixels. The reader then hands the stages a
`VideoRef` instead of decoded frames: where the episode's frames lie in the source's video file
(`from_timestamp` / `to_timestamp`), its frame times and the statistics lerobot recorded for it.
It has the frames' shape and dtype, so schema checks pass; a stage that reads the pixels anyway
gets them decoded (`np.asarray`). The writer copies the episode's encoded packets (a remux: no
decode, no encode) into lerobot's video files (`VideoFileCopier`): several episodes per file, each
at the `from_timestamp` lerobot's writer would give it, a new file when the current one would pass
`video_files_size_in_mb`, the source's codec and settings (its stream is copied) and the source's
`video.*` info. What lerobot's `merge_datasets` does with whole files (`aggregate_videos`,
`concatenate_video_files`: a concat-demuxer remux), done per episode, so that an episode a stage
drops is never read.

A stage that keeps one contiguous run of an episode's frames (`trim`) hands on a reference to
that run (`VideoRef.select_frames`). Where the run starts between keyframes, the copier cuts
smartly: it decodes from the keyframe before, encodes the frames up to the next keyframe with the
source's recorded settings (`video.encoder_for`), from the decoder's own pixel format, and copies
the packets from that keyframe on: one or a few frames encoded per episode instead of all. This
needs a stream whose keyframes carry their own sequence header and whose packets come in
presentation order (AV1, as lerobot writes it: `cuttable`), so that the encoded frames need no
parameters of the source's stream and no copied frame refers to one left out; other streams are
encoded whole. A stage that keeps every k-th frame (`subsample`, or a downsampling `resample`)
hands on a reference to those frames alike: a kept keyframe is copied, shown one output frame after the one before (retimed to
the output's fps); a kept frame that refers to one left out is encoded, each run of them from the
keyframe before it.

Copying needs every episode of a camera to come from streams that concatenate: same codec, size,
pixel format, time base and codec parameters (`stream_signature`), each episode starting on a
keyframe (`copy_signature`); a merge of differently encoded sources encodes instead. Depth videos
(lerobot's 12-bit HEVC) are copied alike, their quantiser parameters with the source's `info`.
"""

from __future__ import annotations

import functools
import shutil
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from shiftkit.datasets.depth import is_depth
from shiftkit.datasets.errors import DatasetError
from shiftkit.datasets.video import TOLERANCE_S, codec_for, decode_pictures, scheduling_kept


class VideoRef:
    """One camera's frames of one source episode, still encoded (see the module docstring)."""

    def __init__(
        self,
        path: str | Path,
        start: float,
        stop: float,
        timestamps: np.ndarray,
        feature: dict[str, Any],
        stats: dict[str, np.ndarray] | None,
    ) -> None:
        self.path = Path(path)
        """The source video file that holds the episode."""
        self.start = float(start)
        """The episode's `from_timestamp` in that file (seconds)."""
        self.stop = float(stop)
        """Its `to_timestamp`."""
        self.timestamps = np.asarray(timestamps, dtype=np.float64)
        """Its frames' times from the episode's start."""
        self.feature = feature
        """The source's feature entry (shape, `video.*` info)."""
        self.stats = stats
        """lerobot's statistics of these frames, as the source recorded them (None: not recorded)."""

    @property
    def shape(self) -> tuple[int, ...]:
        """(frames, height, width, channels), as the decoded frames'."""
        return (len(self.timestamps), *(int(d) for d in self.feature["shape"]))

    @property
    def dtype(self) -> np.dtype:
        """uint8 for RGB frames, float32 (metres) for depth, as the decoded frames'."""
        return np.dtype(np.float32 if is_depth(self.feature) else np.uint8)

    @property
    def ndim(self) -> int:
        """4."""
        return len(self.shape)

    def __len__(self) -> int:
        return len(self.timestamps)

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        from shiftkit.datasets.images import decode_video

        frames = decode_video(self.path, self.start, self.timestamps, str(self.path), self.feature)
        return frames if dtype is None else frames.astype(dtype)

    def __getitem__(self, index: Any) -> np.ndarray:
        picked = np.asarray(index) if isinstance(index, (list, np.ndarray)) else None
        if picked is not None and picked.ndim == 1 and picked.dtype.kind == "i" and np.all(np.diff(picked) > 0):
            from shiftkit.datasets.images import decode_video

            # frames in increasing order (the statistics' samples): those alone are decoded
            return decode_video(self.path, self.start, self.timestamps[picked], str(self.path), self.feature)
        return np.asarray(self)[index]

    def select_frames(self, index: np.ndarray | slice | list[int]) -> VideoRef | np.ndarray:
        """The frames at `index`: still a reference when each is shown once, in order (a run that
        `trim` keeps, every k-th frame that `subsample` keeps; `Episode.select`), else decoded."""
        picked = np.arange(len(self))[index]
        if picked.ndim != 1 or not len(picked) or np.any(np.diff(picked) < 1):
            return np.asarray(self)[index]
        a, b = int(picked[0]), int(picked[-1]) + 1
        if len(picked) == len(self):
            return self
        ts = self.timestamps
        stop = self.start + ts[b] if b < len(self) else self.stop
        # the frames' statistics are not the episode's: computed from them (`stats.episode_stats`)
        return VideoRef(self.path, self.start + ts[a], stop, ts[picked] - ts[a], self.feature, None)

    def __iter__(self):
        return iter(np.asarray(self))

    def state(self) -> dict[str, Any]:
        """What `data_tree` stores of it (a run's parts hold the reference, not the pixels)."""
        return {
            "path": str(self.path),
            "start": self.start,
            "stop": self.stop,
            "timestamps": self.timestamps,
            "feature": self.feature,
            "stats": self.stats,
        }


def cuttable(files: list[Path]) -> bool:
    """Whether episodes of these video files can be cut between keyframes (module docstring): AV1,
    every packet in presentation order."""
    return all(facts.codec == "av1" and facts.in_order for facts in (_file_facts(f)[1] for f in files))


def copy_signature(files: dict[Path, list[float]]) -> tuple | None:
    """The stream signature (`stream_signature`) shared by a camera's video `files`, each given with
    the `from_timestamp`s of its episodes, if every episode starts on a keyframe (a copy starts
    there); None when the files' streams differ or an episode starts between keyframes (lerobot's
    `delete_episodes` re-encodes kept segments as one stream, so with its `g=2` an episode after one
    of odd length does)."""
    signatures = set()
    for path, starts in files.items():
        signature, facts = _file_facts(path)
        if any(round(start / facts.time_base) not in facts.keyframes for start in starts):
            return None
        signatures.add(signature)
    return signatures.pop() if len(signatures) == 1 else None


@dataclass(frozen=True)
class FileFacts:
    """What the copier needs of a source video file, read by one demux (no decoding)."""

    time_base: Fraction
    keyframes: frozenset[int]
    """The pts of its keyframes."""
    pts: np.ndarray
    """Every packet's pts, ascending."""
    sizes: np.ndarray
    """Each packet's bytes (in `pts` order)."""
    codec: str
    """The codec's canonical name (`av1`, `h264`, `hevc`)."""
    in_order: bool
    """Whether the packets come in presentation order (no frame refers to a later one)."""

    @property
    def packets(self) -> int:
        """How many packets (frames) the file holds."""
        return len(self.pts)

    def shown(self, start: float, timestamps: np.ndarray, where: Path) -> np.ndarray:
        """Index (in `pts` order) of the packet shown at each of `start + timestamps` seconds: the
        nearest, within lerobot's tolerance, as the decoder matches frames (`video.decode_episode`)."""
        at = (start + np.asarray(timestamps, dtype=np.float64)) / float(self.time_base)
        after = np.searchsorted(self.pts, at)
        below, above = (np.clip(k, 0, len(self.pts) - 1) for k in (after - 1, after))
        nearest = np.where(np.abs(self.pts[below] - at) <= np.abs(self.pts[above] - at), below, above)
        off = np.abs(self.pts[nearest] - at) * float(self.time_base)
        if len(off) and off.max() > TOLERANCE_S:
            raise DatasetError(f"{where}: no frame at {start + timestamps[int(off.argmax())]:.4f} s")
        return nearest

    def bytes_shown(self, start: float, timestamps: np.ndarray, where: Path) -> int:
        """Bytes of the packets shown at `start + timestamps` seconds."""
        return int(self.sizes[self.shown(start, timestamps, where)].sum())


def _file_facts(path: Path) -> tuple[tuple, FileFacts]:
    """(stream signature, `FileFacts`) of a video file, read once per version of it."""
    st = Path(path).stat()
    return _facts(str(path), st.st_size, st.st_mtime_ns)


@functools.lru_cache(maxsize=256)
def _facts(path: str, size: int, mtime_ns: int) -> tuple[tuple, FileFacts]:
    import av

    signature = stream_signature(Path(path))
    try:
        with av.open(path) as container:
            stream = container.streams.video[0]
            rows = [(p.pts, p.size, p.is_keyframe) for p in container.demux(stream) if p.pts is not None]
            time_base, codec = stream.time_base, stream.codec_context.codec.canonical_name
    except (av.error.FFmpegError, OSError) as exc:
        raise DatasetError(f"cannot read the video stream of {path} ({type(exc).__name__}: {exc})") from None
    in_order = all(a[0] < b[0] for a, b in zip(rows, rows[1:], strict=False))
    rows.sort()
    facts = FileFacts(
        time_base,
        frozenset(pts for pts, _, key in rows if key),
        np.array([pts for pts, _, _ in rows], dtype=np.int64),
        np.array([size for _, size, _ in rows], dtype=np.int64),
        codec,
        in_order,
    )
    return signature, facts


def stream_signature(path: Path) -> tuple:
    """What must be equal for two video files' packets to share one file: codec, size, pixel format,
    time base, frame rate and the codec's parameters (extradata)."""
    import av

    try:
        with av.open(str(path)) as container:
            s = container.streams.video[0]
            ctx = s.codec_context
            return (
                ctx.name,
                ctx.width,
                ctx.height,
                ctx.pix_fmt,
                s.time_base,
                s.average_rate,
                bytes(ctx.extradata or b""),
            )
    except (av.error.FFmpegError, OSError, IndexError) as exc:
        raise DatasetError(f"cannot read the video stream of {path} ({type(exc).__name__}: {exc})") from None


def shows_frames_at(signature: tuple, fps: int) -> bool:
    """Whether a stream of this `stream_signature` can show its frames `1 / fps` apart: the frame
    period a whole number of its time base's ticks (lerobot's 30 fps AV1, 1/15360: any fps that
    divides 15360), what packets copied at another rate (`subsample`, `resample`) are retimed to."""
    return (Fraction(1, fps) / signature[4]).denominator == 1


class VideoFileCopier:
    """Appends episodes' encoded packets (`VideoRef`s) to one camera's video files in lerobot's layout,
    as lerobot's writer appends its encoded episodes (module docstring). A file's episodes are
    written when it is complete (the next would pass the size limit, or `close`): a file that holds
    exactly one source file's episodes, all of them in order (a pass-through, rename, drop or merge),
    is that file copied; any other is remuxed packet by packet. A whole source file is never
    concatenated with what follows (lerobot's `merge_datasets(concatenate_videos=False)` layout):
    the next source's episodes start a new file, so a merge copies its sources' files instead of
    remuxing them into one. Where the output's `fps` is not the source's (`subsample`), the kept frames are shown one output frame apart."""

    def __init__(self, root: Path, key: str, video_path: str, chunks_size: int, max_mb: float, fps: int) -> None:
        self.root, self.key, self.video_path = root, key, video_path
        self.chunks_size, self.max_bytes = chunks_size, max_mb * 1024 * 1024
        self.fps = fps
        self.chunk_file: tuple[int, int] | None = None
        self._pending: list[VideoRef] = []  # the current file's episodes, written by `_flush`
        self._bytes = 0
        self._duration = 0.0  # the current file's to_timestamp so far
        self._source: tuple[str, Any] | None = None  # the open source container (path, container)
        self.signature: tuple | None = None
        self.encoded_frames = 0
        """Frames encoded at cuts (the rest are the source's packets)."""

    def _retimed(self, ref: VideoRef) -> bool:
        """Whether `ref`'s frames are shown at the output's fps, not at their source times."""
        return int((ref.feature.get("info") or {}).get("video.fps", self.fps)) != self.fps

    def _duration_of(self, ref: VideoRef) -> float:
        """How long the episode lasts in the output (lerobot: its frames at the fps)."""
        return len(ref) / self.fps if self._retimed(ref) else ref.stop - ref.start

    def add(self, ref: VideoRef) -> dict[str, Any]:
        """Take one episode; returns its `videos/KEY/...` episode metadata."""
        from lerobot.datasets.utils import update_chunk_file_indices

        signature, facts = _file_facts(ref.path)
        if self.signature is not None and signature != self.signature:
            raise DatasetError(f"{ref.path}: its {self.key} stream is encoded otherwise than the episodes before it")
        self.signature = signature
        size = facts.bytes_shown(ref.start, ref.timestamps, ref.path)
        # lerobot's rollover rule (the size limit), and a new file after a whole source file
        after_whole = bool(self._pending) and ref.path != self._pending[-1].path and self._whole(self._pending)
        if self.chunk_file is None or after_whole or self._bytes + size >= self.max_bytes:
            self._flush()
            self.chunk_file = (
                (0, 0) if self.chunk_file is None else update_chunk_file_indices(*self.chunk_file, self.chunks_size)
            )
            self._bytes, self._duration = 0, 0.0
        self._pending.append(ref)
        start = self._duration
        self._duration = start + self._duration_of(ref)
        self._bytes += size
        return {
            f"videos/{self.key}/chunk_index": self.chunk_file[0],
            f"videos/{self.key}/file_index": self.chunk_file[1],
            f"videos/{self.key}/from_timestamp": start,
            f"videos/{self.key}/to_timestamp": self._duration,
        }

    def _flush(self) -> None:
        """Write the current file from its pending episodes."""
        refs, self._pending = self._pending, []
        if not refs:
            return
        path = self.root / self.video_path.format(
            video_key=self.key, chunk_index=self.chunk_file[0], file_index=self.chunk_file[1]
        )
        path.parent.mkdir(parents=True, exist_ok=True)
        if self._whole(refs):
            shutil.copyfile(refs[0].path, path)
            return
        self._remux(refs, path)

    def _whole(self, refs: list[VideoRef]) -> bool:
        """Whether `refs` are every episode of one source file, in order, shown at their own times."""
        source = refs[0].path
        return (
            all(r.path == source for r in refs)
            and refs[0].start == 0.0
            and all(a.stop == b.start for a, b in zip(refs, refs[1:], strict=False))
            and sum(len(r) for r in refs) == _file_facts(source)[1].packets
            and not any(self._retimed(r) for r in refs)  # one-frame episodes through `subsample`
        )

    def _remux(self, refs: list[VideoRef], path: Path) -> None:
        import av

        # lerobot's concatenate_video_files: faststart, the stream copied from its template
        with av.open(str(path), mode="w", options={"movflags": "faststart"}) as out:
            stream, duration = None, 0.0
            for ref in refs:
                packets, template = self._packets(ref)
                if stream is None:
                    stream = out.add_stream_from_template(template=template, opaque=True)
                    stream.time_base = template.time_base
                shift = round(duration / template.time_base)
                for packet in packets:
                    packet.pts = None if packet.pts is None else packet.pts + shift
                    packet.dts = None if packet.dts is None else packet.dts + shift
                    packet.stream = stream
                    out.mux(packet)
                duration += self._duration_of(ref)

    def _packets(self, ref: VideoRef) -> tuple[list[Any], Any]:
        """The episode's packets, timed from 0, and the source stream. A packet shown in full (all of
        a source episode's, from a keyframe on) is copied, demuxed without decoding; one that refers
        to a frame left out (a cut between keyframes, every k-th frame) is encoded anew."""
        import av

        if self._source is None or self._source[0] != str(ref.path):
            self.close_source()
            self._source = (str(ref.path), av.open(str(ref.path)))
        container = self._source[1]
        stream = container.streams.video[0]
        tb = stream.time_base
        lo, hi = round(ref.start / tb), round(ref.stop / tb)
        container.seek(lo, stream=stream, backward=True)
        lead, packets = [], []  # from the keyframe at or before `lo`; those shown in [lo, hi)
        for packet in container.demux(stream):
            if packet.dts is None:  # the demuxer's flush packet
                continue
            if packet.dts >= hi:
                break
            if packet.pts is not None and packet.pts < lo:
                lead.append(packet)
            elif packet.pts is not None and lo <= packet.pts < hi:
                packets.append(packet)
        shown = list(range(len(packets)))
        if len(packets) != len(ref):  # some frames left out: in presentation order (`cuttable`)
            facts = _file_facts(ref.path)[1]
            first = int(np.searchsorted(facts.pts, lo))  # `packets` are the file's from pts `lo` on
            shown = [int(k) - first for k in facts.shown(ref.start, ref.timestamps, ref.path)]
        copied = [packets[shown[0]].is_keyframe]  # a keyframe, or the frame after a copied one
        for before, i in zip(shown, shown[1:], strict=False):
            copied.append(packets[i].is_keyframe or (copied[-1] and i == before + 1))
        if not all(copied) and not cuttable([ref.path]):
            raise DatasetError(f"{ref.path}: the episode at {ref.start:.4f} s does not start on a keyframe")
        left_out = [packets[i] for i, copy in zip(shown, copied, strict=True) if not copy]
        encoded = iter(self._encoded(ref, stream, lead + packets, left_out, copied))
        retimed, period = self._retimed(ref), Fraction(1, self.fps) / tb
        if retimed and period.denominator != 1:
            raise DatasetError(f"{ref.path}: its time base {tb} cannot show frames at {self.fps} fps")
        out = []
        for j, (i, copy) in enumerate(zip(shown, copied, strict=True)):
            packet = packets[i] if copy else next(encoded)
            at = j * int(period) if retimed else packets[i].pts - lo
            delay = packets[i].pts - packets[i].dts if copy and not retimed else 0
            packet.pts, packet.dts = at, at - delay
            if retimed:
                packet.duration = int(period)
            out.append(packet)
        return out, stream

    def _encoded(
        self, ref: VideoRef, stream: Any, packets: list[Any], frames: list[Any], copied: list[bool]
    ) -> list[Any]:
        """The packets `frames` (of `packets`, which start on a keyframe) show, encoded anew: each run
        of consecutive ones (`copied` false) a stream of its own that starts on a keyframe, decoded
        from the keyframe before it (module docstring)."""
        if not frames:
            return []
        pictures = decode_pictures(stream.codec_context, packets, {p.pts for p in frames})
        todo, runs, run = iter(frames), [], []
        for copy in [*copied, True]:
            if not copy:
                run.append(pictures[next(todo).pts])
            elif run:
                runs.append(run)
                run = []
        out = [packet for run in runs for packet in _encode(run, stream, ref)]
        self.encoded_frames += len(out)
        return out

    def close_source(self) -> None:
        """Close the open source file."""
        if self._source is not None:
            self._source[1].close()
            self._source = None

    def close(self) -> None:
        """Write the last file and close the source."""
        self._flush()
        self.close_source()


def _encode(frames: list[Any], stream: Any, ref: VideoRef) -> list[Any]:
    """`frames` (decoded pictures) encoded with the source's recorded settings into a stream of their
    own that starts on a keyframe, in the decoder's pixel format and the source's clock."""
    import av

    source = stream.codec_context
    codec = codec_for(ref.feature)
    ctx = av.CodecContext.create(codec.vcodec, "w")
    ctx.width, ctx.height, ctx.pix_fmt = source.width, source.height, source.pix_fmt
    ctx.time_base, ctx.framerate = stream.time_base, stream.average_rate
    ctx.options = dict(codec.options)
    out = []
    with scheduling_kept():
        for frame in frames:
            frame.pict_type = av.video.frame.PictureType.NONE  # the encoder decides (a keyframe first)
            out += ctx.encode(frame)
        out += ctx.encode(None)
    if len(out) != len(frames) or not out[0].is_keyframe:
        raise DatasetError(f"{ref.path}: encoding {len(frames)} frames at {ref.start:.4f} s gave {len(out)} packets")
    return out
