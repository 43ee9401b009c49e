"""`shiftkit view` (`app/dataset_view.py`): a multiview dataset made by the demo and a FIRE-aggregated
dataset made by `shiftkit fire`, each saved as a `.rrd` and read back with the Rerun SDK: the
entities are there and their values are the dataset's (frames, depth, every numeric column by its
names, flags as spans, segments, camera poses), the recorded and re-rendered views share frames."""

from __future__ import annotations

import io
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from shiftkit.app.cli import main

rr = pytest.importorskip("rerun")


def read_rrd(path: Path) -> dict[str, dict[str, list]]:
    """{entity: {column: values}} of every chunk in the recording (`frame` is the timeline)."""
    from rerun.experimental import RrdReader

    out: dict[str, dict[str, list]] = {}
    for chunk in RrdReader(path).store().stream():
        batch = chunk.to_record_batch()
        columns = out.setdefault(chunk.entity_path, {})
        for name in batch.schema.names:
            if not name.startswith("rerun.controls"):
                columns.setdefault(name, []).extend(batch.column(name).to_pylist())
    return out


def series(data: dict, entity: str) -> tuple[np.ndarray, np.ndarray]:
    """(frames, values) of a Scalars entity, sorted by frame."""
    cols = data[entity]
    frames = np.asarray(cols["frame"])
    order = np.argsort(frames, kind="stable")
    return frames[order], np.asarray(cols["Scalars:scalars"])[order]


def lane(data: dict, entity: str) -> list[tuple[int, str]]:
    cols = data[entity]
    return sorted(zip(cols["frame"], [s[0] for s in cols["StateChange:state"]], strict=True))


def expected_lane(values: list) -> list[tuple[int, str]]:
    return [(t, v) for t, v in enumerate(values) if t == 0 or values[t - 1] != v]


@pytest.fixture(scope="module")
def multiview(tmp_path_factory) -> Path:
    from shiftkit.app.demo import run_demo

    return Path(run_demo(tmp_path_factory.mktemp("view") / "demo", 2, 0, False, progress=False, views=1)["dataset"])


@pytest.fixture(scope="module")
def fire_dataset(tmp_path_factory) -> Path:
    from shiftkit.envs import families
    from tests.test_fire import EXPERT_ENVS, _fire_cli

    env_name, task = EXPERT_ENVS[0]
    rate = str(min(families()[env_name].control_rates))
    tmp = tmp_path_factory.mktemp("view")
    demo = tmp / "demo"
    assert main(["collect", "--env", env_name, "--task", task, "--episodes", "3", "--control-hz", rate]
                + ["--lerobot", "test/view-demo", "--root", str(demo), "--no-progress"]) == 0  # fmt: skip
    args = _fire_cli(
        env_name, task, demo, tmp / "run", "--repo-id", "test/view-fire", "--dataset-root", str(tmp / "agg")
    )
    assert main(args) == 0
    return tmp / "agg"


def test_view_multiview_dataset(multiview, tmp_path, capsys):
    from shiftkit.datasets.reader import open_lerobot_dataset

    out = tmp_path / "mv.rrd"
    assert main(["view", str(multiview), "--save", str(out), "--no-progress"]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    data = read_rrd(out)
    reader = open_lerobot_dataset(multiview)
    episodes = list(reader.iter_episodes())
    assert [e.meta["multiview"]["view"] for e in episodes] == ["source", 0, "source", 0]
    for view in ("recorded", "view_1"):
        cam = f"world/{view}/mobile_base/base"
        assert {f"/{cam}", f"/{cam}/rgb", f"/{cam}/depth", f"/world/{view}/mobile_base"} <= set(data)
        assert {f"/series/{view}/{k}" for k in ("action", "observation.state")} <= set(data)
        assert {f"/flags/{view}/next.success", f"/segments/{view}/task"} <= set(data)
    start = 0
    for k in (0, 2):  # each source episode and its re-rendered view share frames start..start+n
        n = len(episodes[k])
        for view, ep in (("recorded", episodes[k]), ("view_1", episodes[k + 1])):
            frames, state = series(data, f"/series/{view}/observation.state")
            rows = (frames >= start) & (frames < start + n)
            np.testing.assert_array_equal(frames[rows], np.arange(start, start + n))
            np.testing.assert_allclose(state[rows], ep.frames["observation.state"], rtol=1e-6)
            rgb = data[f"/world/{view}/mobile_base/base/rgb"]
            blobs = [b for f, b in zip(rgb["frame"], rgb["EncodedImage:blob"], strict=True) if start <= f < start + n]
            from PIL import Image

            decoded = np.stack([np.asarray(Image.open(io.BytesIO(bytes(b[0])))) for b in blobs])
            np.testing.assert_array_equal(decoded, ep.frames["observation.images.base"])
            depth = data[f"/world/{view}/mobile_base/base/depth"]
            buffers = [
                b for f, b in zip(depth["frame"], depth["DepthImage:buffer"], strict=True) if start <= f < start + n
            ]
            metres = np.stack([np.frombuffer(bytes(b[0]), dtype=np.float32) for b in buffers]).reshape(n, 48, 64, 1)
            np.testing.assert_array_equal(metres, ep.frames["observation.depth.base"])
            # the episode's base pose and the camera on it, from meta/cameras.json
            pose_cols = data[f"/world/{view}/mobile_base"]
            i = pose_cols["frame"].index(start)
            pose = ep.meta["cameras"]["base"]["base_pose"]
            assert pose_cols["Transform3D:translation"][i][0] == pytest.approx([pose["x"], pose["y"], 0.0])
            assert pose_cols["Transform3D:rotation_axis_angle"][i][0]["angle"] == pytest.approx(pose["yaw"])
            success = [bool(s) for s in ep.frames["next.success"][:, 0]]
            got = [(f - start, s) for f, s in lane(data, f"/flags/{view}/next.success") if start <= f < start + n]
            assert got == expected_lane(["on" if s else "off" for s in success])
        start += n
    names = data["/series/recorded/observation.state"]["SeriesLines:names"][0]
    assert names == reader.features["observation.state"]["names"]
    assert [s for _, s in lane(data, "/episode")] == ["episode 0", "episode 2"]


def test_view_fire_dataset(fire_dataset, tmp_path):
    from shiftkit.datasets.reader import open_lerobot_dataset

    out = tmp_path / "fire.rrd"
    assert main(["view", str(fire_dataset), "--save", str(out), "--no-progress"]) == 0
    data = read_rrd(out)
    episodes = list(open_lerobot_dataset(fire_dataset).iter_episodes())
    assert {"/series/discriminator_score", "/flags/intervention", "/flags/intervention_request"} <= set(data)
    assert {"/segments/source", "/segments/task", "/series/action", "/series/observation.state"} <= set(data)
    frames, score = series(data, "/series/discriminator_score")
    np.testing.assert_array_equal(frames, np.arange(sum(len(e) for e in episodes)))
    np.testing.assert_allclose(score[:, 0], np.concatenate([e.frames["discriminator_score"][:, 0] for e in episodes]))
    labels = {0: "demonstration", 1: "policy", 2: "expert"}
    source = [labels[int(s)] for e in episodes for s in e.frames["source"][:, 0]]
    requests = ["on" if r else "off" for e in episodes for r in e.frames["intervention_request"][:, 0]]
    interventions = ["on" if r else "off" for e in episodes for r in e.frames["intervention"][:, 0]]
    # lanes restart at each episode's first frame
    starts = np.cumsum([0] + [len(e) for e in episodes])[:-1]

    def per_episode(values: list) -> list[tuple[int, str]]:
        out = []
        for s, e in zip(starts, episodes, strict=True):
            out += [(int(s) + t, v) for t, v in expected_lane(values[s : s + len(e)])]
        return out

    assert lane(data, "/segments/source") == per_episode(source)
    assert lane(data, "/flags/intervention_request") == per_episode(requests)
    assert lane(data, "/flags/intervention") == per_episode(interventions)
    assert "expert" in source and "policy" in source  # the run did intervene


def test_view_errors_are_one_line(multiview, tmp_path, capsys, monkeypatch):
    assert main(["view", str(multiview), "--episode", "9", "--save", str(tmp_path / "x.rrd")]) == 2
    assert capsys.readouterr().err.strip().endswith("no episode 9 (the dataset has 4)")
    assert main(["view", str(multiview), "--save", str(tmp_path)]) == 2
    assert "is a directory" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())  # nothing half-written
    if sys.platform.startswith("linux"):  # without --save it spawns a viewer, which needs a display
        monkeypatch.delenv("DISPLAY", raising=False)
        monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
        assert main(["view", str(multiview), "--episode", "0"]) == 2
        assert "no display for the Rerun viewer" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "rerun", None)  # the viz extra not installed
    assert main(["view", str(multiview), "--save", str(tmp_path / "x.rrd")]) == 2
    err = capsys.readouterr().err
    assert (
        err == "shiftkit view: error: the Rerun SDK is not installed: pip install 'shiftkit[viz]' (or rerun-sdk 0.33)\n"
    )


def test_view_episode_selects_its_views(multiview, tmp_path):
    out = tmp_path / "one.rrd"
    assert main(["view", str(multiview), "--episode", "3", "--save", str(out), "--no-progress"]) == 0
    data = read_rrd(out)
    assert [s for _, s in lane(data, "/episode")] == ["episode 2"]  # episode 3 is the view of episode 2
    assert set(series(data, "/series/view_1/observation.state")[0]) == set(
        series(data, "/series/recorded/observation.state")[0]
    )


def test_view_help_imports_no_torch_mujoco_or_rerun():
    code = (
        "import sys; from shiftkit.app.cli import main; main(['view', '--help']);"
        "print(sorted(m for m in ('torch', 'mujoco', 'rerun', 'lerobot') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().endswith("[]") and "--save FILE.rrd" in out


def test_view_summary_names_every_kind(multiview, tmp_path, capsys):
    assert main(["view", str(multiview), "--save", str(tmp_path / "s.rrd"), "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("sent 4 episodes, ") and "views: recorded, view_1" in out
    for kind in ("episode", "flags", "segments", "series", "world"):
        assert f"\n  {kind}: " in out
