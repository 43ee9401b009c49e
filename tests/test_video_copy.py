"""Video frames that pass a pipeline unchanged are copied packet for packet (datasets/video_copy.py),
checked against the truth: datasets written by lerobot 0.6.1's own writer (two AV1 cameras), the
output's frames as lerobot's loader decodes them equal to the source's, its packets (PyAV demux) the
source's bytes, the output loading in lerobot and passing `shiftkit validate --deep`, and nothing
decoded on the way. A stage that changes pixels still encodes."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from shiftkit.app.cli import main
from shiftkit.datasets.sources import SourceConfig
from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, StageSpec
from shiftkit.pipelines.runner import run_pipeline
from tests.helpers import lerobot_train_two_steps, tree_hashes
from tests.lerobot_recordings import Recording, recording

CAMERAS = ("observation.images.front", "observation.images.wrist")
SMALL = Recording(video=True, cameras=("front", "wrist"), depth=(), size=(32, 48), lengths=(8, 8, 8), language=False)
# the same settings, other pictures: a second dataset to merge with the first
OTHER = Recording(
    video=True, cameras=("front", "wrist"), depth=(), size=(32, 48), lengths=(8, 6), language=False, seed=1
)
LARGE = Recording(video=True, cameras=("front", "wrist"), depth=(), size=(480, 640), lengths=(4, 4, 4), language=False)
FILTER_RENAME = [
    StageSpec("filter", {"indices": [0, 2]}),
    StageSpec("rename", {"mapping": {"observation.mode": "observation.phase"}}),
]


def _run(sources: list[Path], out: Path, stages: list[StageSpec], workers: int = 1, **destination) -> Path:
    """Run `stages` on `sources` into `out`; `destination`: more `[destination]` fields (encoder settings)."""
    config = PipelineConfig(
        sources=[SourceConfig(path=str(s)) for s in sources],
        destination=DestinationConfig(root=str(out), **destination),
        stages=stages,
    )
    return run_pipeline(config, workers=workers, progress=False)


def _packets(root: Path, key: str) -> list[bytes]:
    """Every video packet of `key` in `root`, file after file (PyAV demux, no decoding)."""
    import av

    out = []
    for path in sorted((root / "videos" / key).glob("chunk-*/file-*.mp4")):
        with av.open(str(path)) as container:
            out += [bytes(p) for p in container.demux(container.streams.video[0]) if p.dts is not None]
    return out


def _episode_packets(root: Path, key: str, of: Callable[[Any], Any] = bytes) -> list[list[Any]]:
    """Per episode, `of` each of its packets of `key` (by the episodes' `from_timestamp` /
    `to_timestamp`): their bytes, or e.g. whether they are keyframes."""
    import av
    import pandas as pd

    episodes = pd.concat(pd.read_parquet(p) for p in sorted((root / "meta/episodes").glob("*/*.parquet")))
    out = []
    for _, row in episodes.sort_values("episode_index").iterrows():
        chunk, file = int(row[f"videos/{key}/chunk_index"]), int(row[f"videos/{key}/file_index"])
        with av.open(str(root / f"videos/{key}/chunk-{chunk:03d}/file-{file:03d}.mp4")) as container:
            stream = container.streams.video[0]
            lo, hi = (round(row[f"videos/{key}/{b}_timestamp"] / stream.time_base) for b in ("from", "to"))
            out.append([of(p) for p in container.demux(stream) if p.pts is not None and lo <= p.pts < hi])
    return out


def _lerobot_frames(root: Path, key: str) -> list[np.ndarray]:
    """Every frame of `key` as lerobot 0.6.1's `LeRobotDataset` decodes it, in dataset order."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    dataset = LeRobotDataset("test/loaded", root=root, video_backend="pyav")
    return [dataset[i][key].numpy() for i in range(len(dataset))]


def _frames_of(frames: list[np.ndarray], lengths: tuple[int, ...], episodes: list[int]) -> list[np.ndarray]:
    starts = np.cumsum((0, *lengths))
    return [frames[t] for e in episodes for t in range(starts[e], starts[e + 1])]


def _validate_deep(root: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`shiftkit validate --deep` (which decodes: `no_decoding` lifted first)."""
    monkeypatch.undo()
    assert main(["validate", "--deep", str(root)]) == 0


@pytest.fixture
def no_decoding(monkeypatch):
    """Fail any decode of a video frame by shiftkit's reader (the pipeline runs in this process)."""

    def refuse(*args, **kwargs):
        raise AssertionError("a video was decoded")

    monkeypatch.setattr("shiftkit.datasets.images.decode_episode", refuse)


@pytest.mark.parametrize("rec", [SMALL, LARGE], ids=["32x48", "480x640"])
def test_filter_and_rename_copy_the_source_packets(rec, tmp_path, monkeypatch, no_decoding):
    """`filter` + `rename` of a non-camera feature on a two-camera AV1 dataset: no frame decoded (not
    even of the dropped episode), the kept episodes' packets are the source's bytes, lerobot's loader
    decodes the source's frames from the output, the episodes share one file per camera, `info.json`
    keeps the source's `video.*` and the provenance says each camera was copied."""
    source = recording(rec)
    out = _run([source], tmp_path / "out", FILTER_RENAME)
    provenance = json.loads((out / "meta/shiftkit_provenance.json").read_text())
    assert provenance["video"] == dict.fromkeys(CAMERAS, "copied")
    src_info, out_info = (json.loads((r / "meta/info.json").read_text())["features"] for r in (source, out))
    assert "observation.phase" in out_info and "observation.mode" not in out_info
    for key in CAMERAS:
        assert out_info[key] == src_info[key]  # codec, pix_fmt, g, crf: the source's stream
        kept = _episode_packets(source, key)
        assert _episode_packets(out, key) == [kept[0], kept[2]]
        assert _packets(out, key) == kept[0] + kept[2]  # one file, nothing else in it
        assert sorted(p.name for p in (out / "videos" / key).rglob("*.mp4")) == ["file-000.mp4"]
    for key in CAMERAS:
        got, src = _lerobot_frames(out, key), _lerobot_frames(source, key)
        expected = _frames_of(src, rec.lengths, [0, 2])
        assert len(got) == len(expected)
        for a, b in zip(got, expected, strict=True):
            np.testing.assert_array_equal(a, b)
    stats = json.loads((out / "meta/stats.json").read_text())
    assert np.asarray(stats[CAMERAS[0]]["mean"]).shape == (3, 1, 1)
    _validate_deep(out, monkeypatch)


def test_merge_copies_both_sources(tmp_path, monkeypatch, no_decoding):
    """A merge of two lerobot-written datasets encoded alike copies every packet of both, in order,
    each source's video file whole (lerobot's `concatenate_videos=False` layout): the output's files
    are the sources' files, byte for byte, and the second's episodes start at 0 s in theirs."""
    import pandas as pd

    a, b = recording(SMALL), recording(OTHER)
    out = _run([a, b], tmp_path / "merged", [])
    assert json.loads((out / "meta/shiftkit_provenance.json").read_text())["video"] == dict.fromkeys(CAMERAS, "copied")
    episodes = pd.read_parquet(out / "meta/episodes/chunk-000/file-000.parquet")
    for key in CAMERAS:
        files = sorted((out / "videos" / key).rglob("*.mp4"))
        sources = [*(a / "videos" / key).rglob("*.mp4"), *(b / "videos" / key).rglob("*.mp4")]
        assert [f.read_bytes() for f in files] == [f.read_bytes() for f in sources]
        assert episodes[f"videos/{key}/file_index"].tolist() == [0, 0, 0, 1, 1]
        assert episodes[f"videos/{key}/from_timestamp"].tolist()[3] == 0.0
        assert _packets(out, key) == _packets(a, key) + _packets(b, key)
        got = _lerobot_frames(out, key)
        expected = _lerobot_frames(a, key) + _lerobot_frames(b, key)
        for x, y in zip(got, expected, strict=True):
            np.testing.assert_array_equal(x, y)
        assert len(got) == len(expected)
    _validate_deep(out, monkeypatch)


def test_copied_episodes_roll_over_to_new_files(tmp_path, monkeypatch, no_decoding):
    """With lerobot's file size limit reached after each episode, every episode starts a new file
    (lerobot's rule: a file that would pass `video_files_size_in_mb` is not appended to), each from
    timestamp 0, and lerobot still loads the source's frames."""
    from shiftkit.datasets import writer

    class Tiny(writer.VideoFileCopier):
        def __init__(self, root, key, video_path, chunks_size, max_mb, fps):
            super().__init__(root, key, video_path, chunks_size, 1e-6, fps)

    monkeypatch.setattr(writer, "VideoFileCopier", Tiny)
    source = recording(SMALL)
    out = _run([source], tmp_path / "out", [StageSpec("filter", {"indices": [0, 1, 2]})])
    key = CAMERAS[0]
    assert sorted(p.name for p in (out / "videos" / key).rglob("*.mp4")) == [f"file-{i:03d}.mp4" for i in range(3)]
    assert _episode_packets(out, key) == _episode_packets(source, key)
    import pandas as pd

    episodes = pd.read_parquet(out / "meta/episodes/chunk-000/file-000.parquet")
    assert episodes[f"videos/{key}/from_timestamp"].tolist() == [0.0, 0.0, 0.0]
    for x, y in zip(_lerobot_frames(out, key), _lerobot_frames(source, key), strict=True):
        np.testing.assert_array_equal(x, y)


def test_dropping_a_camera_copies_the_other(tmp_path, no_decoding):
    """Dropping a camera needs no pixels: the other camera is copied, nothing is decoded."""
    source = recording(SMALL)
    out = _run([source], tmp_path / "out", [StageSpec("drop", {"features": [CAMERAS[1]]})])
    assert json.loads((out / "meta/shiftkit_provenance.json").read_text())["video"] == {CAMERAS[0]: "copied"}
    assert not (out / "videos" / CAMERAS[1]).exists()
    assert _packets(out, CAMERAS[0]) == _packets(source, CAMERAS[0])


def test_a_pixel_changing_stage_still_encodes(tmp_path, monkeypatch):
    """`resize` changes one camera's pixels: that camera is encoded anew (new size), the other copied."""
    source = recording(SMALL)
    out = _run([source], tmp_path / "out", [StageSpec("resize", {"width": 32, "height": 16, "features": [CAMERAS[0]]})])
    provenance = json.loads((out / "meta/shiftkit_provenance.json").read_text())
    assert provenance["video"] == {CAMERAS[0]: "encoded", CAMERAS[1]: "copied"}
    info = json.loads((out / "meta/info.json").read_text())["features"][CAMERAS[0]]["info"]
    assert (info["video.height"], info["video.width"]) == (16, 32)
    assert _packets(out, CAMERAS[1]) == _packets(source, CAMERAS[1])
    assert len(_lerobot_frames(out, CAMERAS[0])) == sum(SMALL.lengths)
    _validate_deep(out, monkeypatch)


def test_a_copy_starts_only_on_a_keyframe(tmp_path, monkeypatch):
    """lerobot encodes each episode on its own (a keyframe first), but a stream re-encoded as a whole
    (lerobot's `delete_episodes` does that with the kept episodes of a file) may have an episode start
    between keyframes (with `g=2`, after one of odd length, unless the encoder cuts at the scene
    change): no copy can start there. `copy_signature` says so, and such a camera is encoded."""
    from shiftkit.datasets import Dataset
    from shiftkit.datasets.video_copy import copy_signature

    source = recording(SMALL)
    path = source / "videos" / CAMERAS[0] / "chunk-000" / "file-000.mp4"
    fps = SMALL.fps
    assert copy_signature({path: [0.0, 8 / fps, 16 / fps]}) is not None  # lerobot's episode starts
    assert copy_signature({path: [0.0, 8 / fps, 17 / fps]}) is None  # frame 17: between keyframes (g=2)

    monkeypatch.setattr(Dataset, "video_copy_signature", lambda self, key: None if key == CAMERAS[0] else ("same",))
    out = _run([source], tmp_path / "out", FILTER_RENAME)
    provenance = json.loads((out / "meta/shiftkit_provenance.json").read_text())
    assert provenance["video"] == {CAMERAS[0]: "encoded", CAMERAS[1]: "copied"}
    got, src = _lerobot_frames(out, CAMERAS[0]), _frames_of(_lerobot_frames(source, CAMERAS[0]), SMALL.lengths, [0, 2])
    assert len(got) == len(src) == 16
    assert max(float(np.abs(a - b).mean()) for a, b in zip(got, src, strict=True)) < 0.05  # encoded again: lossy


TRIMMED = Recording(
    video=True, cameras=("front", "wrist"), depth=("front",), depth_unit="mm", size=(32, 48), lengths=(8, 9, 8),
    language=False,
)  # fmt: skip


@pytest.mark.parametrize(("head", "tail", "cut"), [(1, 2, 1), (2, 1, 0), (3, 0, 1)])
def test_trim_copies_from_a_keyframe_and_encodes_only_up_to_it(head, tail, cut, tmp_path, monkeypatch):
    """`trim` keeps one run of each episode's frames: an AV1 camera (lerobot's, `g=2`) is copied from
    the run's first keyframe on, and only the frames before it (`cut` per episode: none when the run
    starts on a keyframe) are encoded, from the decoder's pixels with the source's settings, into a
    stream that starts on a keyframe. Checked against the source: the copied packets are its bytes,
    lerobot's loader gives its frames exactly there and near ones at the cut; the HEVC depth (its
    packets out of presentation order) is encoded whole; statistics and `validate --deep` hold."""
    import os

    source = recording(TRIMMED)
    policy = os.sched_getscheduler(0)
    out = _run([source], tmp_path / "out", [StageSpec("trim", {"head": head, "tail": tail})])
    assert os.sched_getscheduler(0) == policy  # the cut's encoder left this thread as it was
    provenance = json.loads((out / "meta/shiftkit_provenance.json").read_text())
    depth = "observation.depth.front"
    assert provenance["video"] == {**dict.fromkeys(CAMERAS, "copied"), depth: "encoded"}
    runs = [(head, n - tail) for n in TRIMMED.lengths]
    if cut:
        assert provenance["video_encoded_at_cuts"] == dict.fromkeys(CAMERAS, cut * len(runs))
    else:
        assert "video_encoded_at_cuts" not in provenance
    for key in CAMERAS:
        src_info, out_info = (json.loads((r / "meta/info.json").read_text())["features"][key] for r in (source, out))
        assert out_info == src_info  # the source's stream settings
        src_packets, out_packets = _episode_packets(source, key), _episode_packets(out, key)
        for (a, b), got, src in zip(runs, out_packets, src_packets, strict=True):
            assert len(got) == b - a and got[cut:] == src[a + cut : b]
        src_frames, got = _lerobot_frames(source, key), _lerobot_frames(out, key)
        starts = np.cumsum((0, *TRIMMED.lengths))
        # per output frame: its source frame, and whether it was encoded (the first `cut` of its run)
        kept = [(int(starts[e]) + t, t - a < cut) for e, (a, b) in enumerate(runs) for t in range(a, b)]
        assert len(got) == len(kept)
        for frame, (t, encoded) in zip(got, kept, strict=True):
            if not encoded:
                np.testing.assert_array_equal(frame, src_frames[t])
        encoded = [(frame, t) for frame, (t, enc) in zip(got, kept, strict=True) if enc]
        if encoded:
            assert _psnr_of_encoded([f for f, _ in encoded], src_frames, [t for _, t in encoded]) > 20
    assert len(_lerobot_frames(out, depth)) == sum(b - a for a, b in runs)
    if (head, tail) == (1, 2):  # references and cuts through two workers' parts: the same bytes
        two = _run([source], tmp_path / "two", [StageSpec("trim", {"head": head, "tail": tail})], workers=2)
        assert _files(two) == _files(out)
    _validate_deep(out, monkeypatch)


@pytest.mark.parametrize(("every", "offset"), [(2, 0), (5, 1), (2, 1)])
def test_subsample_copies_the_kept_keyframes_and_encodes_the_others(every, offset, tmp_path, monkeypatch):
    """`subsample` keeps every k-th frame: on lerobot's AV1 (`g=2`), a kept keyframe is the source's
    packet, shown one output frame after the last; a kept frame that refers to one left out is
    encoded from the decoder's pixels, a stream of its own starting on a keyframe. Checked against
    the source (`_assert_selection_copied`)."""
    source = recording(TRIMMED)
    out = _run([source], tmp_path / "out", [StageSpec("subsample", {"every": every, "offset": offset})])
    kept = [list(range(offset, n, every)) for n in TRIMMED.lengths]
    encoded_frames = _assert_selection_copied(source, out, kept, TRIMMED.fps // every)
    assert any(encoded_frames.values()) == (offset % 2 == 1 or every % 2 == 1)  # g=2: even frames are keys
    if (every, offset) == (5, 1):  # copies and cuts through two workers' parts: the same bytes
        two = _run([source], tmp_path / "two", [StageSpec("subsample", {"every": every, "offset": offset})], workers=2)
        depth = "observation.depth.front"
        files, files_two = _files(out), _files(two)
        assert files.keys() == files_two.keys()
        assert {k: v for k, v in files.items() if depth not in k} == {
            k: v for k, v in files_two.items() if depth not in k
        }
        # the depth is not copied but encoded anew by lerobot's lossless HEVC encoder: the same codes
        for a, b in zip(_lerobot_frames(out, depth), _lerobot_frames(two, depth), strict=True):
            np.testing.assert_array_equal(a, b)
    _validate_deep(out, monkeypatch)


@pytest.mark.parametrize("fps", [5, 8])
def test_a_downsampling_resample_copies_like_subsample(fps, tmp_path, monkeypatch):
    """`resample` to a lower rate holds, per output frame, the source frame at or before its grid time:
    a selection shown once each, copied and encoded as `subsample`'s (10 -> 5 fps is every other
    frame, the same bytes as `subsample`'s; 10 -> 8 fps keeps frames 0, 1, 2, 3, 5, 6, ...: keyframes,
    frames after a copied one and frames after a left-out one). Encoded instead: an upsampling (a
    frame shown twice), and a rate the source's clock cannot show (10 -> 6 fps: the frame period is
    not a whole number of lerobot's 1/10240 s ticks)."""
    from shiftkit.transforms.resample import resampling_grid

    source = recording(TRIMMED)
    out = _run([source], tmp_path / "out", [StageSpec("resample", {"fps": fps})])
    kept = [resampling_grid(np.arange(n) / TRIMMED.fps, TRIMMED.fps, fps)[1].tolist() for n in TRIMMED.lengths]
    encoded_frames = _assert_selection_copied(source, out, kept, fps)
    assert any(encoded_frames.values()) == (fps == 8)
    if fps == 5:
        subsampled = _run([source], tmp_path / "sub", [StageSpec("subsample", {"every": 2})])
        assert {k: v for k, v in _files(out).items() if "videos/observation.images" in k} == {
            k: v for k, v in _files(subsampled).items() if "videos/observation.images" in k
        }
        for other in (20, 6):
            encoded = _run([source], tmp_path / f"at{other}", [StageSpec("resample", {"fps": other})])
            provenance = json.loads((encoded / "meta/shiftkit_provenance.json").read_text())
            assert set(provenance["video"].values()) == {"encoded"}
    _validate_deep(out, monkeypatch)


def _assert_selection_copied(source: Path, out: Path, kept: list[list[int]], fps: int) -> dict[str, int]:
    """`out` holds, per episode, source frames `kept` (each once, in order) shown at `fps`: which
    packets are copied follows the source's keyframe flags (a keyframe, or the frame right after a
    copied one), the copied ones are its bytes and lerobot's loader gives its frames exactly there,
    the encoded ones nearest their own kept source frame; the output's fps and episode durations are
    the new rate's; the HEVC depth is encoded whole. Returns the frames encoded per camera."""
    import pandas as pd

    provenance = json.loads((out / "meta/shiftkit_provenance.json").read_text())
    depth = "observation.depth.front"
    assert provenance["video"] == {**dict.fromkeys(CAMERAS, "copied"), depth: "encoded"}
    info = json.loads((out / "meta/info.json").read_text())
    assert info["fps"] == fps
    starts = np.cumsum((0, *TRIMMED.lengths))
    encoded_frames = {}
    for key in CAMERAS:
        src_info = json.loads((source / "meta/info.json").read_text())["features"][key]
        assert info["features"][key] == {**src_info, "info": {**src_info["info"], "video.fps": fps}}
        src_packets, src_keys = _episode_packets(source, key), _episode_packets(source, key, lambda p: p.is_keyframe)
        copied = []  # per output frame: its source frame (in the dataset), whether it is the source's packet
        for e, (frames, got) in enumerate(zip(kept, _episode_packets(out, key), strict=True)):
            assert len(got) == len(frames)
            for j, t in enumerate(frames):
                is_copy = src_keys[e][t] or (j > 0 and copied[-1][1] and t == frames[j - 1] + 1)
                copied.append((int(starts[e]) + t, is_copy))
                assert (got[j] == src_packets[e][t]) == is_copy
        encoded_frames[key] = sum(not c for _, c in copied)
        src_frames, got = _lerobot_frames(source, key), _lerobot_frames(out, key)
        assert len(got) == len(copied)
        for frame, (t, is_copy) in zip(got, copied, strict=True):
            if is_copy:
                np.testing.assert_array_equal(frame, src_frames[t])
        # an encoded frame is nearest its own source frame among the kept ones (none lost, none out of
        # order; the pictures are ramps, so a left-out neighbour may be as near) and close to it
        shown = [t for t, _ in copied]
        for frame, (t, is_copy) in zip(got, copied, strict=True):
            if not is_copy:
                errors = [np.mean((frame - src_frames[u]) ** 2) for u in shown]
                assert shown[int(np.argmin(errors))] == t and 10 * np.log10(1 / min(errors)) > 30
    assert provenance.get("video_encoded_at_cuts", {}) == {k: n for k, n in encoded_frames.items() if n}
    episodes = pd.concat(pd.read_parquet(p) for p in sorted((out / "meta/episodes").glob("*/*.parquet")))
    for key in (*CAMERAS, depth):
        duration = episodes[f"videos/{key}/to_timestamp"] - episodes[f"videos/{key}/from_timestamp"]
        np.testing.assert_allclose(duration, [len(k) / fps for k in kept], atol=1e-6)
    assert len(_lerobot_frames(out, depth)) == sum(len(k) for k in kept)
    return encoded_frames


def test_subsample_of_one_frame_episodes_shows_them_at_the_new_rate(tmp_path):
    """Episodes of one frame are kept whole by `subsample`: the output file still shows them one
    output frame apart (the source file copied as it is would show them at the source's rate, where
    lerobot's loader would find another episode's frame)."""
    rec = Recording(video=True, cameras=("front", "wrist"), depth=(), size=(32, 48), lengths=(1, 1, 1), language=False)
    source = recording(rec)
    out = _run([source], tmp_path / "out", [StageSpec("subsample", {"every": 2})])
    for key in CAMERAS:
        assert _episode_packets(out, key) == _episode_packets(source, key)
        for a, b in zip(_lerobot_frames(out, key), _lerobot_frames(source, key), strict=True):
            np.testing.assert_array_equal(a, b)


def _files(root: Path) -> dict[str, str]:
    """Every file's hash but the provenance's and card's (they name the executor)."""
    return {k: v for k, v in tree_hashes(root).items() if not k.endswith(("shiftkit_provenance.json", "README.md"))}


@pytest.fixture(scope="module")
def h264_source(tmp_path_factory):
    """A two-camera dataset that lerobot's writer encoded as H.264 yuv444p, crf 23, g 30 (B-frames: the
    packets' decode order is not their display order)."""
    from lerobot.configs import RGBEncoderConfig
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from tests.lerobot_recordings import episode_frames, features

    rec = Recording(video=True, cameras=("front", "wrist"), depth=(), size=(32, 48), lengths=(8, 8, 8), language=False)
    root = tmp_path_factory.mktemp("h264") / "src"
    encoder = RGBEncoderConfig(vcodec="h264", pix_fmt="yuv444p", crf=23, g=30)
    ds = LeRobotDataset.create("test/h264", rec.fps, features(rec), root=root, use_videos=True, rgb_encoder=encoder)
    for e in range(len(rec.lengths)):
        values = episode_frames(rec, e)
        for t in range(rec.lengths[e]):
            ds.add_frame({**{k: v[t] for k, v in values.columns.items()}, "task": values.tasks[t]})
        ds.save_episode()
    ds.finalize()
    return root


def test_an_h264_source_is_copied(h264_source, tmp_path):
    """Packets whose decode order differs from their display order (H.264 B-frames) are copied too."""
    out = _run([h264_source], tmp_path / "out", FILTER_RENAME)
    assert json.loads((out / "meta/shiftkit_provenance.json").read_text())["video"] == dict.fromkeys(CAMERAS, "copied")
    for key in CAMERAS:
        kept = _episode_packets(h264_source, key)
        assert _episode_packets(out, key) == [kept[0], kept[2]]
        expected = _frames_of(_lerobot_frames(h264_source, key), (8, 8, 8), [0, 2])
        for a, b in zip(_lerobot_frames(out, key), expected, strict=True):
            np.testing.assert_array_equal(a, b)


def test_a_re_encoded_camera_keeps_the_source_codec_settings(h264_source, tmp_path):
    """`trim` re-indexes frames, so its cameras are encoded: with the source's codec, pixel format,
    g and crf (H.264 yuv444p crf 23 g 30), not lerobot's AV1 yuv420p defaults; the frames stay close."""
    out = _run([h264_source], tmp_path / "out", [StageSpec("trim", {"head": 1})])
    provenance = json.loads((out / "meta/shiftkit_provenance.json").read_text())
    assert provenance["video"] == dict.fromkeys(CAMERAS, "encoded")
    for key in CAMERAS:
        info = json.loads((out / "meta/info.json").read_text())["features"][key]["info"]
        assert (info["video.codec"], info["video.pix_fmt"], info["video.g"], info["video.crf"]) == (
            "h264",
            "yuv444p",
            30,
            23,
        )
        src = _lerobot_frames(h264_source, key)
        expected = [src[t] for e in range(3) for t in range(8 * e + 1, 8 * e + 8)]
        got = _lerobot_frames(out, key)
        assert len(got) == len(expected)
        mse = np.mean([np.mean((a - b) ** 2) for a, b in zip(got, expected, strict=True)])
        assert 10 * np.log10(1 / mse) > 30  # PSNR in dB (frames in [0, 1]): 36 dB here, noisy pictures


@pytest.mark.parametrize("unit", ["m", "mm"])
def test_depth_video_is_copied_with_its_quantiser(unit, tmp_path, monkeypatch, no_decoding):
    """lerobot's 12-bit HEVC depth video passes `filter` + `rename` as its packets: nothing decoded,
    the quantiser parameters (`video.depth_min`, ...) and unit kept in `info.json`, lerobot's loader
    gives the source's depth, in metres and millimetres alike."""
    rec = Recording(
        video=True, cameras=(), depth=("front",), depth_unit=unit, size=(32, 48), lengths=(8, 8, 8), language=False
    )
    source = recording(rec)
    key = "observation.depth.front"
    out = _run([source], tmp_path / "out", FILTER_RENAME)
    assert json.loads((out / "meta/shiftkit_provenance.json").read_text())["video"] == {key: "copied"}
    src_info, out_info = (json.loads((r / "meta/info.json").read_text())["features"][key] for r in (source, out))
    assert out_info == src_info and out_info["info"]["is_depth_map"]
    kept = _episode_packets(source, key)
    assert _episode_packets(out, key) == [kept[0], kept[2]]
    for a, b in zip(
        _lerobot_frames(out, key), _frames_of(_lerobot_frames(source, key), rec.lengths, [0, 2]), strict=True
    ):
        np.testing.assert_array_equal(a, b)
    _validate_deep(out, monkeypatch)


def test_lerobot_trains_on_a_copied_output(tmp_path, no_decoding):
    """lerobot's own trainer (ACT, 2 steps) reads the copied videos of a filter + rename output."""
    out = _run([recording(SMALL)], tmp_path / "out", FILTER_RENAME)
    assert json.loads((out / "meta/shiftkit_provenance.json").read_text())["video"] == dict.fromkeys(CAMERAS, "copied")
    lerobot_train_two_steps("test/out", out, tmp_path / "train")


def test_lerobot_dataset_tools_edit_a_copied_output(tmp_path, monkeypatch, no_decoding):
    """lerobot's own dataset tools take a pipeline output whose videos were copied: `delete_episodes`
    (re-encodes), `remove_feature` and `merge_datasets` (copy) give datasets that lerobot loads,
    `shiftkit validate --deep` accepts, with the frames of the episodes they kept."""
    from lerobot.datasets import dataset_tools as tools
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    source = recording(SMALL)
    out = _run([source], tmp_path / "out", FILTER_RENAME)
    monkeypatch.undo()  # lerobot's tools and the checks below decode
    ds = LeRobotDataset("test/out", root=out, video_backend="pyav")
    edited = {
        "delete": tools.delete_episodes(ds, [0], output_dir=tmp_path / "del", repo_id="test/del").root,
        "remove": tools.remove_feature(ds, CAMERAS[1], output_dir=tmp_path / "rm", repo_id="test/rm").root,
        "merge": tools.merge_datasets([ds, ds], "test/merged", output_dir=tmp_path / "merged").root,
    }
    lengths = {"delete": SMALL.lengths[2], "remove": SMALL.lengths[0] + SMALL.lengths[2]}
    lengths["merge"] = 2 * lengths["remove"]
    for name, root in edited.items():
        loaded = LeRobotDataset(f"test/{name}", root=root, video_backend="pyav")
        assert len(loaded) == lengths[name], name
        _validate_deep(root, monkeypatch)
    kept = _frames_of(_lerobot_frames(source, CAMERAS[0]), SMALL.lengths, [0, 2])  # the source's frames
    for a, b in zip(_lerobot_frames(edited["remove"], CAMERAS[0]), kept, strict=True):
        np.testing.assert_array_equal(a, b)


def _stream(root: Path, key: str) -> dict:
    """The output stream of `key` as PyAV reads it: codec, pixel format, size, and per file the
    positions (display order) of its keyframes."""
    import av

    out: dict = {"keyframes": []}
    for path in sorted((root / "videos" / key).glob("chunk-*/file-*.mp4")):
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            ctx = stream.codec_context
            out.update(codec=stream.codec.canonical_name, pix_fmt=ctx.pix_fmt, size=(ctx.height, ctx.width))
            packets = sorted((p for p in container.demux(stream) if p.pts is not None), key=lambda p: p.pts)
            out["keyframes"].append([i for i, p in enumerate(packets) if p.is_keyframe])
    return out


def _assert_encoded_as(root: Path, key: str, codec: str, pix_fmt: str, g: int, crf: int) -> dict:
    """The output stream of `key` and its `info.json` entry say `codec`, `pix_fmt`, `g`, `crf`, and
    `info` the stream's size; returns the stream (`_stream`)."""
    stream = _stream(root, key)
    assert (stream["codec"], stream["pix_fmt"]) == (codec, pix_fmt)
    info = json.loads((root / "meta/info.json").read_text())["features"][key]["info"]
    assert (info["video.codec"], info["video.pix_fmt"], info["video.g"], info["video.crf"]) == (codec, pix_fmt, g, crf)
    assert (info["video.height"], info["video.width"]) == stream["size"]
    return stream


def test_a_resized_camera_keeps_the_source_codec_settings(h264_source, tmp_path, monkeypatch):
    """`resize` changes a camera's size only: it is encoded with the source's codec, pixel format, g
    and crf (H.264 yuv444p crf 23 g 30), not lerobot's AV1 yuv420p g 2 defaults; `info.json` says so
    and records the new size; the other camera is copied; the output passes `validate --deep`."""
    key = CAMERAS[0]
    out = _run([h264_source], tmp_path / "out", [StageSpec("resize", {"width": 32, "height": 16, "features": [key]})])
    provenance = json.loads((out / "meta/shiftkit_provenance.json").read_text())
    assert provenance["video"] == {key: "encoded", CAMERAS[1]: "copied"}
    stream = _assert_encoded_as(out, key, "h264", "yuv444p", 30, 23)
    assert stream["size"] == (16, 32)
    assert stream["keyframes"] == [[0, 8, 16]]  # one per episode: g 30 > 8 frames (lerobot's g 2: every other)
    frames = _lerobot_frames(out, key)
    assert len(frames) == 24 and frames[0].shape == (3, 16, 32)
    _validate_deep(out, monkeypatch)


def _psnr_of_encoded(got: list[np.ndarray], source: list[np.ndarray], frames: list[int]) -> float:
    """Encoded frames `got` (lerobot's loader's, in [0, 1]) against the source frames `frames`: each is
    nearer its own source frame than any other (none lost, none out of order) but one that the coding
    error cannot tell from it (the recordings' ramps repeat: a camera's frames 0 and 7 are 41.6 dB
    apart); their PSNR in dB."""
    assert len(got) == len(frames)
    for a, t in zip(got, frames, strict=True):
        errors = [np.mean((a - s) ** 2) for s in source]
        best = int(np.argmin(errors))
        assert best == t or np.mean((source[best] - source[t]) ** 2) < errors[t], (t, best)
    mse = np.mean([np.mean((a - source[t]) ** 2) for a, t in zip(got, frames, strict=True)])
    return float(10 * np.log10(1 / mse))


KEPT = [*range(0, 8), *range(16, 24)]  # the source frames of episodes 0 and 2 (FILTER_RENAME)


@pytest.mark.parametrize(
    ("source", "destination", "encoded_as", "min_psnr"),
    [
        # lerobot's AV1 recording (yuv420p, g 2, crf 30): H.264 as asked, at 4:4:4, its own g and crf;
        # its pictures are noise, which crf 30 keeps only roughly (24 dB as yuv420p)
        ("av1", {"vcodec": "h264", "pix_fmt": "yuv444p"}, ("h264", "yuv444p", 2, 30), 20),
        # the H.264 yuv444p crf 23 g 30 source: g and crf as asked, its codec and pixel format
        ("h264", {"g": 4, "crf": 18}, ("h264", "yuv444p", 4, 18), 30),
    ],
    ids=["av1-to-h264", "h264-g4-crf18"],
)
def test_destination_encoder_settings_over_the_source_ones(
    source, destination, encoded_as, min_psnr, h264_source, tmp_path, monkeypatch
):
    """`[destination]` encoder settings: frames that would be copied are encoded (the user asked for
    another stream), with each given setting, the source's for the others; the stream read back with
    PyAV (codec, pixel format, a keyframe every `g` frames), `info.json` and the provenance say so,
    lerobot loads the source's frames from it (lossy) and `validate --deep` passes."""
    src = recording(SMALL) if source == "av1" else h264_source
    out = _run([src], tmp_path / "out", FILTER_RENAME, **destination)
    assert json.loads((out / "meta/shiftkit_provenance.json").read_text())["video"] == dict.fromkeys(CAMERAS, "encoded")
    for key in CAMERAS:
        stream = _assert_encoded_as(out, key, *encoded_as)
        assert stream["keyframes"] == [list(range(0, 16, encoded_as[2]))] and stream["size"] == (32, 48)
        assert _psnr_of_encoded(_lerobot_frames(out, key), _lerobot_frames(src, key), KEPT) > min_psnr
    _validate_deep(out, monkeypatch)


def test_a_destination_the_source_already_is_still_copies(h264_source, tmp_path, no_decoding):
    """Settings the source stream already has (its codec named as lerobot's encoder is, "h264") ask
    for nothing new: both cameras are copied, packet for packet, nothing decoded."""
    out = _run([h264_source], tmp_path / "out", FILTER_RENAME, vcodec="h264", pix_fmt="yuv444p", g=30, crf=23)
    assert json.loads((out / "meta/shiftkit_provenance.json").read_text())["video"] == dict.fromkeys(CAMERAS, "copied")
    for key in CAMERAS:
        kept = _episode_packets(h264_source, key)
        assert _episode_packets(out, key) == [kept[0], kept[2]]


@pytest.mark.parametrize(
    ("setting", "message"),
    [
        ('vcodec = "nosuch"', "Invalid vcodec 'nosuch'"),
        ("crf = 52", "crf 52 is out of h264's range 0-51"),  # x264 would clamp it: its FFmpeg option allows it
        ('vcodec = "av1"\npix_fmt = "yuv420p"\ncrf = 64', "out of range for codec 'libsvtav1'"),
        ("crf = -1", "crf must be a finite number >= 0, got -1"),
        ("g = 0", "g must be a positive integer, got 0"),
        ('pix_fmt = "nosuch"', "nosuch"),
        ('vcodec = "h264"\npreset = "nosuch"', "the libx264 encoder refuses these settings"),
    ],
    ids=["codec", "crf-h264", "crf-av1", "crf-negative", "g", "pix_fmt", "preset"],
)
def test_bad_destination_encoder_settings_are_one_line_errors(setting, message, h264_source, tmp_path, capfd):
    """A bad encoder setting fails `shiftkit run` before anything is written: exit 2, one line (on
    the file descriptor: nothing the encoder library prints itself)."""
    config = tmp_path / "pipeline.toml"
    config.write_text(f'[[sources]]\npath = "{h264_source}"\n\n[destination]\nroot = "{tmp_path / "out"}"\n{setting}\n')
    code = main(["run", str(config), "--no-progress"])
    err = capfd.readouterr().err.strip()
    assert code == 2, err
    assert err.startswith("shiftkit run: error: ") and message in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out*"))


@pytest.mark.parametrize("rec", [SMALL, LARGE], ids=["32x48", "480x640"])
def test_frames_encoded_unchanged_are_transcoded_from_the_decoder_s_pixels(rec, tmp_path, monkeypatch, no_decoding):
    """Frames that pass unchanged but are encoded (here the destination asks for crf 40) go from the
    source's decoder to the encoder in its pixel format: nothing decoded to RGB (`no_decoding`; the
    kept episodes keep their recorded statistics), the destination's setting recorded, and the
    output nearer the source than the same frames encoded through RGB (the YUV -> RGB -> YUV
    round trip the workers did before); the output passes `validate --deep`."""
    from shiftkit.datasets.images import decode_video
    from shiftkit.datasets.video import decode_episode, encode_episode_video

    source = recording(rec)
    out = _run([source], tmp_path / "out", FILTER_RENAME, crf=40)
    assert json.loads((out / "meta/shiftkit_provenance.json").read_text())["video"] == dict.fromkeys(CAMERAS, "encoded")
    monkeypatch.undo()  # decoding allowed from here on: the check
    n = rec.lengths[0]
    for key in CAMERAS:
        ft = json.loads((out / "meta/info.json").read_text())["features"][key]
        assert ft["info"]["video.crf"] == 40
        src_ft = json.loads((source / "meta/info.json").read_text())["features"][key]
        src_file = source / f"videos/{key}/chunk-000/file-000.mp4"
        src = decode_video(src_file, 0.0, np.arange(n) / rec.fps, "test", src_ft)  # episode 0
        got = decode_video(out / f"videos/{key}/chunk-000/file-000.mp4", 0.0, np.arange(n) / rec.fps, "test", ft)
        through_rgb = encode_episode_video(src, ft, rec.fps, tmp_path / f"{key}-rgb.mp4").path
        rgb = decode_episode(through_rgb, 0.0, np.arange(n) / rec.fps, "test")
        psnr_direct, psnr_rgb = _psnr(got, src), _psnr(rgb, src)
        assert psnr_direct > psnr_rgb + 0.2, (psnr_direct, psnr_rgb)
    _validate_deep(out, monkeypatch)


def _psnr(frames: np.ndarray, reference: np.ndarray) -> float:
    """PSNR in dB of uint8 `frames` against `reference`."""
    return float(10 * np.log10(255.0**2 / np.mean((frames.astype(float) - reference) ** 2)))


def test_statistics_of_encoded_frames_decode_only_the_frames_lerobot_samples(monkeypatch):
    """A camera still encoded (`VideoRef`) whose statistics must be computed (a cut episode is not the
    one its source recorded them for) decodes only the frames lerobot's `sample_images` reads: 100
    of a 300-frame episode, RGB and depth, and the statistics are those of the fully decoded frames."""
    from shiftkit.datasets import images
    from shiftkit.datasets.reader import open_lerobot_dataset
    from shiftkit.datasets.stats import episode_stats
    from shiftkit.datasets.video_copy import VideoRef

    rec = Recording(video=True, cameras=("front",), depth=("front",), size=(32, 48), lengths=(300,), language=False)
    source = recording(rec)
    keys = ("observation.images.front", "observation.depth.front")
    reader = open_lerobot_dataset(source)
    features = reader.features
    decoded = next(reader.iter_episodes([0]))
    refs = next(reader.iter_episodes([0], video_refs=frozenset(keys)))
    uncomputed = {  # as a cut hands them on: no recorded statistics
        k: VideoRef(r.path, r.start, r.stop, r.timestamps, r.feature, None)
        for k, r in ((k, refs.frames[k]) for k in keys)
    }
    asked: list[int] = []
    real = images.decode_episode
    monkeypatch.setattr(
        images, "decode_episode", lambda path, start, ts, *a: asked.append(len(ts)) or real(path, start, ts, *a)
    )
    got = episode_stats(refs.with_frames(**uncomputed), features)
    assert asked == [100, 100]
    expected = episode_stats(decoded, features)
    for key in keys:
        assert got[key].keys() == expected[key].keys()
        for name, value in expected[key].items():
            np.testing.assert_array_equal(got[key][name], value, err_msg=f"{key} {name}")


_WORKER = """
import json, pickle, sys
from shiftkit.pipelines import work
config, answers, units = pickle.load(open(sys.argv[1], "rb"))
work.init_worker(config, None, answers)
for unit in units:
    work.process_unit(unit)
print(json.dumps(sorted(m for m in sys.modules if m.split(".")[0] in ("lerobot", "torch"))))
"""


@pytest.mark.parametrize(
    ("stage", "destination"),
    [
        (StageSpec("trim", {"head": 1, "tail": 2}), {"crf": 29}),  # transcoded from the decoder's pixels
        (StageSpec("resize", {"width": 32, "height": 16, "features": [CAMERAS[0]]}), {}),  # from RGB frames
    ],
    ids=["transcode", "resize"],
)
def test_a_worker_encodes_rgb_video_without_importing_lerobot(stage, destination, tmp_path, monkeypatch):
    """A pool worker (a fresh process, as `spawn` starts it) that encodes RGB video gets each
    camera's codec from its main process (`work.worker_answers`) and does not import lerobot, nor
    torch unless its stage does (`resize` interpolates with torch): 3-6 s and ~0.7 GB per worker here.
    Given no answers it asks lerobot itself. Either way the dataset the writer makes of its parts is
    the one a single process writes, byte for byte."""
    import pickle
    import subprocess
    import sys

    from shiftkit.pipelines import work
    from shiftkit.pipelines.planner import plan_pipeline

    source = recording(SMALL)
    reference = _run([source], tmp_path / "reference", [stage], **destination)
    imported = {}
    for given in ("answers", "none"):
        out = tmp_path / given
        config = PipelineConfig(
            sources=[SourceConfig(path=str(source))],
            destination=DestinationConfig(root=str(out), **destination),
            stages=[stage],
        )
        plan = plan_pipeline(config)
        work.work_dir_for(out).mkdir()  # as the runner prepares it before its executor starts
        (work.work_dir_for(out) / "run_key").write_text(work.run_key(plan))
        answers = work.worker_answers(plan) if given == "answers" else None
        args = tmp_path / f"{given}.pickle"
        args.write_bytes(pickle.dumps((config, answers, work.plan_units(plan))))
        done = subprocess.run([sys.executable, "-c", _WORKER, str(args)], capture_output=True, text=True, check=True)
        imported[given] = json.loads(done.stdout.splitlines()[-1])
        with monkeypatch.context() as m:  # the writer takes the worker's parts: nothing is transformed again
            m.setattr(work, "process_unit", lambda unit: pytest.fail("a finished part was transformed again"))
            run_pipeline(config, progress=False)
        assert _files(out) == _files(reference)
    assert not [m for m in imported["answers"] if m.startswith("lerobot")]
    assert stage.name == "resize" or imported["answers"] == []  # not even torch
    assert "torch" in imported["none"] and "lerobot.configs" in imported["none"]
