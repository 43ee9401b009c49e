"""Importers are pipeline sources found by discovery: a new format is one module (plus its test). A
throw-away importer module on the importers package's path is registered, `shiftkit import` lists it
and imports with it (a pipeline with no stages, its record re-running it), a pipeline file takes it
as a source with stages of its own, and a bad option or format is one line."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from shiftkit.app.cli import main
from shiftkit.datasets.importers import IMPORTERS
from shiftkit.datasets.reader import open_lerobot_dataset

THROWAWAY_IMPORTER = '''
"""`toy`: episodes of 2-D actions from a JSON file {"fps": F, "episodes": [[[x, y], ...], ...]}."""

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shiftkit.datasets.dataclass_config import option
from shiftkit.datasets.episode import Episode
from shiftkit.datasets.features import vector_feature
from shiftkit.datasets.importers import Importer, register_importer


@dataclass
class ToyOptions:
    """Options of the toy importer."""

    file: str
    """JSON file of episodes."""
    task: str = "toy"
    """Task text of every episode."""
    scale: float = option(1.0, rule="positive_float")
    """Factor on every action."""


class ToySource:
    """The episodes of one toy file."""

    def __init__(self, options: ToyOptions) -> None:
        self.path = Path(options.file)
        self.inputs = [self.path]
        data = json.loads(self.path.read_text())
        self.options, self.fps, self.episodes = options, data["fps"], data["episodes"]
        self.features = {"action": vector_feature("float32", ["x", "y"])}
        self.robot_type, self.num_episodes = None, len(self.episodes)

    def episode_groups(self):
        return [list(range(self.num_episodes))]

    def iter_episodes(self, indices):
        for i in indices:
            action = np.asarray(self.episodes[i], dtype=np.float32) * self.options.scale
            n = len(action)
            frames = {"action": action, "timestamp": np.arange(n) / self.fps, "task": np.array([self.options.task] * n)}
            yield Episode(frames, {"source_episode_index": i})

    def describe(self):
        return {"kind": "toy", "path": str(self.path), "num_episodes": self.num_episodes}


IMPORTER = register_importer(
    Importer(
        name="toy",
        help="toy JSON episodes (an importer made by a test)",
        Options=ToyOptions,
        inputs=("file",),
        open=ToySource,
        report=lambda source: [f"{source['num_episodes']} toy episodes"],
    )
)
'''

EPISODES = [[[0.0, 1.0], [1.0, 2.0], [2.0, 3.0], [3.0, 4.0]], [[5.0, 6.0], [6.0, 7.0], [7.0, 8.0]]]


@pytest.fixture
def toy_importer(tmp_path, monkeypatch):
    import shiftkit.datasets.importers as importers

    assert "robomimic" in IMPORTERS and "vpace" in IMPORTERS  # the dataset layer's and the application's
    folder = tmp_path / "importers"
    folder.mkdir()
    (folder / "toy.py").write_text(THROWAWAY_IMPORTER)
    monkeypatch.setattr(importers, "__path__", [*importers.__path__, str(folder)])
    monkeypatch.setattr(IMPORTERS, "_discovered", False)
    monkeypatch.setattr(IMPORTERS, "_items", dict(IMPORTERS._items))
    yield
    sys.modules.pop("shiftkit.datasets.importers.toy", None)


def test_a_new_importer_module_is_found_and_imports(toy_importer, tmp_path, capsys):
    data = tmp_path / "toy.json"
    data.write_text(json.dumps({"fps": 10, "episodes": EPISODES}))
    assert main(["import", "--help"]) == 0
    assert "toy JSON episodes (an importer made by a test)" in capsys.readouterr().out
    assert main(["import", "toy", "--help"]) == 0
    assert "Factor on every action." in capsys.readouterr().out

    out = tmp_path / "out"
    assert main(["import", "toy", str(data), "--scale", "2", "--repo-id", "me/toy", "--root", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "2 toy episodes" in printed and "wrote 2 episodes, 7 frames at 10 fps" in printed
    episodes = list(open_lerobot_dataset(out).iter_episodes())
    for ep, values in zip(episodes, EPISODES, strict=True):
        np.testing.assert_array_equal(ep.frames["action"], np.asarray(values, np.float32) * 2)
    provenance = json.loads((out / "meta" / "shiftkit_provenance.json").read_text())
    assert provenance["sources"][0]["kind"] == "toy" and provenance["stages"] == []
    (recorded,) = provenance["pipeline"]["sources"]
    assert recorded["format"] == "toy" and recorded["options"] == {"file": str(data), "task": "toy", "scale": 2.0}

    # the provenance's pipeline re-runs the import with `shiftkit run`
    again = tmp_path / "again.json"
    again.write_text(json.dumps({**provenance["pipeline"], "destination": {"root": str(tmp_path / "again")}}))
    assert main(["run", str(again), "--no-progress"]) == 0
    capsys.readouterr()
    assert [len(ep) for ep in open_lerobot_dataset(tmp_path / "again").iter_episodes()] == [4, 3]


def test_a_format_is_a_pipeline_source_with_stages(toy_importer, tmp_path, capsys):
    (tmp_path / "toy.json").write_text(json.dumps({"fps": 10, "episodes": EPISODES}))
    (tmp_path / "p.toml").write_text(
        "[[sources]]\n"
        'format = "toy"\n'
        'options = { file = "toy.json", task = "wave" }\n'  # relative to the pipeline file
        'stages = [{ name = "trim", params = { head = 1 } }]\n'
        '[destination]\nroot = "out"\n'
    )
    assert main(["run", str(tmp_path / "p.toml"), "--no-progress"]) == 0
    capsys.readouterr()
    episodes = list(open_lerobot_dataset(tmp_path / "out").iter_episodes())
    np.testing.assert_array_equal(episodes[1].frames["action"], np.asarray(EPISODES[1][1:], np.float32))
    assert set(episodes[0].frames["task"]) == {"wave"}


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ('format = "nope"', "unknown import format 'nope' (known: lerobot-v2.1, robomimic, ros2, toy, vpace)"),
        ('format = "toy"\noptions = { file = "toy.json", scale = -1.0 }', "scale must be a positive finite number"),
        ('format = "toy"\noptions = { file = "toy.json", speed = 2 }', "unknown key 'speed'"),
        ('format = "lerobot-v2.1"\noptions = { source = "old" }', "converted by lerobot's own converter"),
        ('format = "toy"\npath = "toy.json"', "takes its inputs in 'options'"),
    ],
)
def test_bad_sources_are_one_line_errors(toy_importer, tmp_path, capsys, options, message):
    (tmp_path / "toy.json").write_text(json.dumps({"fps": 10, "episodes": EPISODES}))
    (tmp_path / "p.toml").write_text(f'[[sources]]\n{options}\n[destination]\nroot = "out"\n')
    assert main(["plan", str(tmp_path / "p.toml")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err, err
    assert main(["import", "toy", str(tmp_path / "toy.json"), "--scale", "0", "--repo-id", "a/b", "--root", "o"]) == 2
    assert "argument --scale: must be a positive finite number, got '0'" in capsys.readouterr().err
