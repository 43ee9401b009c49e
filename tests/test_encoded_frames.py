"""Unchanged camera frames keep their source PNG bytes through stages and the runner's parts; a
frame a stage changed (even in place) is always encoded afresh."""

from __future__ import annotations

import pickle

import cv2
import numpy as np
import pyarrow.parquet as pq

from shiftkit.datasets.encoded_frames import EncodedFrames, source_bytes
from shiftkit.datasets.reader import open_lerobot_dataset
from shiftkit.datasets.sources import SourceConfig
from shiftkit.datasets.writer import DatasetWriter
from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, StageSpec
from shiftkit.pipelines.runner import run_pipeline
from tests.helpers import write_raw_as_lerobot

KEY = "observation.images.front"


def _png_column(root):
    table = pq.read_table(sorted((root / "data").rglob("*.parquet"))[0], columns=[KEY])
    return [v["bytes"] for v in table.column(KEY).to_pylist()]


def _recode_with_opencv(root):
    """Rewrite the dataset's PNGs with another encoder (same pixels, different bytes), as a
    dataset from elsewhere may have them."""
    path = sorted((root / "data").rglob("*.parquet"))[0]
    table = pq.read_table(path)
    images = table.column(KEY).to_pylist()
    for v in images:
        v["bytes"] = cv2.imencode(".png", cv2.imdecode(np.frombuffer(v["bytes"], np.uint8), 1))[1].tobytes()
    import pyarrow as pa

    table = table.set_column(
        table.schema.get_field_index(KEY), KEY, pa.array(images, type=table.schema.field(KEY).type)
    )
    pq.write_table(table, path)


def test_unchanged_frames_keep_their_bytes_through_stages(synthetic_raw_images, tmp_path):
    src = write_raw_as_lerobot(synthetic_raw_images, "test/src", tmp_path / "src")
    _recode_with_opencv(src)
    source_bytes = set(_png_column(src))
    config = PipelineConfig(
        sources=[SourceConfig(path=str(src))],
        destination=DestinationConfig(root=str(tmp_path / "out")),
        stages=[StageSpec("trim", {"head": 1}), StageSpec("subsample", {"every": 2})],
    )
    out = run_pipeline(config, workers=2, progress=False)
    written = _png_column(out)
    assert written and set(written) <= source_bytes  # reused, not re-encoded by PIL
    for a, b in zip(open_lerobot_dataset(src).iter_episodes(), open_lerobot_dataset(out).iter_episodes(), strict=True):
        np.testing.assert_array_equal(a.frames[KEY][1:][::2], b.frames[KEY])


def test_changed_frames_are_encoded_afresh(synthetic_raw_images, tmp_path):
    src = write_raw_as_lerobot(synthetic_raw_images, "test/src", tmp_path / "src")
    reader = open_lerobot_dataset(src)
    episode = next(reader.iter_episodes())
    frames = episode.frames[KEY]
    assert isinstance(frames, EncodedFrames) and source_bytes(frames[2], frames) is not None
    frames = pickle.loads(pickle.dumps(episode.select(slice(0, 4)).frames[KEY]))  # parts, select
    assert source_bytes(frames[3], frames) is not None
    frames[0, :5] = 255  # in place: the stored bytes no longer match the pixels
    assert source_bytes(frames[0], frames) is None
    episode = episode.select(slice(0, 4)).with_frames(**{KEY: frames})
    with DatasetWriter("test/out", tmp_path / "out", reader.fps, reader.features) as writer:
        writer.add_episode(episode)
    np.testing.assert_array_equal(next(open_lerobot_dataset(tmp_path / "out").iter_episodes()).frames[KEY], frames)


def test_new_frames_are_encoded_by_the_workers_not_the_writer(synthetic_raw_images, tmp_path, monkeypatch):
    """Frames a source or stage made anew are PNG-encoded where the stages run (in parallel with
    several workers); the one writer copies the bytes."""
    from shiftkit.datasets import images

    real_png, real_init = images._png_bytes, DatasetWriter.__init__
    seen = {"writer": False, "encoded_by_writer": 0}

    def png(frame):
        seen["encoded_by_writer"] += seen["writer"]
        return real_png(frame)

    def init(self, *args, **kwargs):
        seen["writer"] = True
        real_init(self, *args, **kwargs)

    monkeypatch.setattr(images, "_png_bytes", png)
    monkeypatch.setattr(DatasetWriter, "__init__", init)
    config = PipelineConfig(
        sources=[SourceConfig(path=str(synthetic_raw_images))],
        destination=DestinationConfig(root=str(tmp_path / "out")),
        stages=[StageSpec("trim", {"head": 1})],
    )
    out = run_pipeline(config, progress=False)  # one worker: in this process, before the writer
    assert seen == {"writer": True, "encoded_by_writer": 0}
    episode = next(open_lerobot_dataset(out).iter_episodes())
    frames = episode.frames[KEY]
    # a part holds the pixels and the PNG bytes once each (the copies that confirm a hit are rebuilt)
    encoded = sum(len(source_bytes(f, frames)) for f in frames)
    assert len(pickle.dumps(frames)) < frames.nbytes + encoded + 4096


def test_raw_camera_frames_travel_as_their_png_files(synthetic_raw_images, tmp_path, monkeypatch):
    """A pass-through of a raw-episode source copies each camera PNG file's bytes into the
    dataset: no frame is encoded again."""
    from shiftkit.datasets import images

    def no_encoding(frame):
        raise AssertionError("an unchanged raw frame was PNG-encoded again")

    monkeypatch.setattr(images, "_png_bytes", no_encoding)
    files = {p.read_bytes() for p in synthetic_raw_images.rglob("frame_*.png")}
    config = PipelineConfig(
        sources=[SourceConfig(path=str(synthetic_raw_images))],
        destination=DestinationConfig(root=str(tmp_path / "out")),
        stages=[StageSpec("trim", {"head": 1})],
    )
    written = _png_column(run_pipeline(config, progress=False))
    assert written and set(written) <= files


def test_raw_pngs_a_reader_decodes_otherwise_are_encoded_afresh(synthetic_raw_images, tmp_path):
    """A grey PNG is read as three equal channels: its own bytes would decode to one channel, so
    the dataset holds an RGB encoding of what the raw reader saw."""
    for path in synthetic_raw_images.rglob("frame_*.png"):
        grey = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2GRAY)
        path.write_bytes(cv2.imencode(".png", grey)[1].tobytes())
    grey_files = {p.read_bytes() for p in synthetic_raw_images.rglob("frame_*.png")}
    config = PipelineConfig(
        sources=[SourceConfig(path=str(synthetic_raw_images))],
        destination=DestinationConfig(root=str(tmp_path / "out")),
    )
    out = run_pipeline(config, progress=False)
    assert not set(_png_column(out)) & grey_files
    frames = next(open_lerobot_dataset(out).iter_episodes()).frames[KEY]
    assert frames.shape[-1] == 3 and np.array_equal(frames[..., 0], frames[..., 2])
