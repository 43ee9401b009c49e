"""The `multiview` stage: re-rendered views are physically consistent (replaying their re-expressed
actions at their base pose succeeds), carry the camera-metadata contract, and drop what IK misses."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from shiftkit.app.collect import CollectConfig, collect
from shiftkit.datasets.errors import ConfigError
from shiftkit.datasets.sources import SourceConfig
from shiftkit.datasets.sources.raw import open_raw_dataset
from shiftkit.envs import make
from shiftkit.envs.base_pose import SAMPLER, BasePose
from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, StageSpec
from shiftkit.pipelines.planner import plan_pipeline
from shiftkit.pipelines.stage import StageContext
from shiftkit.transforms.multiview import Multiview, MultiviewConfig


@pytest.fixture(scope="module")
def lift_episodes(tmp_path_factory):
    out, _ = collect(
        CollectConfig(
            env="mv-lift",
            task="lift",
            episodes=3,
            seed=10,
            out=str(tmp_path_factory.mktemp("mv") / "raw"),
            cameras=("base",),
            depth=True,
            env_kwargs={"view": "fixed"},
        )
    )
    raw = open_raw_dataset(out)
    return [raw.read_episode(i) for i in range(raw.num_episodes)]


def _stage(**params) -> Multiview:
    stage = Multiview(MultiviewConfig(**params), StageContext(fps=10))
    stage.setup()
    return stage


def test_replaying_reexpressed_actions_at_the_sampled_pose_succeeds(lift_episodes):
    stage = _stage(num_views=2)
    env = make("mv-lift", "lift", view="fixed")
    replayed = 0
    for i, episode in enumerate(lift_episodes):
        for out in stage.process(episode, np.random.default_rng(i)):
            pose = BasePose.from_dict(out.meta["cameras"]["base"]["base_pose"])
            env.reset(seed=0, options={"base_pose": pose})
            env.set_sim_state(out.frames["sim.qpos"][0], out.frames["sim.qvel"][0])
            success = False
            for action in out.frames["action"]:
                *_, info = env.step(action)
                success |= info["is_success"]
            assert success, f"episode {i} at {pose}"
            replayed += 1
    assert replayed == 2 * len(lift_episodes)


def test_views_carry_new_base_poses_and_the_same_world_trajectory(lift_episodes):
    episode = lift_episodes[0]
    source = BasePose.from_dict(episode.meta["cameras"]["base"]["base_pose"])
    outs = list(_stage(num_views=3).process(episode, np.random.default_rng(0)))
    assert len(outs) == 3
    src_state = episode.frames["observation.state"]
    for out in outs:
        cams = out.meta["cameras"]["base"]
        pose = BasePose.from_dict(cams["base_pose"])
        assert pose != source and SAMPLER.axis_miss(pose) <= SAMPLER.miss_bound()
        assert cams["intrinsics"] == episode.meta["cameras"]["base"]["intrinsics"]
        assert cams["extrinsics"] == episode.meta["cameras"]["base"]["extrinsics"]
        assert out.meta["multiview"]["source_base_pose"] == source.as_dict()
        state = out.frames["observation.state"]
        assert np.allclose(pose.to_world(state[:, :3]), source.to_world(src_state[:, :3]), atol=1e-5)
        assert np.array_equal(state[:, 7:], src_state[:, 7:])  # fingers do not depend on the frame
        # the block's world position is unchanged; its base-frame coordinates are not
        env_state = out.frames["observation.environment_state"]
        src_env = episode.frames["observation.environment_state"]
        assert np.allclose(pose.to_world(env_state[:, :3]), source.to_world(src_env[:, :3]), atol=1e-5)
        assert np.allclose(
            np.linalg.norm(out.frames["action"][:, :3], axis=1),
            np.linalg.norm(episode.frames["action"][:, :3], axis=1),
            atol=1e-6,
        )
        assert out.frames["observation.images.base"].shape == episode.frames["observation.images.base"].shape
        assert not np.array_equal(
            out.frames["observation.images.base"][0], episode.frames["observation.images.base"][0]
        )
        depth = out.frames["observation.depth.base"]  # re-rendered metres, lerobot's native depth
        assert depth.dtype == np.float32 and depth.shape == episode.frames["observation.depth.base"].shape
        assert not np.array_equal(depth[0], episode.frames["observation.depth.base"][0])
        assert 0.2 < float(np.median(depth)) < 3.0
    assert episode.meta["cameras"]["base"]["base_pose"] == source.as_dict()  # input untouched


def test_matched_gives_one_view_per_episode(lift_episodes):
    stage = _stage(num_views=3, matched=True)
    outs = [list(stage.process(ep, np.random.default_rng(i))) for i, ep in enumerate(lift_episodes)]
    assert [len(o) for o in outs] == [1, 1, 1]
    assert [len(o[0]) for o in outs] == [len(ep) for ep in lift_episodes]


def test_views_that_ik_cannot_follow_are_dropped_and_counted(lift_episodes, caplog):
    stage = _stage(num_views=2, max_ik_error=1e-9)
    with caplog.at_level(logging.WARNING):
        assert list(stage.process(lift_episodes[0], np.random.default_rng(0))) == []
    assert sum("IK missed" in r.message for r in caplog.records) == 2


def test_input_without_simulator_state_is_refused(synthetic_raw, tmp_path):
    config = PipelineConfig(
        sources=[SourceConfig(path=str(synthetic_raw))],
        destination=DestinationConfig(root=str(tmp_path / "o")),
        stages=[StageSpec(name="multiview", params={})],
    )
    with pytest.raises(ConfigError, match="multiview: input lacks sim.qpos") as info:
        plan_pipeline(config)
    assert "\n" not in str(info.value)


def test_multiview_dataset_cameras_json_carries_per_episode_base_poses(tmp_path):
    import json

    from shiftkit.datasets.reader import open_lerobot_dataset
    from shiftkit.pipelines.runner import run_pipeline

    raw, _ = collect(
        CollectConfig(env="mv-lift", task="lift", episodes=2, out=str(tmp_path / "raw"), cameras=("base",), depth=True)
    )
    config = PipelineConfig(
        sources=[SourceConfig(path=str(raw))],
        destination=DestinationConfig(root=str(tmp_path / "out")),
        stages=[StageSpec(name="multiview", params={"num_views": 2})],
    )
    dest = run_pipeline(config, progress=False)
    doc = json.loads((dest / "meta" / "cameras.json").read_text())
    assert doc["format"] == "shiftkit-cameras"
    # the camera's intrinsics and its pose on the base are constant; the base pose varies per episode
    assert {"intrinsics", "extrinsics"} <= set(doc["cameras"]["base"])
    poses = [doc["episodes"][str(i)]["base"]["base_pose"] for i in range(4)]
    assert len({json.dumps(p, sort_keys=True) for p in poses}) == 4
    for pose in poses:
        assert SAMPLER.axis_miss(BasePose.from_dict(pose)) <= SAMPLER.miss_bound()
    reader = open_lerobot_dataset(dest)
    assert [e.meta["cameras"]["base"]["base_pose"] for e in reader.iter_episodes([0, 1, 2, 3])] == poses
