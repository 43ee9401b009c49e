"""Cameras a pipeline must encode (a stage re-indexed or changed their frames) are encoded by the
workers, each output episode into a file of its own with the writer's encoder, and the writer
appends those files as lerobot's writer appends its own encodes (datasets/video.py). Checked on a
dataset written by lerobot 0.6.1's own writer (two AV1 cameras and 12-bit HEVC depth): a run's
parts hold the encoded files, not pixels, its work folder stays within twice the output's size,
and the output is the same bytes whether one worker or two encoded it, and the frames lerobot's
loader decodes from it are the source's (within the codec's loss)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from shiftkit.datasets.sources import SourceConfig
from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, StageSpec
from shiftkit.pipelines.runner import run_pipeline
from tests.helpers import tree_hashes
from tests.lerobot_recordings import Recording, recording

REC = Recording(
    video=True, cameras=("front", "wrist"), depth=("front",), size=(64, 80), lengths=(9, 8, 7), language=False
)
VIDEOS = ("observation.images.front", "observation.images.wrist", "observation.depth.front")
TRIM = [StageSpec("trim", {"head": 1, "tail": 1})]


def _config(source: Path, out: Path) -> PipelineConfig:
    # trimmed, and RGB asked at another crf than the source's (depth: HEVC, never cut): all encoded
    return PipelineConfig(
        sources=[SourceConfig(path=str(source))], destination=DestinationConfig(root=str(out), crf=25), stages=TRIM
    )


def _folder_bytes(root: Path) -> int:
    return sum(p.stat().st_size for p in root.rglob("*") if p.is_file())


def test_parts_hold_encoded_video_and_the_scratch_stays_small(tmp_path):
    from shiftkit.datasets.video import EncodedVideo
    from shiftkit.pipelines.planner import plan_pipeline
    from shiftkit.pipelines.work import PartStore, plan_units, process_unit, set_up_worker, work_dir_for

    source = recording(REC)
    config = _config(source, tmp_path / "out")
    plan = set_up_worker(plan_pipeline(config))
    for unit in plan_units(plan):
        process_unit(unit)
    work = work_dir_for(plan.destination)
    parts = PartStore(work)
    for i, n in enumerate(REC.lengths):
        ((episode, _),) = list(parts.read(0, i))
        for key in VIDEOS:
            video = episode.frames[key]
            assert isinstance(video, EncodedVideo) and video.path.is_file() and len(video) == n - 2
    scratch = _folder_bytes(work)
    out = run_pipeline(config, progress=False)  # resumes from the parts: only the writer runs
    assert json.loads((out / "meta/shiftkit_provenance.json").read_text())["video"] == dict.fromkeys(VIDEOS, "encoded")
    pixels = sum(n - 2 for n in REC.lengths) * 64 * 80 * (3 + 3 + 4)  # the frames as the stages held them
    assert scratch <= 2 * _folder_bytes(out) < pixels
    assert not work.exists()


def test_the_output_is_the_same_bytes_with_two_workers_and_holds_the_source_frames(tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    source = recording(REC)
    one = run_pipeline(_config(source, tmp_path / "one"), progress=False)
    more = run_pipeline(_config(source, tmp_path / "more"), workers=2, progress=False)
    videos = {k: v for k, v in tree_hashes(one).items() if k.startswith("videos/")}
    assert videos and videos == {k: v for k, v in tree_hashes(more).items() if k.startswith("videos/")}
    src = LeRobotDataset("test/src", root=source, video_backend="pyav")
    out = LeRobotDataset("test/out", root=one, video_backend="pyav")
    starts = np.cumsum([0, *REC.lengths])
    k = 0
    for e, n in enumerate(REC.lengths):
        for t in range(1, n - 1):
            a, b = src[int(starts[e]) + t], out[k]
            for key in VIDEOS[:2]:  # RGB within the lossy codec's reach of the source's frames
                diff = (a[key].float() - b[key].float()).abs().mean().item()
                assert diff < 0.03, (e, t, key, diff)
            k += 1
    assert k == len(out)
