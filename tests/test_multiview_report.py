"""Dropped views are counted in the run summary and the provenance: views that IK cannot
follow or that lose the object, and source episodes left without any view (which have no output
episode to carry the count), equal to the stage's own per-pose decisions, with 1 or 2 workers and
after a run stopped half-way is resumed."""

from __future__ import annotations

import json

import pytest

from shiftkit.app.cli import main
from shiftkit.app.collect import CollectConfig, collect
from shiftkit.datasets.sources.raw import open_raw_dataset
from shiftkit.envs.base_pose import BasePose
from shiftkit.pipelines.config import load_pipeline_config
from shiftkit.pipelines.runner import run_pipeline
from shiftkit.pipelines.stage import StageContext
from shiftkit.pipelines.work import PART_SUFFIX, episode_rng, work_dir_for
from shiftkit.transforms.multiview import Multiview, MultiviewConfig

SEED = 6  # source episode 2 loses both views; 1 and 3 lose one each
# Noise far beyond the sampler's default: some poses leave the arm unable to reach the recorded
# tool poses (IK) and some turn the camera away from the block (out of view).
PARAMS = {"num_views": 2, "xy_noise": 0.3, "yaw_noise": 1.2, "depth": False}
PIPELINE = """
seed = {seed}
[[sources]]
path = "{raw}"
[[stages]]
name = "multiview"
params = {params}
[destination]
root = "{dest}"
"""


@pytest.fixture(scope="module")
def raw(tmp_path_factory):
    out, _ = collect(
        CollectConfig(
            env="mv-lift",
            task="lift",
            episodes=5,
            seed=10,
            out=str(tmp_path_factory.mktemp("mvr") / "raw"),
            cameras=("base",),
            env_kwargs={"view": "fixed"},
        )
    )
    return out


@pytest.fixture(scope="module")
def expected(raw):
    """The counts from the stage's decision for each pose it samples, one call per pose."""
    stage = Multiview(MultiviewConfig(**PARAMS), StageContext(fps=10))
    stage.setup()
    source = open_raw_dataset(raw)
    counts = {"episodes_without_views": 0, "views_dropped_ik": 0, "views_dropped_out_of_view": 0, "views_kept": 0}
    for i in range(source.num_episodes):
        episode = source.read_episode(i)
        rng = episode_rng(SEED, 0, i, 0)  # the runner's rng of source 0, episode i, stage 0
        old = BasePose.from_dict(episode.meta["cameras"]["base"]["base_pose"])
        env = stage._env(episode.meta["sim_model"], (48, 64))
        kept = 0
        for _ in range(PARAMS["num_views"]):
            result = stage._render_view(episode, env, old, stage._sampler.sample(rng))
            if isinstance(result, str):
                counts[f"views_dropped_{result}"] += 1
            else:
                kept += 1
        counts["views_kept"] += kept
        counts["episodes_without_views"] += kept == 0
    # the fixture exercises every kind of count, so no check below can pass on zeros
    assert all(counts.values()), counts
    return counts


def _config(tmp_path, raw, name):
    path = tmp_path / f"{name}.toml"
    params = "{ " + ", ".join(f"{k} = {json.dumps(v)}" for k, v in PARAMS.items()) + " }"
    path.write_text(PIPELINE.format(seed=SEED, raw=raw, params=params, dest=tmp_path / name))
    return path


def _report(dest):
    prov = json.loads((dest / "meta" / "shiftkit_provenance.json").read_text())
    (stage,) = prov["stages"]
    assert stage["name"] == "multiview"
    return stage["report"], prov["output"]["episodes"]


def test_run_summary_provenance_and_info_count_dropped_views(tmp_path, raw, expected, capsys):
    config = _config(tmp_path, raw, "one")
    assert main(["run", str(config), "--no-progress"]) == 0
    out = capsys.readouterr().out
    line = ", ".join(f"{k} {v}" for k, v in expected.items())
    assert f"stage 1 multiview: {line}" in out.splitlines()
    report, episodes = _report(tmp_path / "one")
    assert report == expected and episodes == expected["views_kept"]
    assert main(["info", str(tmp_path / "one")]) == 0
    assert f"    report: {line}" in capsys.readouterr().out.splitlines()
    assert f"counted: {line}" in (tmp_path / "one" / "README.md").read_text()


def test_two_workers_count_the_same(tmp_path, raw, expected):
    dest = run_pipeline(load_pipeline_config(_config(tmp_path, raw, "two")), workers=2, progress=False)
    assert _report(dest) == (expected, expected["views_kept"])


def test_resumed_run_counts_finished_episodes_once(tmp_path, raw, expected, monkeypatch):
    config = load_pipeline_config(_config(tmp_path, raw, "resumed"))
    process = Multiview.process

    def stop_at_episode_3(self, episode, rng):
        if episode.meta["source_episode_index"] == 3:
            raise KeyboardInterrupt  # as if the run were killed here
        yield from process(self, episode, rng)

    monkeypatch.setattr(Multiview, "process", stop_at_episode_3)
    with pytest.raises(KeyboardInterrupt):
        run_pipeline(config, progress=False)
    parts = sorted(p.name for p in (work_dir_for(tmp_path / "resumed") / "parts").glob(f"*.{PART_SUFFIX}"))
    assert len(parts) == 3  # episodes 0-2 finished (2 without any view), their counts kept with them
    monkeypatch.setattr(Multiview, "process", process)
    dest = run_pipeline(config, progress=False)
    assert _report(dest) == (expected, expected["views_kept"])


def test_a_stage_that_counts_nothing_has_no_report(tmp_path, raw):
    path = tmp_path / "trim.toml"
    path.write_text(
        f'[[sources]]\npath = "{raw}"\n[[stages]]\nname = "trim"\nparams = {{ head = 1 }}\n'
        f'[destination]\nroot = "{tmp_path / "trim"}"\n'
    )
    dest = run_pipeline(load_pipeline_config(path), progress=False)
    prov = json.loads((dest / "meta" / "shiftkit_provenance.json").read_text())
    assert prov["stages"][0]["name"] == "trim" and "report" not in prov["stages"][0]
