"""Stage kinds: frame-for-frame stages (`FrameStage`) and re-indexing ones (`ReindexStage`), and what
the planner derives from them: per output camera, whether its frames pass unchanged from every source
(`Plan.frames_pass_unchanged`), the fact that lets the writer copy a source's video instead of
encoding it again. The planner's answer is checked against the truth: where it says yes, every
output frame of that camera is its source frame's pixels."""

from __future__ import annotations

import numpy as np
import pytest

from shiftkit.datasets.features import CAMERA_DTYPES
from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, PipelineSource, StageSpec
from shiftkit.pipelines.planner import plan_pipeline
from shiftkit.pipelines.runner import run_pipeline
from shiftkit.pipelines.stage import STAGES, FrameStage, ReindexStage, Stage, register_stage
from shiftkit.pipelines.work import transform_episode
from tests.lerobot_recordings import Recording, recording

# a lerobot-written video recording: RGB front and wrist, millimetre depth of the front camera
VIDEO = Recording(fps=10, lengths=(7, 5), cameras=("front", "wrist"), depth=("front",), depth_unit="mm",
                  video=True, size=(16, 32), language=False)  # fmt: skip
FRONT, WRIST, DEPTH = "observation.images.front", "observation.images.wrist", "observation.depth.front"


def test_every_shipped_stage_says_its_kind():
    kinds = {name: ("reindex" if issubclass(cls, ReindexStage) else "frame" if issubclass(cls, FrameStage) else "other")
             for name, cls in STAGES.items() if cls.__module__.startswith("shiftkit.")}  # fmt: skip
    assert {n for n, k in kinds.items() if k == "reindex"} == {"trim", "subsample", "resample", "success_examples"}
    assert {n for n, k in kinds.items() if k == "other"} == {"force_match"}  # a slower replay: its own frame map


def _plan(stages, tmp_path, video=None, own=()):
    source = PipelineSource(path=str(recording(VIDEO)), stages=[StageSpec(n, p) for n, p in own])
    config = PipelineConfig(
        sources=[source],
        destination=DestinationConfig(root=str(tmp_path / "out"), video=video),
        stages=[StageSpec(n, p) for n, p in stages],
    )
    return plan_pipeline(config)


@pytest.mark.parametrize(
    ("stages", "video", "unchanged"),
    [
        ([], None, {FRONT, WRIST, DEPTH}),
        ([("rename", {"mapping": {FRONT: "observation.images.top"}}), ("drop", {"features": [WRIST]})], None,
         {"observation.images.top", DEPTH}),
        ([("resize", {"width": 32, "height": 8, "features": [WRIST]})], None, {FRONT, DEPTH}),
        ([("depth_image", {"unit": "m"})], None, {FRONT, WRIST}),  # depth stored in another unit
        ([("filter", {"min_length": 6})], None, {FRONT, WRIST, DEPTH}),  # whole episodes dropped
        ([("trim", {"head": 1})], None, {FRONT, WRIST, DEPTH}),  # one contiguous run of each episode
        ([("subsample", {"every": 2})], None, {FRONT, WRIST, DEPTH}),  # every other frame, each once
        ([("resample", {"fps": 5})], None, {FRONT, WRIST, DEPTH}),  # downsampled: every other frame, each once
        ([("resample", {"fps": 20})], None, set()),  # upsampled: each frame shown twice
        ([], False, set()),  # stored as images instead of video
    ],
)  # fmt: skip
def test_the_plan_says_which_cameras_pass_unchanged(tmp_path, stages, video, unchanged):
    plan = _plan(stages, tmp_path, video)
    cameras = {k for k, ft in plan.features.items() if ft["dtype"] in CAMERA_DTYPES}
    assert {k for k in cameras if plan.frames_pass_unchanged(k)} == unchanged
    assert not plan.frames_pass_unchanged("action") and not plan.frames_pass_unchanged("nope")
    # the truth: a camera said to pass unchanged holds its source frames' pixels, frame for frame
    source = plan.sources[0]
    renamed = {"observation.images.top": FRONT}
    for episode in source.iter_episodes(list(range(source.num_episodes))):
        for out, _ in [(o, None) for o in transform_episode(plan, 0, episode)[0]]:
            for key in unchanged:
                np.testing.assert_array_equal(
                    np.asarray(out.frames[key]), np.asarray(episode.frames[renamed.get(key, key)])[out.origin()]
                )


def test_a_source_s_own_stages_count_too(tmp_path):
    plan = _plan([], tmp_path, own=[("resize", {"width": 32, "height": 8, "features": [FRONT]})])
    assert not plan.frames_pass_unchanged(FRONT) and plan.frames_pass_unchanged(WRIST)


def test_a_frame_stage_that_changes_frames_is_refused(synthetic_raw, tmp_path):
    """A stage declared frame for frame that drops a frame (or sets another frame map) fails its run,
    naming the stage and its kind."""
    from dataclasses import dataclass

    @dataclass
    class ShorteningConfig:
        """Parameters of `shortening`."""

    class Shortening(FrameStage):
        name, version, Config = "shortening", 1, ShorteningConfig

        def transform_features(self, features):
            return features

        def process(self, episode, rng):
            yield episode.select(slice(0, len(episode) - 1))

    register_stage(Shortening)
    try:
        config = PipelineConfig(
            sources=[PipelineSource(path=str(synthetic_raw))],
            destination=DestinationConfig(root=str(tmp_path / "out")),
            stages=[StageSpec("shortening", {})],
        )
        with pytest.raises(ValueError, match="frame stage 'shortening' changed its episode's frames"):
            run_pipeline(config, progress=False)
    finally:
        STAGES._items.pop("shortening")


def test_a_reindex_stage_moves_events_from_its_map(synthetic_raw):
    """A re-indexing stage gives only the map; the base moves the events (here: a success on a dropped
    frame lands on the kept frame before it)."""
    from shiftkit.datasets.sources.raw import RawSource
    from shiftkit.pipelines.stage import Reindex, StageContext

    class KeepEven(ReindexStage):
        name, version = "keep_even", 1

        def transform_features(self, features):
            return features

        def reindex(self, episode, rng):
            index = np.arange(0, len(episode), 2)
            yield Reindex(index, np.arange(len(index)) / 5)

    episode = next(RawSource(synthetic_raw).iter_episodes([0]))
    success = np.zeros((len(episode), 1), bool)
    success[-1] = True  # the last frame (odd: 12 frames) is dropped
    episode = episode.with_frames(**{"next.success": success})
    (out,) = KeepEven(None, StageContext(fps=10)).process(episode, np.random.default_rng(0))
    assert out.origin().tolist() == list(range(0, 12, 2))
    assert out.frames["next.success"].reshape(-1).tolist() == [False] * 5 + [True]
    assert isinstance(KeepEven(None, StageContext(fps=10)), Stage)
