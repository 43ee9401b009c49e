"""The multiview env family (mv-lift, mv-stack, mv-pick-insert, mv-door): base poses per view,
base-frame observations and actions, camera metadata, state restore and the scripted experts."""

from __future__ import annotations

import numpy as np
import pytest

import shiftkit.envs as envs
from shiftkit.envs.base_pose import AIM, SAMPLER, BasePose
from shiftkit.envs.multiview.experts import rollout
from shiftkit.envs.multiview.physics import rebase_state

TASKS = [("mv-lift", "lift"), ("mv-stack", "stack"), ("mv-pick-insert", "pick-insert"), ("mv-door", "door")]


def test_views_fixed_uses_centre_pose_multiview_samples_aimed_poses():
    fixed = envs.make("mv-lift", "lift", view="fixed")
    multi = envs.make("mv-lift", "lift", view="multiview")
    poses = []
    for seed in range(20):
        _, info = fixed.reset(seed=seed)
        assert BasePose.from_dict(info["base_pose"]) == SAMPLER.centre_pose()
        _, info = multi.reset(seed=seed)
        pose = BasePose.from_dict(info["base_pose"])
        assert SAMPLER.axis_miss(pose) <= SAMPLER.miss_bound()
        poses.append(pose.yaw)
    assert np.ptp(poses) > 0.4  # yaw spread over the 0.8 rad range
    with pytest.raises(ValueError, match="view"):
        envs.make("mv-lift", "lift", view="sideways")


def test_observations_are_in_the_base_frame():
    env = envs.make("mv-lift", "lift")
    for seed in range(5):
        obs, info = env.reset(seed=seed)
        pose = BasePose.from_dict(info["base_pose"])
        block_world = pose.to_world(obs[13:16])
        # reset box: block centre within 12.5 cm of the world task centre, whatever the base pose
        assert np.all(np.abs(block_world[:2]) <= 0.125 + 1e-6)
        assert np.linalg.norm(obs[13:15] - AIM[:2]) < 0.125 * np.sqrt(2) + 0.03
        assert np.allclose(obs[:3], env.physics.tcp_pos(), atol=1e-6)


@pytest.mark.parametrize("yaw", [-0.6, 0.2])
def test_actions_move_the_tcp_along_base_axes_whatever_the_base_yaw(yaw):
    env = envs.make("mv-stack", "stack")
    obs, _ = env.reset(seed=0, options={"base_pose": SAMPLER.solve(yaw)})
    start = obs[:3].copy()
    for _ in range(3):
        obs, *_ = env.step(np.array([1.0, 0, 0, 0, 0, 0, 1.0]))
    moved = obs[:3] - start
    assert moved[0] > 0.05 and abs(moved[1]) < 0.01 and abs(moved[2]) < 0.01


def test_camera_metadata_and_state_restore():
    env = envs.make("mv-door", "door", width=64, height=48)
    _, info = env.reset(seed=3)
    cams = env.camera_metadata()["base"]
    assert set(cams) == {"intrinsics", "extrinsics", "base_pose"}
    assert cams["intrinsics"]["width"] == 64 and cams["intrinsics"]["fy"] == pytest.approx(24 / np.tan(np.deg2rad(35)))
    assert cams["extrinsics"]["frame"] == "base" and cams["base_pose"] == info["base_pose"]
    rgb = env.render_rgb()
    for _ in range(5):
        env.step(env.action_space.sample())
    env.set_sim_state(info["qpos"], info["qvel"])
    assert np.array_equal(env.render_rgb(), rgb)


def test_rebase_state_keeps_object_world_poses():
    env = envs.make("mv-stack", "stack")
    _, info = env.reset(seed=1)
    old = env.base_pose
    world = [env.base_pose.to_world(env.physics.object_pos(n)) for n in ("blue", "green")]
    new = SAMPLER.solve(0.1)
    qpos, qvel = rebase_state(env.physics, info["qpos"], info["qvel"], old, new)
    env.set_base_pose(new)
    env.set_sim_state(qpos, qvel)
    for name, w in zip(("blue", "green"), world, strict=True):
        assert np.allclose(new.to_world(env.physics.object_pos(name)), w, atol=1e-9)


@pytest.mark.parametrize("pair", TASKS, ids=[t for _, t in TASKS])
@pytest.mark.parametrize("view", ["fixed", "multiview"])
def test_expert_succeeds_and_rollout_carries_camera_metadata(pair, view):
    env = envs.make(*pair, view=view)
    results = [rollout(env, seed, cameras=("base",) if seed == 0 else ()) for seed in range(3)]
    assert all(r.succeeded for r in results)
    r = results[0]
    assert r.images["base"].shape == (len(r.actions), 48, 64, 3)
    assert r.meta["cameras"]["base"]["base_pose"] == results[0].meta["cameras"]["base"]["base_pose"]
    assert r.meta["view"] == view
