"""Door + tactile finger: reset distribution, impedance control, the simulated STS and its marker
wrench estimate, the experts (fast: one short episode each)."""

from __future__ import annotations

import numpy as np
import pytest

import shiftkit.envs as envs
from shiftkit.envs.door_tactile.env import DoorTactileEnv
from shiftkit.envs.door_tactile.experts import rollout
from shiftkit.envs.door_tactile.physics import STIFFNESS
from shiftkit.envs.door_tactile.tasks import START_HALF, START_OFFSET_ALONG_NORMAL, START_OFFSET_BACK, START_YAW
from shiftkit.envs.geometry import rotation_vector
from shiftkit.envs.sts import PadContacts
from shiftkit.envs.tactile_estimation import MarkerWrenchEstimator, detect_markers


@pytest.fixture(scope="module")
def env_open():
    env = envs.make("door-tactile", "flat-handle-open")
    yield env
    env.close()


@pytest.mark.parametrize("task", ["flat-handle-open", "knob-close"])
def test_reset_distribution(task):
    """Sensor start in a 3 cm cube around the nominal pose with yaw within +-0.15 rad; door closed
    for open tasks, open (above the spring zone) for close tasks; no contact at the start."""
    env = envs.make("door-tactile", task)
    offsets, yaws = [], []
    for seed in range(8):
        obs, info = env.reset(seed=seed)
        p = env.physics
        angle = p.door_angle()
        if env.task.opening:
            assert angle == pytest.approx(0.0, abs=1e-9)
        else:
            assert 0.85 <= angle <= 0.95
        pos, rot = p.grasp_pose(angle)
        nominal = pos + rot[:, 2] * START_OFFSET_ALONG_NORMAL + p.door_outward(angle) * START_OFFSET_BACK
        offsets.append(p.ee_pos() - nominal)
        turn = rotation_vector(p.ee_rot() @ rot.T)
        assert np.abs(turn[:2]).max() < 1e-3  # only a yaw about world z
        yaws.append(turn[2])
        assert not info["handle_contact"] and np.allclose(obs[:7], [0, 0, 0, 0, 0, 0, 1])
        assert obs[18] == 0.0  # the STS starts in visual mode
    offsets = np.array(offsets)
    assert np.abs(offsets).max() <= START_HALF + 2e-4 and np.abs(yaws).max() <= START_YAW + 1e-3
    assert offsets.std(axis=0).min() > 0.003 and np.std(yaws) > 0.03  # really spread, not constant
    env.close()


def test_impedance_holds_pose_and_presses_with_its_stiffness(env_open):
    env = env_open
    env.reset(seed=0)
    p = env.physics
    start = p.ee_pos()
    for _ in range(10):
        env.step(np.zeros(7))
    assert np.linalg.norm(p.ee_pos() - start) < 0.003  # gravity compensated, no drift
    # a target 2 cm behind the handle face: the contact force is about stiffness x remaining depth
    pos, rot = p.grasp_pose()
    p.reset(pos - rot[:, 2] * 0.002, rot, 0.0)
    p.target_pos, p.target_rot = pos + rot[:, 2] * 0.02, rot
    p.simulate(600)
    fz = env.sensor.contact_wrench(p.data)[2]
    depth_left = (p.target_pos - p.ee_pos()) @ rot[:, 2]
    assert fz == pytest.approx(STIFFNESS[0] * depth_left, rel=0.2) and 6.0 < fz < 12.0


def test_relative_actions_move_in_the_sensor_frame(env_open):
    env = env_open
    env.reset(seed=1)
    for _ in range(3):
        obs, *_ = env.step(np.array([1.0, 0, 0, 0, 0, 0, 0]))
    assert obs[0] > 0.01 and abs(obs[1]) < 0.003 and abs(obs[2]) < 0.003  # along the finger
    np.testing.assert_allclose(np.linalg.norm(obs[3:7]), 1.0, atol=1e-5)
    assert obs[7] < obs[0]  # the previous relative pose lags the current one


def test_sts_images_modes_and_raw_wrench(env_open):
    env = env_open
    env.reset(seed=2)
    visual = env.sts_image()
    assert visual.shape == (48, 64, 3) and visual.dtype == np.uint8  # the env's camera size
    obs, *_ = env.step(np.array([0, 0, 0, 0, 0, 0, 1.0]))
    tactile = env.sts_image()
    assert obs[18] == 1.0 and tactile.shape == (48, 64, 3)
    np.testing.assert_array_equal(env.render_rgb("sts"), tactile)  # what evaluation renders
    assert len(detect_markers(tactile)) == len(env.sensor.reference_mm)
    assert np.abs(obs[14:18]).max() < 0.2  # no contact: the estimate stays near zero
    with pytest.raises(ValueError, match="mode"):
        env.sensor.set_mode("infrared")
    # F~: fixed nonlinear gain, seeded noise, same seed -> same readings
    env.sensor.reset(5)
    a = [env.sensor.raw_wrench([1.0, -2.0, 10.0, 0.01]) for _ in range(3)]
    env.sensor.reset(5)
    b = [env.sensor.raw_wrench([1.0, -2.0, 10.0, 0.01]) for _ in range(3)]
    np.testing.assert_array_equal(a, b)
    assert a[0][2] != pytest.approx(10.0, rel=0.1) and a[0][1] < 0 < a[0][0]  # unscaled, signs kept


def test_marker_estimate_follows_the_contact_wrench(env_open):
    sensor = env_open.sensor
    sensor.reset(3)
    none = PadContacts(np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0))
    est = MarkerWrenchEstimator()
    est.reset(sensor.render_markers(sensor.marker_positions(none), none))
    readings = []
    for fx, fy, fz in ((0, 0, 2), (0, 0, 8), (4, 0, 8), (0, -4, 8)):
        c = PadContacts(np.array([[0.002, -0.001]]), np.array([[fx, fy, fz]], float), np.zeros(1))
        readings.append(est.raw(sensor.render_markers(sensor.marker_positions(c), c)))
    r = np.array(readings)
    assert r[1, 2] > r[0, 2] > 0  # pressure spreads the markers: Fz grows with the normal force
    assert r[2, 0] > 0.1 and r[2, 0] > 4 * abs(r[2, 1])  # shear along x moves the markers along x
    assert r[3, 1] < -0.1 and -r[3, 1] > 4 * abs(r[3, 0])


def test_scripted_expert_closes_the_door():
    env = DoorTactileEnv("flat-handle-close")
    r = rollout(env, seed=0, cameras=("wrist",))
    assert r.succeeded and not r.success[0]
    assert r.images["wrist"].shape == (len(r.actions), 48, 64, 3) and r.images["sts"].shape[1:] == (48, 64, 3)
    assert r.actions[:, 6].max() == 1.0 and r.actions[0, 6] == 0.0  # switches to tactile for contact
    assert r.observations[:, 23].max() > 5.0  # pressed on the handle
    extras = env.episode_extras()  # what eval records: the switch and the first observed contact
    assert extras["first_tactile_step"] == int(np.argmax(r.actions[:, 6] > 0.5))
    contact = extras["first_contact_step"]
    assert not r.observations[:contact, 21:25].any() and r.observations[contact, 23] > 0
    env.close()


def test_kinesthetic_dataset_converts_to_lerobot(tmp_path, capsys):
    """`shiftkit collect --kinesthetic` (5 episodes) -> `shiftkit run` with no stages -> a LeRobot
    dataset with STS and wrist images, x_raw and F~_raw that LeRobotDataset loads."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from shiftkit.app.cli import main
    from shiftkit.datasets.sources.raw import open_raw_dataset

    raw, out = tmp_path / "raw", tmp_path / "lerobot"
    args = ["collect", "--env", "door-tactile", "--task", "knob-close", "--kinesthetic", "--episodes", "5"]
    assert main([*args, "--cameras", "wrist,sts", "--out", str(raw)]) == 0
    assert "5 successful" in capsys.readouterr().out
    dataset = open_raw_dataset(raw)
    for i in range(5):
        ep = dataset.read_episode(i)
        meta = ep.meta
        assert meta["kinesthetic"] and abs(meta["mode_switch_step"] - meta["first_contact_step"]) <= 4
        action = ep.frames["action"]
        assert (action[:, 6] == (np.arange(len(action)) >= meta["mode_switch_step"])).all()  # operator label
    config = tmp_path / "p.toml"
    config.write_text(f'[[sources]]\npath = "{raw}"\n[destination]\nroot = "{out}"\nrepo_id = "test/door"\n')
    assert main(["run", str(config), "--no-progress"]) == 0
    ds = LeRobotDataset("test/door", root=out, video_backend="pyav")
    assert ds.num_episodes == 5
    frame = ds[len(ds) - 1]
    assert tuple(frame["observation.images.sts"].shape) == (3, 48, 64)
    assert tuple(frame["observation.images.wrist"].shape) == (3, 48, 64)
    assert tuple(frame["observation.wrench"].shape) == (4,) and tuple(frame["observation.ee_pose"].shape) == (7,)
    assert ds.features["observation.wrench"]["names"] == ["Fx", "Fy", "Fz", "tau_z"]


def test_position_replay_tracks_poses_but_loses_the_force():
    from shiftkit.envs.door_tactile.experts import kinesthetic_rollout, replay_positions

    env = DoorTactileEnv("knob-close")
    demo = kinesthetic_rollout(env, seed=1)
    assert demo.succeeded and demo.arrays["wrench_raw"].shape == (len(demo.actions), 4)
    replay = replay_positions(env, 1, demo.arrays["ee_pose"], demo.actions[:, 6], demo.meta["recording_start_step"])
    assert len(replay.actions) == len(demo.actions) - 1 + 10  # plus the settling steps
    # the replay follows x_raw (within the impedance controller's lag) ...
    env.set_sim_state(replay.qpos[-1], replay.qvel[-1])
    assert np.linalg.norm(env.ee_pose()[:3] - demo.arrays["ee_pose"][-1, :3]) < 0.01
    # ... but presses far less than the demonstration did (F = K (x_d - x) with x_d = x_raw)
    assert replay.observations[:, 23].max() < 0.5 * demo.observations[:, 23].max()
    env.close()


@pytest.mark.parametrize(("label", "mode"), [(0.0, "visual"), (0.3, "visual"), (0.7, "tactile"), (1.0, "tactile")])
def test_sts_mode_action_switches_half_way_between_the_labels(env_open, label, mode):
    """Datasets label the mode 1 (tactile) / 0 (visual): a policy regressing it switches at 0.5."""
    env_open.reset(seed=3)
    env_open.step(np.array([0, 0, 0, 0, 0, 0, label]))
    assert env_open.sensor.mode == mode


@pytest.mark.parametrize("fixed", ["visual", "tactile"])
def test_fixed_sensor_mode_holds_for_the_whole_episode(fixed):
    """The fixed-mode baselines (thesis Fig. 4.13): 6-dim actions without `sts_mode`, the sensor
    in that mode from the reset on whatever replay asks, and the observation showing it."""
    env = envs.make("door-tactile", "flat-handle-open", sensor_mode=fixed, max_episode_seconds=0.5)
    assert env.action_names == ("dx", "dy", "dz", "drx", "dry", "drz") and env.action_space.shape == (6,)
    obs, info = env.reset(seed=0)
    value = float(fixed == "tactile")
    observed = [obs[18]]
    for _ in range(3):
        obs, _, _, _, info = env.step(np.array([0, 0, 0.3, 0, 0, 0]))
        observed.append(obs[18])
        assert env.sensor.mode == info["sts_mode"] == fixed
    other = "visual" if fixed == "tactile" else "tactile"
    env.step_pose(env.physics.ee_pos(), env.physics.ee_rot(), other)  # a fixed mode wins over replay's
    assert env.sensor.mode == fixed and observed == [value] * 4
    if fixed == "visual":
        assert (obs[14:18] == 0).all()  # the markers are dark: no wrench estimate
    assert env.episode_extras() == {
        "sensor_mode": fixed,
        "tactile_steps": 4 * int(fixed == "tactile"),
        "first_tactile_step": 0 if fixed == "tactile" else None,
        "first_contact_step": None,
    }
    with pytest.raises(ValueError, match="action must be 6 finite numbers"):
        env.step(np.zeros(7))  # no mode dim to switch with
    with pytest.raises(ValueError, match="sensor_mode must be one of policy, visual, tactile"):
        envs.make("door-tactile", "flat-handle-open", sensor_mode="both")
    env.close()


@pytest.mark.parametrize(("expert", "fixed"), [("scripted", "visual"), ("kinesthetic", "tactile")])
def test_collect_in_a_fixed_sensor_mode(tmp_path, expert, fixed):
    """`collect --env-kwarg sensor_mode=...` records the fixed-mode env: 6-dim actions named as the
    env names them, every frame in that mode (state and STS image)."""
    from shiftkit.app.collect import CollectConfig, collect
    from shiftkit.datasets.sources.raw import open_raw_dataset

    kwargs = {"sensor_mode": fixed}
    out, _ = collect(
        CollectConfig(
            env="door-tactile",
            task="knob-close",
            episodes=1,
            expert=expert,
            env_kwargs=kwargs,
            out=str(tmp_path / "raw"),
        )
    )
    dataset = open_raw_dataset(out)
    assert dataset.index["names"]["action"] == ["dx", "dy", "dz", "drx", "dry", "drz"]
    ep = dataset.read_episode(0)
    assert ep.frames["action"].shape[1] == 6 and ep.meta["outcome"] == "success"
    state = ep.frames["observation.state"]
    assert (state[:, 18] == float(fixed == "tactile")).all()
    # every STS frame is the fixed mode's image of the recorded state (tactile: up to the marker
    # estimator's low-pass and pixel noise), far from the other mode's
    env = envs.make("door-tactile", "knob-close")
    env.reset(seed=0)
    other = "visual" if fixed == "tactile" else "tactile"
    for t in range(0, len(ep), 5):
        env.set_sim_state(ep.frames["sim.qpos"][t], ep.frames["sim.qvel"][t])
        frame = ep.frames["observation.images.sts"][t].astype(float)
        render = {
            "visual": env.sensor.visual_image(env.physics.data),
            "tactile": env.sensor.tactile_image(env.physics.data),
        }
        assert np.abs(frame - render[fixed]).mean() < 0.3 * np.abs(frame - render[other]).mean()
    env.close()
