"""What lerobot 0.6.1 writes beyond frames survives a pipeline: its language columns
(`language_persistent`, `language_events`: per frame, a list of message rows; a persistent row's
time moves with the time line) through every stage that keeps frames, the other files of a source's `meta/` and its info.json `tools`, under the local
and the datatrove executors."""

from __future__ import annotations

import numpy as np
import pytest

from shiftkit.datasets.episode import Episode
from shiftkit.datasets.features import object_column
from shiftkit.datasets.reader import open_lerobot_dataset
from shiftkit.datasets.sources import SourceConfig
from shiftkit.datasets.writer import DatasetWriter
from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, StageSpec
from shiftkit.pipelines.runner import run_pipeline

FPS, LENGTH = 10, 12


def _rows(e: int, t: int) -> tuple[list[dict], list[dict]]:
    persistent = [
        {
            "role": "user",
            "content": f"pick block {e}",
            "style": None,
            "timestamp": 0.0,
            "camera": None,
            "tool_calls": None,
        }
    ]
    events = (
        [{"role": "assistant", "content": "grasped", "style": "interjection", "camera": None, "tool_calls": None}]
        if t in (5, 6)
        else []
    )
    return persistent, events


@pytest.fixture(scope="module")
def annotated(tmp_path_factory):
    from lerobot.datasets.language import language_feature_info

    features = {
        "observation.state": {"dtype": "float32", "shape": (2,), "names": ["t", "e"]},
        "action": {"dtype": "float32", "shape": (2,), "names": ["t", "e"]},
        **language_feature_info(),
    }
    root = tmp_path_factory.mktemp("language") / "src"
    with DatasetWriter("test/language", root, FPS, features) as writer:
        for e in range(3):
            rows = [_rows(e, t) for t in range(LENGTH)]
            state = np.stack([np.array([t, e], np.float32) for t in range(LENGTH)])
            writer.add_episode(
                Episode(
                    {
                        "observation.state": state,
                        "action": state + 1,
                        "language_persistent": object_column([r[0] for r in rows]),
                        "language_events": object_column([r[1] for r in rows]),
                        "timestamp": (np.arange(LENGTH) / FPS).astype(np.float32),
                        "task": np.array(["pick"] * LENGTH),
                    }
                )
            )
    return root


def test_language_columns_survive_stages_and_load_in_lerobot(annotated, tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    config = PipelineConfig(
        sources=[SourceConfig(path=str(annotated))],
        destination=DestinationConfig(root=str(tmp_path / "out"), repo_id="test/language"),
        stages=[StageSpec("filter", {"indices": [0, 2]}), StageSpec("trim", {"head": 1}), StageSpec("subsample", {})],
    )
    out = run_pipeline(config, workers=2, progress=False)
    episodes = list(open_lerobot_dataset(out).iter_episodes())
    assert [len(ep) for ep in episodes] == [6, 6]
    kept = list(range(1, LENGTH, 2))
    for ep, e in zip(episodes, (0, 2), strict=True):
        # the persistent row became active 0.1 s before the first kept frame, which is now at 0 s
        moved = [{**row, "timestamp": float(np.float32(-0.1))} for row in _rows(e, 0)[0]]
        assert list(ep.frames["language_persistent"]) == [moved] * len(kept)
        # Each kept frame fires the events of the frames it stands for (frame 6's moves to 5).
        assert list(ep.frames["language_events"]) == [_rows(e, t)[1] + _rows(e, t + 1)[1] for t in kept]
    ds = LeRobotDataset("test/language", root=out)
    assert ds.meta.has_language_columns
    assert ds.hf_dataset[2]["language_events"] == _rows(0, 5)[1] * 2  # frame 5 of episode 0: both events


@pytest.mark.parametrize("executor", ["local", "datatrove-local"])
def test_source_meta_files_and_tools_are_carried(annotated, tmp_path, executor):
    import json
    import shutil

    src = tmp_path / "src"
    shutil.copytree(annotated, src)
    (src / "meta" / "temporal_proportions_sparse.json").write_text('{"pick": 1.0}')
    info = json.loads((src / "meta" / "info.json").read_text())
    tools = [{"type": "function", "function": {"name": "say", "parameters": {"type": "object"}}}]
    (src / "meta" / "info.json").write_text(json.dumps({**info, "tools": tools}))
    config = PipelineConfig(
        sources=[SourceConfig(path=str(src))],
        destination=DestinationConfig(root=str(tmp_path / "out"), repo_id="test/language"),
        stages=[StageSpec("trim", {"head": 1})],
    )
    out = run_pipeline(config, workers=1, executor=executor, progress=False)
    assert (out / "meta" / "temporal_proportions_sparse.json").read_text() == '{"pick": 1.0}'
    assert json.loads((out / "meta" / "info.json").read_text())["tools"] == tools
