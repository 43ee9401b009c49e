"""`shiftkit import robomimic`: a robomimic HDF5 file (robomimic's documented layout, written here with
h5py) becomes a LeRobot dataset: demos in order, mask/ filter keys, cameras, state, sim state."""

from __future__ import annotations

import hashlib
import json

import h5py
import numpy as np
import pytest

from shiftkit.app.cli import main
from shiftkit.app.importing import import_dataset
from shiftkit.datasets.reader import open_lerobot_dataset

LENGTHS = {"demo_0": 5, "demo_1": 3, "demo_10": 4}  # demo_10 sorts after demo_1 numerically


def _demo_arrays(name: str, n: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(int(name[5:]))
    return {
        "obs/agentview_image": rng.integers(0, 256, (n, 6, 8, 3), dtype=np.uint8),
        "obs/robot0_eef_pos": rng.normal(size=(n, 3)),
        "obs/robot0_gripper_qpos": rng.normal(size=(n, 2)).astype(np.float32),
        "obs/object": rng.normal(size=(n, 4)),
        "actions": rng.uniform(-1, 1, (n, 7)),
        "rewards": (np.arange(n) == n - 1).astype(np.float64),
        "dones": (np.arange(n) == n - 1).astype(np.int64),
        "states": rng.normal(size=(n, 9)),
    }


K = [[100.0, 0.0, 3.5], [0.0, 101.0, 2.5], [0.0, 0.0, 1.0]]
POSE = [[1.0, 0.0, 0.0, 0.5], [0.0, 0.0, -1.0, 0.1], [0.0, 1.0, 0.0, 1.2], [0.0, 0.0, 0.0, 1.0]]
CAMERA_INFO = {
    "agentview": {"intrinsics": K, "extrinsics": POSE},
    "robot0_eye_in_hand": {"intrinsics": K, "extrinsics": POSE},
}


def _write(path, demos=LENGTHS, env_args=None, total=None, edit=None, ep_meta=None):
    """A robomimic dataset file: data/{demo_N/{obs,next_obs,actions,rewards,dones,states}}, mask/."""
    env_args = env_args or {"env_name": "Lift", "env_type": 1, "env_kwargs": {"control_freq": 20, "robots": ["Panda"]}}
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["env_args"] = json.dumps(env_args)
        data.attrs["total"] = sum(demos.values()) if total is None else total
        for name, n in demos.items():
            arrays = _demo_arrays(name, n)
            if edit:
                edit(name, arrays)
            g = data.create_group(name)
            g.attrs["num_samples"] = n
            g.attrs["model_file"] = f"<mujoco model='{name}'/>"
            g.attrs["camera_info"] = json.dumps(CAMERA_INFO)  # as dataset_states_to_obs.py writes it
            if ep_meta:
                g.attrs["ep_meta"] = json.dumps(ep_meta(name))
            for key, arr in arrays.items():
                g.create_dataset(key, data=arr)
                if key.startswith("obs/"):
                    g.create_dataset("next_" + key, data=np.roll(arr, -1, axis=0))
        mask = f.create_group("mask")
        mask.create_dataset("train", data=np.array([b"demo_0", b"demo_10"]))
        mask.create_dataset("valid", data=np.array([b"demo_1"]))
    return path


def _sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_robomimic_file_imports(tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    src = _write(tmp_path / "low_dim.hdf5")
    digest = _sha(src)
    dataset = import_dataset("robomimic", {"file": str(src)}, "rm/lift", tmp_path / "out")
    assert (dataset.num_episodes, dataset.info["total_frames"], dataset.fps) == (3, 12, 20)
    assert _sha(src) == digest

    ds = LeRobotDataset("rm/lift", root=tmp_path / "out")
    assert ds.num_episodes == 3 and ds.fps == 20 and ds.meta.robot_type == "Panda"
    assert list(ds.features["observation.images.agentview"]["shape"]) == [6, 8, 3]
    assert ds.features["observation.state"]["names"] == [
        "robot0_eef_pos_0",
        "robot0_eef_pos_1",
        "robot0_eef_pos_2",
        "robot0_gripper_qpos_0",
        "robot0_gripper_qpos_1",
    ]
    assert ds.features["observation.environment_state"]["names"] == [f"object_{i}" for i in range(4)]
    assert ds.features["sim.state"]["dtype"] == "float64"
    assert list(ds.meta.tasks.index) == ["Lift"]

    episodes = list(open_lerobot_dataset(tmp_path / "out").iter_episodes())
    assert [ep.meta["source"]["demo"] for ep in episodes] == ["demo_0", "demo_1", "demo_10"]
    for ep in episodes:
        name = ep.meta["source"]["demo"]
        raw = _demo_arrays(name, LENGTHS[name])
        assert len(ep) == LENGTHS[name]
        np.testing.assert_array_equal(ep.frames["observation.images.agentview"], raw["obs/agentview_image"])
        state = np.concatenate([raw["obs/robot0_eef_pos"], raw["obs/robot0_gripper_qpos"]], axis=1)
        np.testing.assert_array_equal(ep.frames["observation.state"], state.astype(np.float32))
        np.testing.assert_array_equal(ep.frames["sim.state"], raw["states"])  # full precision, for re-rendering
        np.testing.assert_array_equal(ep.frames["action"], raw["actions"].astype(np.float32))
        assert ep.frames["next.done"].reshape(-1).tolist() == raw["dones"].astype(bool).tolist()
        assert ep.frames["next.reward"].reshape(-1).tolist() == raw["rewards"].tolist()
        model = f"<mujoco model='{name}'/>".encode()
        assert ep.meta["sim"]["model_file_sha256"] == hashlib.sha256(model).hexdigest()
        # shiftkit's camera metadata: intrinsics in pixels at the stored size, the pose in the world frame
        assert ep.meta["cameras"] == {
            "agentview": {
                "intrinsics": {"fx": 100.0, "fy": 101.0, "cx": 3.5, "cy": 2.5, "width": 8, "height": 6},
                "extrinsics": {"frame": "world", "position": [0.5, 0.1, 1.2], "rotation": [r[:3] for r in POSE[:3]]},
            }
        }

    provenance = json.loads((tmp_path / "out" / "meta" / "shiftkit_provenance.json").read_text())
    assert provenance["sources"][0]["sha256"] == digest
    assert provenance["sources"][0]["importer"]["env_args"]["env_name"] == "Lift"
    # an import is a pipeline with the importer as its source: its record re-runs it
    assert provenance["pipeline"]["sources"] == [
        {
            "path": None,
            "repo_id": None,
            "revision": None,
            "format": "robomimic",
            "options": {"file": str(src), "filter_key": None, "fps": None, "task": None, "obs_keys": None},
            "stages": [],
        }
    ]


def test_filter_key_fps_and_task(tmp_path, capsys):
    src = _write(tmp_path / "image.hdf5", env_args={"env_name": "Lift", "env_kwargs": {}})
    args = ["import", "robomimic", str(src), "--repo-id", "rm/train", "--filter-key", "train"]
    assert main([*args, "--root", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no integer env_kwargs.control_freq" in err and "give --fps" in err
    assert not (tmp_path / "a").exists()

    args += ["--fps", "10", "--task", "lift the cube", "--obs-keys", "robot0_eef_pos,agentview_image"]
    assert main([*args, "--root", str(tmp_path / "a")]) == 0
    assert "image.hdf5: 2 demos (mask/train)" in capsys.readouterr().out
    episodes = list(open_lerobot_dataset(tmp_path / "a").iter_episodes())
    assert [ep.meta["source"]["demo"] for ep in episodes] == ["demo_0", "demo_10"]
    assert set(episodes[0].frames) >= {"observation.state", "observation.images.agentview"}
    assert "observation.environment_state" not in episodes[0].frames
    assert episodes[0].frames["observation.state"].shape == (5, 3)
    assert set(episodes[1].frames["task"]) == {"lift the cube"}
    np.testing.assert_allclose(episodes[1].frames["timestamp"], np.arange(4) / 10)


def test_language_instruction_per_demo(tmp_path):
    """robocasa-style files keep a language instruction per demo in the ep_meta attribute; 1-DoF actions are (T,)."""

    def one_dim_actions(name, arrays):  # a 1-DoF robot stores actions as (T,)
        arrays["actions"] = arrays["actions"][:, 0]

    src = _write(
        tmp_path / "lang.hdf5",
        ep_meta=lambda name: {"lang": f"open drawer {name[5:]}", "layout_id": 3},
        edit=one_dim_actions,
    )
    import_dataset("robomimic", {"file": str(src), "filter_key": "valid"}, "rm/lang", tmp_path / "o")
    (ep,) = open_lerobot_dataset(tmp_path / "o").iter_episodes()
    assert set(ep.frames["task"]) == {"open drawer 1"}
    np.testing.assert_array_equal(
        ep.frames["action"][:, 0], _demo_arrays("demo_1", 3)["actions"][:, 0].astype(np.float32)
    )


def test_states_only_file(tmp_path):
    """robosuite's converted demo.hdf5 has no observations yet: actions + simulator states import."""

    def states_only(name, arrays):
        for key in [k for k in arrays if k.startswith("obs/") or k in ("rewards", "dones")]:
            del arrays[key]

    src = _write(tmp_path / "demo.hdf5", edit=states_only)
    dataset = import_dataset("robomimic", {"file": str(src)}, "rm/raw", tmp_path / "o")
    assert (dataset.num_episodes, dataset.info["total_frames"]) == (3, 12)
    ep = next(open_lerobot_dataset(tmp_path / "o").iter_episodes())
    assert sorted(k for k in ep.frames if k not in ("timestamp", "task")) == ["action", "sim.state"]
    np.testing.assert_array_equal(ep.frames["sim.state"], _demo_arrays("demo_0", 5)["states"])


def _nan_action(name, arrays):
    if name == "demo_1":
        arrays["actions"][2, 0] = np.nan


def _ragged(name, arrays):
    if name == "demo_10":
        arrays["obs/robot0_eef_pos"] = arrays["obs/robot0_eef_pos"][:-1]


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda p: p.write_text("not hdf5") and p, "not an HDF5 file"),
        (lambda p: h5py.File(p, "w").close() or p, "no 'data' group"),
        (lambda p: _write(p, edit=_nan_action), "data/demo_1/actions contains NaN/inf"),
        (lambda p: _write(p, edit=_ragged), "data/demo_10/obs/robot0_eef_pos has 3 samples, actions have 4"),
        (lambda p: _write(p, total=99), "total is 99, the demos hold 12"),
        (lambda p: _write(p, demos={}), "holds no demo_N groups"),
    ],
)
def test_bad_files_are_one_line_errors(tmp_path, capsys, make, message):
    src = make(tmp_path / "bad.hdf5")
    digest = _sha(src)
    assert main(["import", "robomimic", str(src), "--repo-id", "a/b", "--root", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err and "Traceback" not in err, err
    assert not (tmp_path / "o").exists() and not list(tmp_path.glob(".o.partial-*"))
    assert _sha(src) == digest


def test_bad_options_are_one_line_errors(tmp_path, capsys):
    src = _write(tmp_path / "x.hdf5")
    for extra, message in (
        (["--filter-key", "20_percent"], "no filter key '20_percent' under mask/ (known: ['train', 'valid'])"),
        (["--obs-keys", "robot0_joint_pos"], "has no key(s) ['robot0_joint_pos']"),
        (["--fps", "0"], "--fps: must be a positive integer"),
    ):
        assert main(["import", "robomimic", str(src), "--repo-id", "a/b", "--root", str(tmp_path / "o"), *extra]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and message in err, err
    assert main(["import", "robomimic", str(tmp_path / "none.hdf5"), "--repo-id", "a/b", "--root", str(tmp_path / "o")])
    assert "no such file" in capsys.readouterr().err
