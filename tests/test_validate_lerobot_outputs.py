"""`shiftkit validate` accepts what lerobot's own dataset tools write (when lerobot loads it) and
fails only on what would make a trainer fail."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from shiftkit.app.cli import main
from shiftkit.datasets.check import validate_dataset
from shiftkit.datasets.errors import DatasetError
from tests.helpers import write_raw_as_lerobot


@pytest.fixture
def shiftkit_dataset(synthetic_raw_images, tmp_path):
    return write_raw_as_lerobot(synthetic_raw_images, "test/src", tmp_path / "src")


def test_outputs_of_lerobot_tools_validate(shiftkit_dataset, tmp_path, capsys):
    from lerobot.datasets import dataset_tools as tools
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset("test/src", root=shiftkit_dataset)
    n = ds.meta.total_frames
    reward = np.linspace(0, 1, n, dtype=np.float32)
    shutil.copytree(shiftkit_dataset, tmp_path / "tasks")
    outputs = {
        "add_features": tools.add_features(
            ds,
            {"next.reward": (reward, {"dtype": "float32", "shape": (1,), "names": None})},
            output_dir=tmp_path / "add",
            repo_id="test/add",
        ).root,
        "remove_feature": tools.remove_feature(
            ds, "observation.environment_state", output_dir=tmp_path / "rm", repo_id="test/rm"
        ).root,
        "convert_image_to_video_dataset": tools.convert_image_to_video_dataset(
            ds, tmp_path / "video", repo_id="test/video", num_workers=1
        ).root,
        "merge_datasets": tools.merge_datasets([ds, ds], "test/merged", output_dir=tmp_path / "merged").root,
        "modify_tasks": tools.modify_tasks(LeRobotDataset("test/t", root=tmp_path / "tasks"), new_task="push").root,
    }
    for tool, root in outputs.items():
        LeRobotDataset(f"test/{tool}", root=root, video_backend="pyav")  # lerobot loads it ...
        capsys.readouterr()
        assert main(["validate", str(root)]) == 0, tool  # ... so shiftkit accepts it
        printed = capsys.readouterr().out
        assert printed.splitlines()[-1].startswith("ok: "), tool
        if tool == "add_features":  # lerobot writes no statistics for an added feature
            assert "warning: " in printed and "'next.reward'" in printed


def _edit_stats(root, edit):
    path = root / "meta/stats.json"
    stats = json.loads(path.read_text())
    edit(stats)
    path.write_text(json.dumps(stats))


def test_statistics_a_trainer_fails_on_are_errors(shiftkit_dataset):
    assert validate_dataset(shiftkit_dataset)["warnings"] == []

    _edit_stats(shiftkit_dataset, lambda s: s["observation.state"].pop("min"))
    with pytest.raises(DatasetError, match=r"statistics of 'observation.state' lack \['min'\]"):
        validate_dataset(shiftkit_dataset)

    _edit_stats(shiftkit_dataset, lambda s: s.pop("observation.state"))
    assert "'observation.state'" in validate_dataset(shiftkit_dataset)["warnings"][0]

    _edit_stats(shiftkit_dataset, lambda s: s["action"].update(std=[float("nan")] * len(s["action"]["std"])))
    with pytest.raises(DatasetError, match="'action' hold NaN or inf"):
        validate_dataset(shiftkit_dataset)

    _edit_stats(shiftkit_dataset, lambda s: s.pop("action"))
    with pytest.raises(DatasetError, match="no statistics for 'action'"):
        validate_dataset(shiftkit_dataset)
