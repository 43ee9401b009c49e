"""`success_examples`: success states per task from reset-based and play episodes, N per task with a
seeded selection that does not depend on worker count, written as a dataset LeRobotDataset loads."""

from __future__ import annotations

import json

import numpy as np
import pytest

from shiftkit.datasets.errors import ConfigError
from shiftkit.datasets.reader import open_lerobot_dataset
from shiftkit.datasets.sources import SourceConfig
from shiftkit.datasets.sources.raw import open_raw_dataset
from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, StageSpec
from shiftkit.pipelines.planner import plan_pipeline
from shiftkit.pipelines.runner import run_pipeline
from tests.helpers import tree_hashes


def _config(raw, dest, seed=0, stages=None, **params):
    return PipelineConfig(
        sources=[SourceConfig(path=str(raw))],
        destination=DestinationConfig(root=str(dest), repo_id="test/examples"),
        stages=stages or [StageSpec(name="success_examples", params=params)],
        seed=seed,
    )


def _examples(root):
    """(task, source episode, source frame) of every written example, in dataset order."""
    reader = open_lerobot_dataset(root)
    out = []
    for ep in reader.iter_episodes():
        assert len(ep) == 1
        src = ep.meta["source"]
        out.append((str(ep.frames["task"][0]), src["source_episode_index"], src["frame_index"]))
    return out, reader


@pytest.fixture(scope="module")
def play_raw(tmp_path_factory):
    """Three real play episodes of the Panda env (reach, grasp, lift, move-object, close) at 5 Hz."""
    from shiftkit.app.collect import CollectConfig, collect

    out = tmp_path_factory.mktemp("play") / "raw"
    collect(CollectConfig(task="lift", play=True, episodes=3, control_hz=5, out=str(out)))
    return out


def test_final_states_of_reset_based_episodes(synthetic_raw, tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    dest = tmp_path / "ex"
    run_pipeline(_config(synthetic_raw, dest, n_per_task=None, states="final"), progress=False)
    raw = open_raw_dataset(synthetic_raw)
    sources = list(raw.iter_episodes(list(range(raw.num_episodes))))
    successful = [i for i, ep in enumerate(sources) if ep.frames["next.success"].reshape(-1)[-1]]
    assert successful, "fixture must contain successful episodes"

    examples, reader = _examples(dest)
    # one example per successful episode: its last frame (the state after the final action is not recorded)
    assert examples == [("reach", i, len(sources[i]) - 1) for i in successful]
    for ep, i in zip(reader.iter_episodes(), successful, strict=True):
        np.testing.assert_array_equal(ep.frames["observation.state"][0], sources[i].frames["observation.state"][-1])
        assert ep.frames["timestamp"][0] == 0.0

    ds = LeRobotDataset("test/examples", root=dest)
    assert ds.num_episodes == len(successful) and len(ds) == len(successful)
    assert list(ds.meta.tasks.index) == ["reach"]


def test_n_per_task_is_a_seeded_sample_independent_of_workers(synthetic_raw, tmp_path):
    raw = open_raw_dataset(synthetic_raw)
    candidates = []  # frames holding a success state: t + 1 after a successful action t (last frame stands in)
    for i, ep in enumerate(raw.iter_episodes(list(range(raw.num_episodes)))):
        success = ep.frames["next.success"].reshape(-1)
        candidates += [("reach", i, f) for f in sorted({min(t + 1, len(ep) - 1) for t in np.flatnonzero(success)})]
    assert len(candidates) > 8, "fixture must have more candidates than the sample size"

    run_pipeline(_config(synthetic_raw, tmp_path / "w1", seed=3, n_per_task=5, states="success"), progress=False)
    run_pipeline(
        _config(synthetic_raw, tmp_path / "w2", seed=3, n_per_task=5, states="success"), workers=2, progress=False
    )
    # provenance differs only in what it should record (worker count, destination)
    data = {k: v for k, v in tree_hashes(tmp_path / "w1").items() if k != "meta/shiftkit_provenance.json"}
    assert data == {k: v for k, v in tree_hashes(tmp_path / "w2").items() if k != "meta/shiftkit_provenance.json"}
    chosen, _ = _examples(tmp_path / "w1")
    assert len(chosen) == 5 and set(chosen) <= set(candidates)
    assert chosen == sorted(chosen, key=candidates.index), "examples keep source order"

    run_pipeline(_config(synthetic_raw, tmp_path / "s4", seed=4, n_per_task=5, states="success"), progress=False)
    assert _examples(tmp_path / "s4")[0] != chosen, "another seed picks another sample"
    provenance = json.loads((tmp_path / "w1" / "meta" / "shiftkit_provenance.json").read_text())
    assert provenance["stages"][0]["params"] == {"n_per_task": 5, "states": "success", "tasks": None}
    assert provenance["output"]["episodes"] == 5


def test_select_keeps_the_smallest_keys_per_task():
    from shiftkit.datasets.errors import DatasetError
    from shiftkit.pipelines.stage import StageContext
    from shiftkit.transforms.success_examples import SuccessExamples, SuccessExamplesConfig

    stage = SuccessExamples(SuccessExamplesConfig(n_per_task=2), StageContext(fps=10))
    keys = {"reach": [0.9, 0.1, 0.5, 0.3], "lift": [0.2, 0.8]}
    metas = [{"task": t, "selection_key": k} for t in keys for k in keys[t]]
    assert stage.select(metas) == [False, True, False, True, True, True]
    assert SuccessExamples(SuccessExamplesConfig(n_per_task=None), StageContext(fps=10)).select(metas) is None
    with pytest.raises(DatasetError, match="selection_key"):
        stage.select([{"task": "reach"}])


def test_play_segments_give_one_example_set_per_task(play_raw, tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from shiftkit.envs import make
    from shiftkit.envs.panda_play.tasks import TASKS

    raw = open_raw_dataset(play_raw)
    sources = list(raw.iter_episodes(list(range(raw.num_episodes))))
    expected = {}
    for i, ep in enumerate(sources):
        for seg in ep.meta["segments"]:
            if seg["success"]:
                expected.setdefault(seg["task"], []).append((i, min(seg["end"], len(ep) - 1)))
    assert {"reach", "grasp", "lift"} <= set(expected)

    dest = tmp_path / "ex"
    run_pipeline(_config(play_raw, dest, n_per_task=None, states="final"), progress=False)
    examples, _ = _examples(dest)
    got = {}
    for task, episode, frame in examples:
        got.setdefault(task, []).append((episode, frame))
    assert got == expected

    # the example states satisfy the task's success predicate in the simulator (restored from sim.qpos/qvel)
    env = make("panda-play", "lift", control_hz=5)
    for task in ("reach", "grasp", "lift"):
        for episode, frame in got[task]:
            env.physics.set_state(
                sources[episode].frames["sim.qpos"][frame], sources[episode].frames["sim.qvel"][frame]
            )
            assert TASKS[task].predicate(env.facts()), f"{task} example (episode {episode}, frame {frame})"
    env.close()

    # tasks are told apart by the task index; N per task and the task filter
    dest2 = tmp_path / "ex2"
    run_pipeline(_config(play_raw, dest2, n_per_task=2, states="success", tasks=["reach", "lift"]), progress=False)
    ds = LeRobotDataset("test/examples", root=dest2)
    assert sorted(ds.meta.tasks.index) == ["lift", "reach"]
    task_index = np.asarray(ds.hf_dataset["task_index"]).reshape(-1)
    assert sorted(np.bincount(task_index).tolist()) == [2, 2]


def test_bad_input_and_config_are_one_line_errors(synthetic_raw, tmp_path):
    no_success = [
        StageSpec(name="drop", params={"features": ["next.success"]}),
        StageSpec(name="success_examples", params={}),
    ]
    with pytest.raises(ConfigError, match="needs a per-frame bool 'next.success'"):
        plan_pipeline(_config(synthetic_raw, tmp_path / "a", stages=no_success))
    with pytest.raises(ConfigError, match="n_per_task must be a positive integer") as info:
        plan_pipeline(_config(synthetic_raw, tmp_path / "b", n_per_task=0))
    assert "\n" not in str(info.value)
    with pytest.raises(ConfigError, match="states"):
        plan_pipeline(_config(synthetic_raw, tmp_path / "c", states="last"))
