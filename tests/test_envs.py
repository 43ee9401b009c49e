"""Conformance of every registered environment/task: spaces, reset/step API, determinism, the
success flag, simulator state in info, and render shapes."""

from __future__ import annotations

from dataclasses import replace

import gymnasium as gym
import mujoco
import numpy as np
import pytest

import shiftkit.envs as envs
from shiftkit.envs.panda_play.physics import OBSERVATION_NAMES, PandaPlayPhysics

PAIRS = [(env, task) for env, tasks in envs.ENV_TASKS.items() for task in tasks]


def _run(env, seed: int, steps: int) -> tuple[np.ndarray, np.ndarray]:
    obs, info = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    frames, qpos = [obs], [info["qpos"]]
    for _ in range(steps):
        obs, reward, terminated, truncated, info = env.step(rng.uniform(-1, 1, env.action_space.shape))
        frames.append(obs)
        qpos.append(info["qpos"])
    return np.array(frames), np.array(qpos)


@pytest.fixture(scope="module")
def shared_envs():
    made = {pair: envs.make(*pair) for pair in PAIRS}
    yield made
    for env in made.values():
        env.close()


@pytest.mark.parametrize("pair", PAIRS, ids=[f"{e}-{t}" for e, t in PAIRS])
def test_reset_step_spaces_and_info(shared_envs, pair):
    env = shared_envs[pair]
    family = envs.env_family(pair[0])
    obs, info = env.reset(seed=0)
    dims = len(family.observation_names)
    assert env.observation_space.shape == (dims,) and env.observation_space.dtype == np.float32
    assert env.action_space.shape == (len(family.action_names),)
    assert tuple(env.observation_names) == tuple(family.observation_names)
    assert sorted(np.r_[family.state_indices, family.environment_state_indices].tolist()) == list(range(dims))
    if pair[0] == "panda-play":
        assert dims == 59 and tuple(env.observation_names) == OBSERVATION_NAMES
    assert env.observation_space.contains(obs)
    for key in ("is_success", "qpos", "qvel"):
        assert key in info
    for _ in range(3):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert env.observation_space.contains(obs) and np.isfinite(obs).all()
        assert isinstance(info["is_success"], bool) and reward == float(info["is_success"])
        assert terminated is False and truncated is False
        assert info["qpos"].shape == (env.physics.model.nq,) and info["qvel"].shape == (env.physics.model.nv,)
    with pytest.raises(ValueError):
        env.step(np.full(env.action_space.shape, np.nan))
    for camera in family.cameras:
        assert env.render_rgb(camera).shape == (48, 64, 3) and env.render_depth(camera).shape == (48, 64)


@pytest.mark.parametrize("pair", PAIRS, ids=[f"{e}-{t}" for e, t in PAIRS])
def test_same_seed_same_arrays(shared_envs, pair):
    env = shared_envs[pair]
    a_obs, a_q = _run(env, seed=7, steps=15)
    b_obs, b_q = _run(env, seed=7, steps=15)
    _, c_q = _run(env, seed=8, steps=2)
    assert np.array_equal(a_obs, b_obs) and np.array_equal(a_q, b_q)
    assert not np.array_equal(a_q[0], c_q[0])  # the reset state depends on the seed


def test_gym_ids_registered_and_kwargs_pass_through():
    for env_name, task in PAIRS:
        env_id = envs.gym_id(env_name, task)
        assert env_id in gym.registry
    env = gym.make("shiftkit/PandaPlay-Lift-v0", control_hz=5)
    obs, _ = env.reset(seed=1)
    assert obs.shape == (59,)
    assert env.unwrapped.physics.n_substeps == 100 and env.unwrapped.max_episode_steps == 90
    env.close()


def test_panda_play_observation_names():
    assert envs.env_family("panda-play").observation_names == OBSERVATION_NAMES


def test_reset_state_matches_reference_conventions(shared_envs):
    env = shared_envs[("panda-play", "lift")]
    for seed in range(5):
        obs, _ = env.reset(seed=seed)
        assert np.allclose(obs[[14, 21]], 0.145, atol=5e-4)  # resting block centre height
        assert np.allclose(obs[6:12], 1.0, atol=0.02)  # gripper open, history filled
        assert np.all(np.abs(obs[[12, 19]]) <= 0.075 + 1e-6) and np.all(np.abs(obs[[13, 20]] - 0.5) <= 0.075 + 1e-6)
        assert 0.175 - 1e-3 <= obs[2] <= 0.27 + 1e-3
        assert np.all(obs[[18, 25]] >= 0)  # quaternion w >= 0 (xyzw order)
        assert np.abs(obs[26:38]).max() < 0.05
        assert np.allclose(obs[38:41], obs[12:15] - obs[0:3], atol=1e-6)
        assert np.allclose(obs[47:50] + obs[12:15], [0.075, 0.5, 0.125], atol=1e-6)


def test_unstack_stack_starts_green_on_blue(shared_envs):
    env = shared_envs[("panda-play", "unstack-stack")]
    obs, _ = env.reset(seed=3)
    assert obs[21] == pytest.approx(0.185, abs=2e-3) and np.linalg.norm(obs[19:21] - obs[12:14]) < 2e-3


def test_hold_counts_and_5hz():
    physics = PandaPlayPhysics(5)
    assert physics.n_substeps == 100 and physics.n_ticks == 4 and physics.max_step == pytest.approx(0.04)
    from shiftkit.envs.panda_play.tasks import TASKS

    assert TASKS["lift"].hold_steps(20) == 10 and TASKS["move-object"].hold_steps(20) == 20


def test_gripper_positive_opens_negative_closes(shared_envs):
    """docs/panda_play.md: gripper action > 0 opens, < 0 closes; 0 keeps the last command."""
    env = shared_envs[("panda-play", "grasp")]
    obs, _ = env.reset(seed=0)
    for command, check in ((-1.0, lambda f: f < 0.1), (0.0, lambda f: f < 0.1), (1.0, lambda f: f > 0.95)):
        for _ in range(10):
            obs, *_ = env.step(np.array([0.0, 0.0, 0.0, command]))
        assert check(obs[6]) and check(obs[7]), (command, obs[6:8])
    from shiftkit.envs.panda_play.tasks import close_gripper, open_gripper

    facts = replace(env.facts(), tcp=env.facts().blocks[0] + [0.0, 0.0, 0.05])  # near a block, still
    assert open_gripper(replace(facts, gripper_action=1.0)) and not open_gripper(replace(facts, gripper_action=-1.0))
    assert close_gripper(replace(facts, gripper_action=-1.0)) and not close_gripper(replace(facts, gripper_action=1.0))


@pytest.mark.parametrize("control_hz", [20, 5])
def test_step_simulates_exactly_like_mj_step(control_hz):
    """The first substep of a control step reuses the position/velocity stages computed at the end
    of the previous step; the result must be bitwise what plain mj_step gives."""
    physics = PandaPlayPhysics(control_hz)
    physics.reset(np.random.default_rng(0))
    model, data = physics.model, physics.data
    replay = mujoco.MjData(model)
    rng = np.random.default_rng(1)
    for _ in range(4):
        mujoco.mj_copyData(replay, model, data)
        physics.step(rng.uniform(-1, 1, 4))
        if control_hz == 20:  # one controller tick: the controls now in data are the ones used
            replay.ctrl[:] = data.ctrl
            mujoco.mj_step(model, replay, nstep=physics.n_substeps)
            assert np.array_equal(replay.qpos, data.qpos) and np.array_equal(replay.qvel, data.qvel)
    # and the state returned is fully forwarded (kinematics match the new qpos)
    site = physics.tcp_site
    before = data.site_xpos[site].copy()
    mujoco.mj_forward(model, data)
    assert np.array_equal(before, data.site_xpos[site])


def test_5hz_action_is_held_over_the_control_period():
    """At 5 Hz the desired TCP advances every 50 ms tick (as the reference advances it every
    substep), so the arm is still moving at full speed at the end of a step."""
    physics = PandaPlayPhysics(5)
    physics.reset(np.random.default_rng(0))
    start = physics.desired_tcp.copy()
    direction = np.sign(0.5 - start[1])  # towards the tray centre line: clear of the bounds
    physics.step(np.array([0.0, direction, 0.0, 1.0]))
    assert physics.desired_tcp[1] - start[1] == pytest.approx(direction * 0.04)
    assert direction * physics.tcp_velocity()[1] > 0.12  # 0.2 m/s commanded (one 4 cm jump: 0.07)


def test_render_shapes(shared_envs):
    env = envs.make("panda-play", "reach", render_mode="rgb_array", width=64, height=48)
    env.reset(seed=0)
    rgb = env.render()
    assert rgb.shape == (48, 64, 3) and rgb.dtype == np.uint8 and rgb.std() > 5
    depth = env.render_depth()
    assert depth.shape == (48, 64) and depth.dtype == np.float32
    assert 0.3 < float(np.median(depth)) < 2.0  # metres from the front camera to the scene
    full = envs.make("panda-play", "reach", width=32, height=24, render_quality="full")
    full.reset(seed=0)
    assert full.render_rgb("overhead").shape == (24, 32, 3)
    env.close()
    full.close()


def test_unknown_names_raise():
    with pytest.raises(ValueError, match="unknown task"):
        envs.make("panda-play", "fly")
    with pytest.raises(ValueError, match="unknown env"):
        envs.make("kitchen", "lift")


NEW_FAMILY = '''"""A family a test adds as a new folder: Panda play's scene and expert under another name."""

from dataclasses import replace

from shiftkit.envs import panda_play
from shiftkit.envs.family import register_family

FAMILY = register_family(replace(panda_play.FAMILY, name="toy-play", gym_prefix="ToyPlay"))
'''


def test_a_new_family_folder_is_discovered(tmp_path, monkeypatch):
    """Adding an env family is one new folder under envs/: discovery registers it with its gymnasium
    ids, and what the rest of shiftkit asks of a family (make, the expert as a policy) comes from
    its registration."""
    import sys

    from shiftkit.envs.family import FAMILIES

    (tmp_path / "toy_play").mkdir()
    (tmp_path / "toy_play" / "__init__.py").write_text(NEW_FAMILY)
    assert "panda-play" in FAMILIES  # discovered
    monkeypatch.setattr(FAMILIES, "_items", dict(FAMILIES._items))
    monkeypatch.setattr(FAMILIES, "_discovered", False)
    monkeypatch.setattr(envs, "__path__", [*envs.__path__, str(tmp_path)])
    family = envs.env_family("toy-play")  # the registry's discovery imports the new folder too
    try:
        assert envs.gym_id("toy-play", "lift") in gym.registry
        env = envs.make("toy-play", "lift")
        env.reset(seed=0)
        assert family.expert_policy(env).act(None).shape == env.action_space.shape
        env.close()
    finally:
        sys.modules.pop("shiftkit.envs.toy_play", None)
        for task in family.tasks:
            gym.registry.pop(family.gym_id(task), None)
    with pytest.raises(ValueError, match=r"unknown env 'toy-pl' \(known: .*toy-play"):
        envs.env_family("toy-pl")
