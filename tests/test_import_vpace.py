"""`shiftkit import vpace`: the published VPACE/LfGP expert buffers become LeRobot datasets (example
sets as one-frame episodes per task, trajectories split into episodes) that LeRobotDataset loads."""

from __future__ import annotations

import gzip
import hashlib
import json
import pickle
from pathlib import Path

import numpy as np
import pytest

from shiftkit.app.cli import main
from shiftkit.app.importers.vpace import (
    ReferenceName,
    parse_reference_name,
    read_vpace_buffer,
    task_from_filename,
)
from shiftkit.app.importing import import_dataset
from shiftkit.datasets.episode import META_COLUMN
from shiftkit.datasets.errors import DatasetError, ShiftkitError
from shiftkit.datasets.reader import open_lerobot_dataset

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "vpace"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"published VPACE data not found at {DATA}")
TRAJECTORY_FILES = ("full_trajectories_2_stack.gz", "full_trajectories_3_lift.gz", "full_trajectories_4_reach.gz")
# Episode lengths after circular-buffer reordering, measured on the published files.
EXPECTED_LENGTHS = {
    "stack": [7, 12, 12, 11, 11, 11, 13, 11, 11, 12, 12, 12, 31, 11, 12, 11],
    "lift": [8, 9, 9, 19, 18, 10, 9, 9, 11, 9, 10, 8, 19, 9, 14, 12, 9, 8],
    "reach": [5, 10, 9, 15, 9, 10, 12, 6, 10, 9, 10, 9, 15, 7, 8, 7, 15, 8, 8, 7, 11],
}


def _raw(path):
    """The file as stored, rows put back in insertion order (independent of the importer)."""
    with gzip.open(path) as f:
        d = pickle.load(f)
    if d["count"] > d["memory_size"]:
        d = {k: np.roll(d[k], -d["pointer"], axis=0) if isinstance(d[k], np.ndarray) else d[k] for k in d}
    return d


def _full_observation(ep):
    """Reference layout back from the dataset split: state[:12] + environment_state + state[12:]."""
    s, e = ep.frames["observation.state"], ep.frames["observation.environment_state"]
    return np.concatenate([s[:, :12], e, s[:, 12:]], axis=1)


def _write_buffer(path, obs, next_obs, actions, rewards, pointer, count):
    size = len(obs)
    data = {
        "observations": obs,
        "next_observations": next_obs,
        "actions": actions,
        "rewards": rewards,
        "dones": np.zeros((size, 1), bool),
        "memory_size": size,
        "pointer": pointer,
        "count": count,
    }
    with gzip.open(path, "wb") as f:
        pickle.dump(data, f)
    return path


@needs_data
def test_published_example_sets(tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from shiftkit.envs.panda_play.physics import ENVIRONMENT_STATE_INDICES, OBSERVATION_NAMES, STATE_INDICES

    # Writing is ~10 ms per one-frame episode: the test writes the lift set (+ 10 reach rows) and reads
    # the full reach file; `shiftkit import vpace` of both files gives 2400 examples (see the docs).
    reach = read_vpace_buffer(DATA / "examples_1200_4_reach.gz")
    assert (reach.task, reach.kind(), len(reach.observations), reach.obs_dim) == ("reach", "examples", 1200, 59)
    files = [DATA / "examples_1200_3_lift.gz", tmp_path / "10_reach.gz"]
    raw_reach = _raw(DATA / "examples_1200_4_reach.gz")
    _write_buffer(
        files[1],
        *(raw_reach[k][:10] for k in ("observations", "next_observations", "actions", "rewards")),
        pointer=0,
        count=10,
    )
    dataset = import_dataset("vpace", {"files": [str(f) for f in files]}, "vpace/examples", tmp_path / "ex")
    kind = dataset.provenance["sources"][0]["importer"]["kind"]
    assert (kind, dataset.num_episodes, dataset.info["total_frames"], dataset.fps) == ("examples", 1210, 1210, 20)

    ds = LeRobotDataset("vpace/examples", root=tmp_path / "ex")
    assert ds.num_episodes == 1210 and len(ds) == 1210
    counts = np.bincount(np.asarray(ds.hf_dataset["task_index"]).reshape(-1))
    assert {t: int(counts[i]) for t, i in ds.meta.tasks["task_index"].items()} == {"lift": 1200, "reach": 10}
    assert ds.features["observation.state"]["names"] == [OBSERVATION_NAMES[i] for i in STATE_INDICES]
    assert ds.features["observation.environment_state"]["names"] == [
        OBSERVATION_NAMES[i] for i in ENVIRONMENT_STATE_INDICES
    ]
    assert "action" not in ds.features, "actions of independent success states are not meaningful"

    table = ds.hf_dataset.with_format("numpy")
    state, env_state = np.asarray(table["observation.state"]), np.asarray(table["observation.environment_state"])
    full = np.concatenate([state[:, :12], env_state, state[:, 12:]], axis=1)
    np.testing.assert_array_equal(full, np.concatenate([_raw(f)["observations"][:, :59] for f in files]))
    assert np.all(np.asarray(table["episode_index"]) == np.arange(1210))
    reader = open_lerobot_dataset(tmp_path / "ex")
    assert json.loads(reader.episodes.iloc[1201][META_COLUMN])["source"] == {"file": "10_reach.gz", "rows": [1, 2]}

    provenance = json.loads((tmp_path / "ex" / "meta" / "shiftkit_provenance.json").read_text())
    (source,) = provenance["sources"]
    assert [f["sha256"] for f in source["files"]] == [hashlib.sha256(f.read_bytes()).hexdigest() for f in files]
    assert source["files"][0]["path"] == str(files[0].resolve())
    assert source["importer"]["kind"] == "examples"

    # The VPACE trainer reads the example set back in the env's observation order, by dimension name.
    from shiftkit.policies.trainers.vpace.example_buffer import load_dataset_examples

    examples, _ = load_dataset_examples([str(tmp_path / "ex")], ["reach"], observation_names=list(OBSERVATION_NAMES))
    np.testing.assert_array_equal(examples["reach"].obs, raw_reach["observations"][:10, :59])


@needs_data
def test_published_trajectories_split_into_episodes(tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    files = [str(DATA / f) for f in TRAJECTORY_FILES]
    dataset = import_dataset("vpace", {"files": files}, "vpace/trajectories", tmp_path / "tr")
    (source,) = dataset.provenance["sources"]
    assert {f["task"]: f["lengths"] for f in source["files"]} == EXPECTED_LENGTHS
    counts = (source["importer"]["kind"], dataset.num_episodes, dataset.info["total_frames"], dataset.fps)
    assert counts == ("trajectories", 55, 600, 5)

    ds = LeRobotDataset("vpace/trajectories", root=tmp_path / "tr")
    assert ds.num_episodes == 55 and len(ds) == 600 and ds.fps == 5
    assert len(ds.features["observation.state"]["names"]) == 12  # VPACE-era: no force-torque dims

    episodes = list(open_lerobot_dataset(tmp_path / "tr").iter_episodes())
    start = 0
    for name in TRAJECTORY_FILES:
        raw = _raw(DATA / name)
        task = task_from_filename(name)
        eps = episodes[start : start + len(EXPECTED_LENGTHS[task])]
        start += len(eps)
        obs = np.concatenate([_full_observation(ep) for ep in eps])
        np.testing.assert_array_equal(obs, raw["observations"][:, :53])
        acts = np.concatenate([ep.frames["action"] for ep in eps])
        np.testing.assert_array_equal(acts[:, :3], raw["actions"][:, :3])
        np.testing.assert_array_equal(acts[:, 3], -raw["actions"][:, 3])  # published > 0 closes; shiftkit > 0 opens
        offset = 0
        for e, ep in enumerate(eps):
            n = len(ep)
            # continuity inside an episode, a jump between episodes
            np.testing.assert_array_equal(
                raw["next_observations"][offset : offset + n - 1, :53], _full_observation(ep)[1:]
            )
            if offset + n < len(obs):
                assert np.any(raw["next_observations"][offset + n - 1] != raw["observations"][offset + n])
            # the sparse reward marks each episode's last transition
            assert ep.frames["next.reward"].reshape(-1).tolist() == [0.0] * (n - 1) + [1.0]
            assert set(ep.frames["task"]) == {task}
            assert ep.meta["source"]["start_overwritten"] == (e == 0 and raw["count"] > raw["memory_size"])
            offset += n


def test_circular_buffer_order_and_reward_columns(tmp_path):
    rng = np.random.default_rng(0)
    # three episodes of 3 steps (54-column rows) written into a ring of 7 rows after 9 insertions
    steps = []
    for _ in range(3):
        states = rng.normal(size=(4, 54)).astype(np.float32)
        states[:, -1] = 0
        steps += [(states[t], states[t + 1]) for t in range(3)]
    obs = np.stack([s for s, _ in steps])
    nxt = np.stack([n for _, n in steps])
    actions = rng.uniform(-1, 1, (9, 4)).astype(np.float32)
    rewards = np.stack([np.arange(9), -np.arange(9)], axis=1).astype(np.float32)  # columns differ
    # insertion k goes to slot k % 7: insertions 0 and 1 were overwritten by 7 and 8, the oldest is at slot 2
    stored = {
        k: np.zeros((7, *a.shape[1:]), np.float32)
        for k, a in (("obs", obs), ("nxt", nxt), ("act", actions), ("rew", rewards))
    }
    for k in range(2, 9):
        slot = k % 7
        stored["obs"][slot], stored["nxt"][slot] = obs[k], nxt[k]
        stored["act"][slot], stored["rew"][slot] = actions[k], rewards[k]
    path = _write_buffer(
        tmp_path / "7_task-x.gz", stored["obs"], stored["nxt"], stored["act"], stored["rew"], pointer=9 % 7, count=9
    )

    buf = read_vpace_buffer(path)
    assert buf.task == "task-x" and buf.overwritten_rows == 2
    np.testing.assert_array_equal(buf.observations, obs[2:, :53])
    assert buf.kind() == "trajectories" and buf.episode_bounds() == [(0, 1), (1, 4), (4, 7)]

    dataset = import_dataset("vpace", {"files": [str(path)]}, "t/ring", tmp_path / "ds")
    assert dataset.provenance["sources"][0]["files"][0]["lengths"] == [1, 3, 3]
    episodes = list(open_lerobot_dataset(tmp_path / "ds").iter_episodes())
    assert episodes[0].meta["source"]["start_overwritten"] and not episodes[1].meta["source"]["start_overwritten"]
    np.testing.assert_array_equal(np.concatenate([ep.frames["next.reward"] for ep in episodes]), rewards[2:])
    info = json.loads((tmp_path / "ds" / "meta" / "info.json").read_text())
    assert info["features"]["next.reward"]["names"] == ["reward_0", "reward_1"]


def test_bad_inputs_are_one_line_errors(tmp_path, capsys):
    evil = tmp_path / "1_evil.gz"
    with gzip.open(evil, "wb") as f:
        f.write(b"cos\nsystem\n(S'echo pwned'\ntR.")  # a pickle that would run a shell command
    with pytest.raises(DatasetError, match="refusing to load os.system|posix.system"):
        read_vpace_buffer(evil)
    with pytest.raises(DatasetError, match="cannot tell the task"):
        task_from_filename("buffer.gz")
    bad_width = _write_buffer(
        tmp_path / "2_lift.gz",
        *(np.zeros((3, 10), np.float32),) * 2,
        np.zeros((3, 4), np.float32),
        np.zeros((3, 1), np.float32),
        0,
        3,
    )
    with pytest.raises(DatasetError, match=r"neither \(N, 60\) nor \(N, 54\)"):
        read_vpace_buffer(bad_width)
    empty = _write_buffer(
        tmp_path / "3_lift.gz",
        *(np.zeros((0, 60), np.float32),) * 2,
        np.zeros((0, 4), np.float32),
        np.zeros((0, 1), np.float32),
        0,
        0,
    )
    with pytest.raises(DatasetError, match="empty buffer"):
        read_vpace_buffer(empty)
    with pytest.raises(ShiftkitError, match="invalid repo id"):
        import_dataset("vpace", {"files": [str(bad_width)]}, "not a repo id", tmp_path / "never")
    assert not (tmp_path / "never").exists()

    assert (
        main(
            ["import", "vpace", str(tmp_path / "missing_3_lift.gz"), "--repo-id", "a/b", "--root", str(tmp_path / "o")]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no such file" in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


@needs_data
def test_cli_import(tmp_path, capsys):
    args = ["import", "vpace", str(DATA / "full_trajectories_4_reach.gz"), "--repo-id", "vpace/reach", "--root"]
    assert main([*args, str(tmp_path / "r")]) == 0
    out = capsys.readouterr().out
    assert "task 'reach', 200 transitions in 21 episodes" in out and "wrote 21 episodes, 200 frames at 5 fps" in out
    assert main([*args, str(tmp_path / "r")]) == 2
    assert "destination already exists" in capsys.readouterr().err
    mixed = [str(DATA / "examples_1200_4_reach.gz"), str(DATA / "full_trajectories_4_reach.gz")]
    assert main(["import", "vpace", *mixed, "--repo-id", "a/b", "--root", str(tmp_path / "m")]) == 2
    assert "mix observation widths" in capsys.readouterr().err


# Every .gz under utiasSTARS/vpace `expert_data/` (commit f806e40), by the task it holds (the reference's
# env_default_configs.py names them `<index>_[<scene>-]<task>[_<revision>]` for Panda play and
# `<env>[_[random_]<aux>[_<variant>]]` for the other environments).
REFERENCE_FILE_TASKS = {
    "open": (
        "1200_per_task/0_bring-open.gz",
        "1200_per_task/0_insert-open.gz",
        "1200_per_task/0_stack-open.gz",
        "full_trajectories/200_per_task/0_bring-open.gz",
        "full_trajectories/200_per_task/0_insert-open.gz",
        "full_trajectories/200_per_task/0_stack-open.gz",
        "full_trajectories/200_per_task/0_unstack-stack-open.gz",
    ),
    "close": (
        "1200_per_task/1_close.gz",
        "full_trajectories/200_per_task/1_close.gz",
        "full_trajectories/200_per_task/1_unstack-stack-close.gz",
    ),
    "bring": (
        "1200_per_task/2_bring.gz",
        "full_trajectories/200_per_task/2_bring.gz",
    ),
    "insert": (
        "1200_per_task/2_insert.gz",
        "full_trajectories/200_per_task/0_insert.gz",
        "full_trajectories/200_per_task/2_insert.gz",
    ),
    "stack": (
        "1200_per_task/2_stack.gz",
        "full_trajectories/200_per_task/2_stack.gz",
    ),
    "lift": (
        "1200_per_task/3_lift.gz",
        "full_trajectories/200_per_task/3_lift.gz",
        "full_trajectories/200_per_task/3_unstack-stack-lift.gz",
    ),
    "unstack": ("1200_per_task/3_unstack.gz",),
    "reach": (
        "1200_per_task/4_reach.gz",
        "1200_per_task/PandaReach_reach.gz",
        "1200_per_task/SimPandaReach_reach.gz",
        "1200_per_task/hand_dapg/door-human-v0_reach.gz",
        "1200_per_task/hand_dapg/door-human-v0_reach_mulperep.gz",
        "1200_per_task/hand_dapg/door-human-v0_reach_oneperep.gz",
        "1200_per_task/hand_dapg/hammer-human-v0_reach.gz",
        "1200_per_task/hand_dapg/hammer-human-v0_reach_mulperep.gz",
        "1200_per_task/hand_dapg/hammer-human-v0_reach_mulperep_withvel.gz",
        "1200_per_task/hand_dapg/hammer-human-v0_reach_oneperep.gz",
        "1200_per_task/hand_dapg/hammer-human-v0_reach_oneperep_withvel.gz",
        "1200_per_task/hand_dapg/relocate-human-v0-najp_reach.gz",
        "1200_per_task/hand_dapg/relocate-human-v0_reach.gz",
        "1200_per_task/hand_dapg/with_vel/relocate-human-v0-najp_reach.gz",
        "1200_per_task/sawyer/no_grip_pos/sawyer_bin_picking_random_reach.gz",
        "1200_per_task/sawyer/no_grip_pos/sawyer_bin_picking_reach.gz",
        "1200_per_task/sawyer/no_grip_pos/sawyer_box_close_random_reach.gz",
        "1200_per_task/sawyer/no_grip_pos/sawyer_box_close_reach.gz",
        "1200_per_task/sawyer/no_grip_pos/sawyer_drawer_close_random_reach.gz",
        "1200_per_task/sawyer/no_grip_pos/sawyer_drawer_close_reach.gz",
        "1200_per_task/sawyer/no_grip_pos/sawyer_drawer_open_random_reach.gz",
        "1200_per_task/sawyer/no_grip_pos/sawyer_drawer_open_random_reach_p02z.gz",
        "1200_per_task/sawyer/no_grip_pos/sawyer_drawer_open_reach.gz",
        "1200_per_task/sawyer/no_grip_pos/sawyer_lift_random_reach.gz",
        "1200_per_task/sawyer/no_grip_pos/sawyer_lift_reach.gz",
        "1200_per_task/sawyer/no_grip_pos/sawyer_push_random_reach.gz",
        "1200_per_task/sawyer/no_grip_pos/sawyer_push_random_reach_p025.gz",
        "1200_per_task/sawyer/no_grip_pos/sawyer_push_random_reach_p1.gz",
        "1200_per_task/sawyer/no_grip_pos/sawyer_push_random_reach_p6.gz",
        "1200_per_task/sawyer/no_grip_pos/sawyer_push_reach.gz",
        "1200_per_task/sawyer/sawyer_bin_picking_random_reach.gz",
        "1200_per_task/sawyer/sawyer_box_close_random_reach.gz",
        "1200_per_task/sawyer/sawyer_drawer_close_random_reach.gz",
        "1200_per_task/sawyer/sawyer_drawer_open_random_reach.gz",
        "1200_per_task/sawyer/sawyer_drawer_open_random_reach_with_grasp.gz",
        "1200_per_task/sawyer/sawyer_lift_random_reach.gz",
        "1200_per_task/sawyer/sawyer_push_random_reach.gz",
        "1200_per_task/sawyer/with_vel/sawyer_bin_picking_random_reach.gz",
        "1200_per_task/sawyer/with_vel/sawyer_lift_random_reach.gz",
        "50_per_task/PandaDoorAngle_reach.gz",
        "50_per_task/PandaDoorNoJamAngle_reach.gz",
        "50_per_task/PandaDoor_reach.gz",
        "50_per_task/PandaDrawerLine_reach.gz",
        "50_per_task/PandaDrawer_reach.gz",
        "full_trajectories/200_per_task/4_reach.gz",
        "full_trajectories/200_per_task/4_unstack-stack-reach.gz",
    ),
    "move-object": (
        "1200_per_task/5_move.gz",
        "1200_per_task/5_move_new.gz",
        "full_trajectories/200_per_task/5_move.gz",
        "full_trajectories/200_per_task/5_move_fix.gz",
        "full_trajectories/200_per_task/5_unstack-stack-move.gz",
    ),
    "PandaReach": ("1200_per_task/PandaReach.gz",),
    "SimPandaReach": ("1200_per_task/SimPandaReach.gz",),
    "door-human-v0": ("1200_per_task/hand_dapg/door-human-v0.gz",),
    "grasp": (
        "1200_per_task/hand_dapg/door-human-v0_grasp.gz",
        "1200_per_task/hand_dapg/door-human-v0_grasp_straighthandle.gz",
        "1200_per_task/hand_dapg/door-human-v0_grasp_turnedhandle.gz",
        "1200_per_task/hand_dapg/hammer-human-v0_grasp.gz",
        "1200_per_task/hand_dapg/hammer-human-v0_grasp_oneperep_withvel.gz",
        "1200_per_task/hand_dapg/hammer-human-v0_grasp_withvel.gz",
        "1200_per_task/hand_dapg/relocate-human-v0-najp_grasp.gz",
        "1200_per_task/hand_dapg/relocate-human-v0_grasp.gz",
        "1200_per_task/hand_dapg/with_vel/relocate-human-v0-najp_grasp.gz",
        "1200_per_task/sawyer/sawyer_bin_picking_random_grasp.gz",
        "1200_per_task/sawyer/sawyer_box_close_random_grasp.gz",
        "1200_per_task/sawyer/sawyer_drawer_close_random_grasp.gz",
        "1200_per_task/sawyer/sawyer_drawer_open_random_grasp.gz",
        "1200_per_task/sawyer/sawyer_lift_random_grasp.gz",
        "1200_per_task/sawyer/sawyer_push_random_grasp.gz",
        "50_per_task/PandaDoorAngle_grasp.gz",
        "50_per_task/PandaDoorNoJamAngle_grasp.gz",
        "50_per_task/PandaDoor_grasp.gz",
        "50_per_task/PandaDrawerLine_grasp.gz",
        "50_per_task/PandaDrawer_grasp.gz",
    ),
    "hammer-human-v0": ("1200_per_task/hand_dapg/hammer-human-v0.gz",),
    "relocate-human-v0-najp": (
        "1200_per_task/hand_dapg/relocate-human-v0-najp.gz",
        "1200_per_task/hand_dapg/with_vel/relocate-human-v0-najp.gz",
    ),
    "relocate-human-v0": ("1200_per_task/hand_dapg/relocate-human-v0.gz",),
    "sawyer_air_reach": ("1200_per_task/sawyer/no_grip_pos/sawyer_air_reach.gz",),
    "sawyer_bin_picking": (
        "1200_per_task/sawyer/no_grip_pos/sawyer_bin_picking.gz",
        "1200_per_task/sawyer/sawyer_bin_picking.gz",
        "1200_per_task/sawyer/sawyer_bin_picking_ORIG.gz",
        "1200_per_task/sawyer/with_vel/sawyer_bin_picking.gz",
    ),
    "sawyer_box_close": (
        "1200_per_task/sawyer/no_grip_pos/sawyer_box_close.gz",
        "1200_per_task/sawyer/sawyer_box_close.gz",
    ),
    "sawyer_drawer_close": (
        "1200_per_task/sawyer/no_grip_pos/sawyer_drawer_close.gz",
        "1200_per_task/sawyer/sawyer_drawer_close.gz",
    ),
    "sawyer_drawer_open": (
        "1200_per_task/sawyer/no_grip_pos/sawyer_drawer_open.gz",
        "1200_per_task/sawyer/sawyer_drawer_open.gz",
    ),
    "sawyer_lift": (
        "1200_per_task/sawyer/no_grip_pos/sawyer_lift.gz",
        "1200_per_task/sawyer/sawyer_lift.gz",
        "1200_per_task/sawyer/sawyer_lift_no_xyrandom.gz",
        "1200_per_task/sawyer/with_vel/sawyer_lift.gz",
    ),
    "sawyer_push": (
        "1200_per_task/sawyer/no_grip_pos/sawyer_push.gz",
        "1200_per_task/sawyer/sawyer_push.gz",
    ),
    "sawyer_reach": ("1200_per_task/sawyer/no_grip_pos/sawyer_reach.gz",),
    "PandaDoor": ("50_per_task/PandaDoor.gz",),
    "PandaDoorAngle": ("50_per_task/PandaDoorAngle.gz",),
    "PandaDoorNoJamAngle": ("50_per_task/PandaDoorNoJamAngle.gz",),
    "PandaDrawer": ("50_per_task/PandaDrawer.gz",),
    "PandaDrawerLine": ("50_per_task/PandaDrawerLine.gz",),
    "unstack-stack": ("full_trajectories/200_per_task/2_unstack-stack.gz",),
}


def test_every_reference_file_name_names_its_task():
    names = [(name, task) for task, files in REFERENCE_FILE_TASKS.items() for name in files]
    assert len(names) == 123
    for name, task in names:
        assert task_from_filename(name) == task, name
        assert task_from_filename(f"examples_1200_{Path(name).name}") == task, name  # local copies keep a prefix
    assert parse_reference_name("0_stack-open.gz") == ReferenceName("open", "stack", None)
    assert parse_reference_name("5_move_new.gz") == ReferenceName("move-object", None, "new")
    assert parse_reference_name("sawyer_drawer_open_random_reach_p02z.gz") == ReferenceName(
        "reach", "sawyer_drawer_open", "p02z"
    )
    assert parse_reference_name("relocate-human-v0-najp_grasp.gz") == ReferenceName("grasp", "relocate-human-v0-najp")
    assert parse_reference_name("SimPandaReach.gz") == ReferenceName("SimPandaReach", "SimPandaReach")


def test_revised_recording_imports_without_task(tmp_path, capsys):
    """`1200_per_task/5_move_new.gz` (VPACE-era, 54 columns) imports as move-object examples."""
    rng = np.random.default_rng(1)
    obs = rng.normal(size=(3, 54)).astype(np.float32)
    obs[:, -1] = 0
    folder = tmp_path / "1200_per_task"
    folder.mkdir()
    path = _write_buffer(folder / "5_move_new.gz", obs, obs, np.zeros((3, 4), np.float32), np.ones((3, 5)), 0, 3)
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    assert main(["import", "vpace", str(path), "--repo-id", "vpace/move", "--root", str(tmp_path / "m")]) == 0
    assert "5_move_new.gz: task 'move-object', 3 examples" in capsys.readouterr().out
    episodes = list(open_lerobot_dataset(tmp_path / "m").iter_episodes())
    assert [ep.meta["task"] for ep in episodes] == ["move-object"] * 3
    np.testing.assert_array_equal(np.concatenate([_full_observation(ep) for ep in episodes]), obs[:, :53])
    provenance = json.loads((tmp_path / "m" / "meta" / "shiftkit_provenance.json").read_text())
    assert provenance["sources"][0]["files"][0]["file_name"] == {"task": "move-object", "scene": None, "variant": "new"}
    assert hashlib.sha256(path.read_bytes()).hexdigest() == digest

    # Files of the reference's other environments have their names mapped; their layout is refused by name.
    sawyer = _write_buffer(
        tmp_path / "sawyer_lift_random_reach.gz",
        *(np.zeros((2, 8), np.float32),) * 2,
        np.zeros((2, 4)),
        np.zeros((2, 1)),
        0,
        2,
    )
    with pytest.raises(DatasetError, match=r"\(2, 8\) is neither .* \(sawyer_lift data: shiftkit has no environment"):
        read_vpace_buffer(sawyer)
