"""Force matching: replay poses x_rep = A^-1 (F~ - b) + x_raw in the sensor frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from shiftkit.envs.geometry import matrix_to_quat_xyzw, quat_xyzw_to_matrix
from shiftkit.transforms.force_calibration import WRENCH_AXES, AxisFit, Calibration
from shiftkit.transforms.force_matching import force_matched_poses, median_filter
from tests.helpers import lerobot_train_two_steps


def linear_calibration(offset: float = 0.0) -> Calibration:
    axes = {
        "Fx": AxisFit(offset, [100.0], clip=0.02),
        "Fy": AxisFit(offset, [-100.0], clip=0.02),
        "Fz": AxisFit(offset, [200.0, 400.0], [0.005], clip=0.026),
        "tau_z": AxisFit(offset, [2.0], clip=1.0),
    }
    return Calibration("test", axes)


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1
    return np.concatenate([rng.uniform(-0.5, 0.5, (n, 3)), q], axis=1)


def test_median_filter_removes_spikes_and_keeps_steps():
    x = np.zeros((9, 2))
    x[4, 0] = 10.0  # a one-frame spike
    x[6:, 1] = 1.0  # a step
    out = median_filter(x, 3)
    assert out[:, 0].tolist() == [0.0] * 9
    assert out[:, 1].tolist() == x[:, 1].tolist()
    assert median_filter(x, 1).tolist() == x.tolist()


def test_quaternion_round_trip():
    poses = random_poses(20)
    assert matrix_to_quat_xyzw(quat_xyzw_to_matrix(poses[:, 3:])) == pytest.approx(poses[:, 3:], abs=1e-12)


def test_zero_force_is_position_replay():
    poses = random_poses(12)
    assert np.array_equal(force_matched_poses(poses, np.zeros((12, 4)), linear_calibration(), 5), poses)
    rep = force_matched_poses(poses, np.full((12, 4), 0.3), linear_calibration(offset=0.3), 5)
    assert np.array_equal(rep, poses)


def test_offsets_in_the_sensor_frame():
    poses = random_poses(6, seed=3)
    rot = quat_xyzw_to_matrix(poses[:, 3:])
    wrench = np.tile([1.0, 0.5, 2.0, 0.2], (6, 1))  # constant: the median filter keeps it
    rep = force_matched_poses(poses, wrench, linear_calibration(), 3)
    # Fx / 100, Fy / -100, Fz past the 5 mm breakpoint on the second slope, tau_z / 2
    e = np.array([0.01, -0.005, 0.005 + (2.0 - 200.0 * 0.005) / 400.0, 0.1])
    assert rep[:, :3] == pytest.approx(poses[:, :3] + np.einsum("tij,j->ti", rot, e[:3]), abs=1e-12)
    turn = quat_xyzw_to_matrix(rep[:, 3:]) @ np.transpose(rot, (0, 2, 1))  # world-frame rotation R_rep R^T
    local = np.transpose(rot, (0, 2, 1)) @ turn @ rot  # in the sensor frame: about z by erz
    angle = np.arctan2(local[:, 1, 0], local[:, 0, 0])
    assert angle == pytest.approx(np.full(6, 0.1), abs=1e-12)
    assert local[:, 2, 2] == pytest.approx(np.ones(6), abs=1e-12)


def test_offsets_are_clipped():
    poses = random_poses(3)
    rep = force_matched_poses(poses, np.tile([0.0, 0.0, 1e6, 0.0], (3, 1)), linear_calibration(), 1)
    assert np.linalg.norm(rep[:, :3] - poses[:, :3], axis=1) == pytest.approx(np.full(3, 0.026))


# ----------------------------------------------------------------------------- in the simulator
SENSOR = "door-tactile-v1:sts"


@pytest.fixture(scope="module")
def kinesthetic(tmp_path_factory):
    """Two simulated kinesthetic demonstrations (flat handle) with wrist and STS images."""
    from shiftkit.app.collect import CollectConfig, collect

    out = tmp_path_factory.mktemp("kin") / "raw"
    collect(CollectConfig(env="door-tactile", task="flat-handle-open", episodes=2, expert="kinesthetic", out=str(out)))
    return out


@pytest.fixture(scope="module")
def calibration_file(tmp_path_factory):
    """A calibration of the simulated sensor from one push of each kind."""
    from shiftkit.transforms.force_calibration import calibrate_env

    cal, _, _ = calibrate_env("door-tactile", "knob-open", [0], [])
    return cal.save(tmp_path_factory.mktemp("cal") / "calib.json")


def stage(features, **params):
    from shiftkit.pipelines.stage import StageContext, build_stage

    s = build_stage("force_match", params, StageContext(fps=10), "test")
    s.transform_features(features)
    s.setup()
    return s


def episodes(raw):
    from shiftkit.datasets.sources.raw import open_raw_dataset

    ds = open_raw_dataset(raw)
    return ds.features(), list(ds.iter_episodes())


def replayed(s, episode):
    out = list(s.process(episode, np.random.default_rng(0)))
    return out[0] if out else None


def test_position_mode_is_the_family_position_replay(kinesthetic):
    from shiftkit.envs.door_tactile.experts import replay_positions

    features, (ep, _) = episodes(kinesthetic)
    s = stage(features, mode="position", hold_steps=0, sts_images=False)
    out = replayed(s, ep)
    n = len(ep)
    assert len(out) == n and out.meta["replay_mode"] == "position"
    env = s._env("flat-handle-open", (48, 64, 3))
    ref = replay_positions(
        env,
        ep.meta["seed"],
        ep.frames["observation.ee_pose"],
        ep.frames["action"][:, -1],
        ep.meta["recording_start_step"],
        settle_steps=0,  # the stage holds the last pose only with `hold_steps`, 0 here
    )
    # the same physics (to rounding): poses, door and contact state, actions; the sensor's noise
    # stream differs, since this stage also draws the raw reading of every replayed frame
    close = dict(rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(out.frames["observation.state"][: n - 1, :14], ref.observations[:, :14], **close)
    np.testing.assert_allclose(out.frames["observation.environment_state"][: n - 1], ref.observations[:, 19:], **close)
    np.testing.assert_allclose(out.frames["action"][: n - 1], ref.actions, **close)


def test_zero_force_is_exactly_position_replay(kinesthetic, tmp_path):
    features, (ep, _) = episodes(kinesthetic)
    Calibration(SENSOR, linear_calibration().axes).save(tmp_path / "zero.json")
    zero = ep.with_frames(**{"observation.wrench": np.zeros_like(ep.frames["observation.wrench"])})
    fm = replayed(stage(features, calibration=str(tmp_path / "zero.json"), axes=list(WRENCH_AXES)), zero)
    pos = replayed(stage(features, mode="position"), zero)
    assert fm.frames.keys() == pos.frames.keys()
    for key in fm.frames:
        assert np.array_equal(fm.frames[key], pos.frames[key]), key
    assert "observation.images.sts_visual" in fm.frames and "observation.images.sts" not in fm.frames


def test_force_matching_restores_the_demonstrated_press(kinesthetic, calibration_file):
    """Position replay loses the contact force; force-matched replay presses as the person did."""
    features, eps = episodes(kinesthetic)
    fm_stage = stage(features, calibration=str(calibration_file), sts_images=False, slowdown=2)
    pos_stage = stage(features, mode="position", sts_images=False, slowdown=2)
    for ep in eps:
        demo = ep.frames["observation.environment_state"][:, 4]  # true normal force on the pad
        touching = np.flatnonzero(demo > 1.0)
        fm = replayed(fm_stage, ep).frames["observation.environment_state"][::2, 4][touching]
        pos = replayed(pos_stage, ep).frames["observation.environment_state"][::2, 4][touching]
        assert np.median(fm) == pytest.approx(np.median(demo[touching]), rel=0.3)
        assert np.median(pos) < 0.3 * np.median(demo[touching])


def test_drop_failed_and_outcome(kinesthetic):
    features, (ep, _) = episodes(kinesthetic)
    keeping = stage(features, mode="position", sts_images=False)
    kept = replayed(keeping, ep)
    assert kept.meta["replay_success"] is False and kept.meta["outcome"] == "failure"
    assert keeping.take_report() == {"replays_failed": 1, "episodes_dropped": 0}
    dropping = stage(features, mode="position", sts_images=False, drop_failed=True)
    assert replayed(dropping, ep) is None
    assert dropping.take_report() == {"replays_failed": 1, "episodes_dropped": 1}  # run summary, provenance


def test_bad_inputs_are_one_line_errors(kinesthetic, synthetic_raw, tmp_path):
    from shiftkit.datasets.errors import ConfigError, DatasetError

    features, (ep, _) = episodes(kinesthetic)
    linear_calibration().save(tmp_path / "other.json")  # sensor "test"
    for params, message in [
        ({"calibration": str(tmp_path / "other.json")}, "is for sensor 'test', not 'door-tactile-v1:sts'"),
        ({}, 'mode "force_matched" needs a calibration file'),
        ({"mode": "position", "axes": ["Fq"]}, "unknown wrench axes"),
        ({"mode": "position", "env": "nope"}, "unknown env 'nope'"),
    ]:
        with pytest.raises(ConfigError, match=message):
            stage(features, **params)
    with pytest.raises(ConfigError, match="needs the kinesthetic recording's 'observation.ee_pose'"):
        stage(episodes(synthetic_raw)[0], mode="position")
    s = stage(features, mode="position", sts_images=False)
    with pytest.raises(DatasetError, match="no simulator 'seed'"):
        replayed(s, type(ep)(ep.frames, {**ep.meta, "seed": None}))
    wide = {**features, "action": {**features["action"], "shape": (4,)}}
    with pytest.raises(ConfigError, match=r"'action' has 4 dims, not door-tactile's \('dx'"):
        stage(wide, mode="position")


def test_a_fixed_mode_recording_replays_without_the_mode_dim(tmp_path):
    """A demonstration recorded with `sensor_mode=visual` (6-dim actions, no wrist camera) replays
    into 6-dim actions at the recording's STS image size."""
    from shiftkit.app.collect import CollectConfig, collect

    out, _ = collect(
        CollectConfig(
            env="door-tactile",
            task="knob-close",
            episodes=1,
            expert="kinesthetic",
            env_kwargs={"sensor_mode": "visual", "max_episode_seconds": 1.5},
            width=32,
            height=24,
            out=str(tmp_path / "raw"),
        )
    )
    features, (ep,) = episodes(out)
    assert features["action"]["shape"] == (6,)
    replay = replayed(stage(features, mode="position"), ep)
    assert replay.frames["action"].shape == (len(ep) + 10, 6)
    assert replay.frames["observation.images.sts_visual"].shape[1:] == (24, 32, 3)


REPO = Path(__file__).resolve().parents[1]


CALIBRATION = REPO / "docs" / "force_matching_calibration.json"


def docs_pipeline(name: str, raw: Path, out: Path, config: Path, calibration: Path = CALIBRATION) -> Path:
    """docs/pipelines/NAME.toml written to `config`, reading `raw` and writing `out`."""
    text = (REPO / "docs" / "pipelines" / f"{name}.toml").read_text()
    text = text.replace("../../data/door_kinesthetic", str(raw)).replace(f"../../out/door_{name}", str(out))
    text = text.replace("docs/force_matching_calibration.json", str(calibration))
    config.write_text(text)
    return config


@pytest.mark.parametrize("fixed", ["visual", "tactile"])
def test_docs_fixed_mode_pipelines_plan_the_baseline_datasets(kinesthetic, tmp_path, fixed):
    """docs/pipelines/force_matched_{visual,tactile}.toml: force-matched replay, one STS image, a
    6-dim action without sts_mode (the env's action in that fixed sensor mode)."""
    from shiftkit.envs import make
    from shiftkit.pipelines.config import load_pipeline_config
    from shiftkit.pipelines.planner import plan_pipeline

    name = f"force_matched_{fixed}"
    plan = plan_pipeline(load_pipeline_config(docs_pipeline(name, kinesthetic, tmp_path / "out", tmp_path / "p.toml")))
    env = make("door-tactile", "flat-handle-open", sensor_mode=fixed)
    assert plan.features["action"]["names"] == list(env.action_names)
    assert "observation.images.sts" in plan.features and "observation.images.sts_visual" not in plan.features
    env.close()


@pytest.mark.slow
def test_docs_pipelines_run_with_two_workers_and_train_act(kinesthetic, tmp_path):
    """docs/pipelines/{force_matched,position_replay}.toml run with 2 workers; the outputs load in
    LeRobotDataset (action with `sts_mode`, one STS image) and lerobot-train (ACT) trains 2 steps."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from shiftkit.app.cli import main

    roots = {}
    for name in ("force_matched", "position_replay"):
        config = docs_pipeline(name, kinesthetic, tmp_path / name, tmp_path / f"{name}.toml")
        assert main(["run", str(config), "--workers", "2", "--no-progress"]) == 0
        ds = LeRobotDataset(f"local/door_{name}", root=tmp_path / name)
        assert ds.meta.total_episodes == 2
        assert ds.features["action"]["names"][-1] == "sts_mode"
        assert "observation.images.sts" in ds.features and "observation.images.sts_visual" not in ds.features
        roots[name] = tmp_path / name
    lerobot_train_two_steps("local/door_force_matched", roots["force_matched"], tmp_path / "train")


def test_damping_feed_forward_moves_targets_along_the_velocity(tmp_path):
    from shiftkit.datasets.episode import Episode

    Calibration(SENSOR, linear_calibration().axes).save(tmp_path / "zero.json")
    poses = random_poses(1)[[0] * 6]
    poses[:, 0] += 0.01 * np.arange(6)  # 1 cm per frame along x: 0.1 m/s at 10 fps
    actions = np.zeros((6, 7), np.float32)
    ep = Episode(
        {
            "observation.ee_pose": poses,
            "observation.wrench": np.zeros((6, 4)),
            "action": actions,
            "timestamp": np.arange(6) / 10.0,
            "task": np.array(["flat-handle-open"] * 6),
        }
    )
    features = {
        "observation.ee_pose": {"dtype": "float64", "shape": (7,)},
        "observation.wrench": {"dtype": "float64", "shape": (4,)},
        "action": {"dtype": "float32", "shape": (7,)},
    }
    plain = stage(features, calibration=str(tmp_path / "zero.json")).targets(ep)
    fed = stage(features, calibration=str(tmp_path / "zero.json"), damping_time=0.15).targets(ep)
    assert np.array_equal(plain[:6], poses)  # zero force: the recorded poses (+ the closing pose)
    # 0.15 s x 0.1 m/s (the last recorded frame's velocity sees the still closing pose)
    assert fed[:5, :3] - plain[:5, :3] == pytest.approx(np.tile([0.015, 0.0, 0.0], (5, 1)), abs=1e-12)
    assert np.array_equal(fed[:, 3:], plain[:, 3:])


@pytest.mark.slow
def test_docs_pipelines_resume_after_sigkill(tmp_path, caplog):
    """SIGKILL of `shiftkit run --workers 2` (its whole process group) once some episodes are
    replayed: the re-run resumes them and writes the uninterrupted run's bytes, for both docs
    pipelines; a calibration re-made before the re-run discards the interrupted work (nothing stale
    is mixed in)."""
    import json
    import shutil

    from shiftkit.app.cli import main
    from shiftkit.pipelines.config import load_pipeline_config
    from shiftkit.pipelines.runner import run_pipeline
    from shiftkit.pipelines.work import work_dir_for
    from tests.helpers import dataset_bytes, finished_parts, shiftkit_process, sigkill_when, survivors

    raw, episodes = tmp_path / "raw", 4
    collect = ["collect", "--env", "door-tactile", "--task", "flat-handle-open", "--expert", "kinesthetic"]
    tiny = ["--width", "32", "--height", "24", "--env-kwarg", "max_episode_seconds=2", "--no-progress"]
    assert main([*collect, "--episodes", str(episodes), "--cameras", "wrist", *tiny, "--out", str(raw)]) == 0
    calibration = Path(shutil.copy(CALIBRATION, tmp_path / "calib.json"))

    def run(name: str, dest: Path, kill: bool = False) -> str:
        """Run (in this process) or start and SIGKILL a run; returns the resume line if any."""
        config = docs_pipeline(name, raw, dest, tmp_path / f"{dest.name}.toml", calibration)
        if kill:
            proc = shiftkit_process("run", str(config), "--no-progress", "--workers", "2", cwd=tmp_path)
            workers = sigkill_when(proc, lambda: finished_parts(dest) >= 1, group=True)
            assert workers is not None, f"{name}: the run ended before it could be killed"
            assert not survivors(workers) and not dest.exists()
            assert 1 <= finished_parts(dest) < episodes
            return ""
        caplog.clear()
        run_pipeline(load_pipeline_config(config), progress=False)  # any worker count gives the same bytes
        assert not work_dir_for(dest).exists()
        return next((r.getMessage() for r in caplog.records if r.getMessage().startswith("resuming")), "")

    for name in ("force_matched", "position_replay"):
        run(name, tmp_path / f"clean_{name}")
        run(name, tmp_path / name, kill=True)
        done = finished_parts(tmp_path / name)
        assert run(name, tmp_path / name) == f"resuming: {done} of {episodes} source episodes were already transformed"
        assert dataset_bytes(tmp_path / name) == dataset_bytes(tmp_path / f"clean_{name}"), f"{name}: resumed differs"

    # interrupted, then the calibration is re-made at the same path: the old parts are not reused
    run("force_matched", tmp_path / "recalibrated", kill=True)
    fit = json.loads(calibration.read_text())
    fit["axes"]["Fz"]["slopes"] = [1.2 * k for k in fit["axes"]["Fz"]["slopes"]]
    calibration.write_text(json.dumps(fit))
    assert run("force_matched", tmp_path / "recalibrated") == ""
    run("force_matched", tmp_path / "clean_recalibrated")
    assert dataset_bytes(tmp_path / "recalibrated") == dataset_bytes(tmp_path / "clean_recalibrated")
    assert dataset_bytes(tmp_path / "recalibrated") != dataset_bytes(tmp_path / "clean_force_matched")


# ----------------------------------------------------------------------------- replay plans for a robot
def run_stages(source: Path, dest: Path, *stages: tuple[str, dict]) -> Path:
    from shiftkit.datasets.sources import SourceConfig
    from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, StageSpec
    from shiftkit.pipelines.runner import run_pipeline

    stages_ = [StageSpec(name=n, params=p) for n, p in stages]
    config = PipelineConfig([SourceConfig(path=str(source))], DestinationConfig(root=str(dest)), stages_, seed=0)
    run_pipeline(config, progress=False)
    return dest


@pytest.fixture(scope="module")
def four_demos(tmp_path_factory):
    """Four short kinesthetic door demonstrations (2 s, small images, wrist camera)."""
    from shiftkit.app.collect import CollectConfig, collect

    out = tmp_path_factory.mktemp("four") / "raw"
    config = CollectConfig(
        env="door-tactile",
        task="flat-handle-open",
        episodes=4,
        expert="kinesthetic",
        cameras=("wrist",),
        width=32,
        height=24,
        env_kwargs={"max_episode_seconds": 2.0},
        out=str(out),
    )
    collect(config)
    return out


def test_replay_plan_executed_by_the_robot_joins_into_the_simulated_replay(four_demos, tmp_path, capsys):
    """force_match execute="plan" -> the door-tactile robot executes and records it -> replay_join
    gives the in-simulator force_match output: the same features, episodes and frames (to 1e-6,
    float32 rounding of the action; the simulated robot runs the same physics, so in practice
    exactly), the same replay outcome and first contact."""
    from shiftkit.app.cli import main
    from shiftkit.datasets.reader import open_lerobot_dataset

    fm = {"calibration": str(CALIBRATION), "slowdown": 2, "damping_time": 0.25}
    sim = run_stages(four_demos, tmp_path / "sim", ("force_match", fm))
    plan = run_stages(four_demos, tmp_path / "plan", ("force_match", {**fm, "execute": "plan"}))
    reader = open_lerobot_dataset(plan)
    assert set(reader.features) == {"action"}
    assert reader.features["action"]["names"] == ["x", "y", "z", "qx", "qy", "qz", "qw", "sts_mode"]
    first = next(reader.iter_episodes([0]))
    assert first.meta["replay_plan"]["warmup_steps"] == first.meta["recording_start_step"]
    assert set(np.unique(first.frames["action"][:, 7])) == {0.0, 1.0}  # the operator's mode switch
    assert main(["sim-robot", str(plan), "--out", str(tmp_path / "rec")]) == 0
    assert "4 episodes" in capsys.readouterr().out
    joined = run_stages(tmp_path / "rec", tmp_path / "joined", ("replay_join", {}))
    a, b = open_lerobot_dataset(sim), open_lerobot_dataset(joined)
    assert a.features == b.features and a.num_episodes == b.num_episodes == 4
    demos = episodes(four_demos)[1]
    for demo, ea, eb in zip(demos, a.iter_episodes([0, 1, 2, 3]), b.iter_episodes([0, 1, 2, 3]), strict=True):
        assert sorted(ea.frames) == sorted(eb.frames)
        assert len(ea) == len(eb) == 2 * len(demo) + 10  # slowdown 2, 10 hold steps
        for key in ea.frames:
            if key == "task":
                assert list(ea.frames[key]) == list(eb.frames[key])
            else:
                np.testing.assert_allclose(eb.frames[key], ea.frames[key], atol=1e-6, err_msg=key)
        for key in ("outcome", "replay_success", "first_contact_step", "mode_switch_step", "seed"):
            assert ea.meta[key] == eb.meta[key], key


def test_bad_replay_plans_and_recordings_are_one_line_errors(four_demos, tmp_path, capsys):
    from shiftkit.app.cli import main
    from shiftkit.datasets.errors import ConfigError, DatasetError
    from shiftkit.datasets.sources.raw import RawDatasetWriter
    from shiftkit.pipelines.stage import StageContext, build_stage

    demos = run_stages(four_demos, tmp_path / "demos")  # a LeRobot dataset that is no plan
    assert main(["sim-robot", str(demos), "--out", str(tmp_path / "rec")]) == 2
    err = capsys.readouterr().err
    assert "not a replay plan ('action' must be x, y, z" in err and err.count("\n") == 1
    assert not (tmp_path / "rec").exists()
    features, (ep, *_) = episodes(four_demos)
    join = build_stage("replay_join", {}, StageContext(fps=10), "test")
    with pytest.raises(ConfigError, match="'action' must be the replay plan's sent target"):
        join.transform_features(features)
    with pytest.raises(ConfigError, match='drop_failed needs execute = "sim"'):
        stage(features, mode="position", execute="plan", drop_failed=True)
    # a recording whose measured pose holds a NaN (raw files are checked on read; a LeRobot one here)
    sent = np.tile([0.5, 0.0, 0.4, 0.0, 0.0, 0.0, 1.0, 1.0], (3, 1))
    pose = sent[:, :7].copy()
    pose[1, 0] = np.nan
    recording = {"observation.ee_pose": {"dtype": "float64", "shape": (7,)}, "action": {"shape": (8,)}}
    join.transform_features(recording)
    bad = type(ep)({"action": sent, "observation.ee_pose": pose}, {"source_episode_index": 3})
    with pytest.raises(DatasetError, match="episode 3: 'observation.ee_pose' contains NaN"):
        list(join.process(bad, np.random.default_rng(0)))
    with RawDatasetWriter(tmp_path / "nopose", fps=10, names={"action": list("xyzabcdm")}) as writer:
        writer.add_episode({"timestamp": np.arange(3) / 10, "action": sent}, meta={"task": "t"})
    with pytest.raises(ConfigError, match="needs the measured sensor pose 'observation.ee_pose'"):
        run_stages(tmp_path / "nopose", tmp_path / "j", ("replay_join", {}))
