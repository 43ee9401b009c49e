"""No silent wrong results: each case once finished with exit 0 and wrong data before it was fixed."""

from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import DatasetError
from shiftkit.datasets.sources import SourceConfig
from shiftkit.datasets.synthetic import write_synthetic_raw
from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, StageSpec
from shiftkit.pipelines.stage import STAGES, StageContext, build_stage
from tests.helpers import tree_hashes
from tests.reliability.harness import cli

# Frame-rate-changing stages and the parameters to try, from their registration (`resampling_params`).
RESAMPLERS = {name: cls.resampling_params for name, cls in STAGES.items() if cls.resampling_params}
EVENT_EXAMPLES = 40


def test_every_frame_rate_stage_is_covered():
    changes_fps = {name for name, cls in STAGES.items() if _changes_fps(name, cls.example_params)}
    assert {"subsample", "resample"} <= changes_fps
    assert changes_fps <= set(RESAMPLERS), f"give {changes_fps - set(RESAMPLERS)} resampling_params"


def test_a_frame_rate_stage_must_give_resampling_params():
    from shiftkit.pipelines.stage import Stage, register_stage

    class Halve(Stage):
        name, version, Config = "halve_fps", 1, dict

        def transform_fps(self, fps: int) -> int:
            return fps // 2

        def transform_features(self, features):
            return features

        def process(self, episode, rng):
            yield episode

    with pytest.raises(TypeError, match="changes the frame rate but gives no resampling_params"):
        register_stage(Halve)
    assert "halve_fps" not in STAGES


def _changes_fps(name: str, params: dict | None) -> bool:
    if params is None:
        return False
    try:
        stage = build_stage(name, params, StageContext(fps=10), name)
    except Exception:
        return False
    return stage.transform_fps(10) != 10


@settings(max_examples=EVENT_EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    name=st.sampled_from(sorted(RESAMPLERS)),
    length=st.integers(1, 40),
    success_from_end=st.integers(1, 3),
    data=st.data(),
)
def test_resampling_keeps_episode_end_events(name, length, success_from_end, data):
    """An episode ending in success (only its last frames flagged) still does after any resampling;
    `next.done` likewise; and no event appears where none was."""
    params = {k: data.draw(st.sampled_from(v), label=k) for k, v in RESAMPLERS[name].items()}
    if name == "subsample" and params["offset"] >= params["every"]:
        params["offset"] = 0
    stage = build_stage(name, params, StageContext(fps=60), name)
    success = np.zeros((length, 1), bool)
    success[-min(success_from_end, length) :] = True
    done = np.zeros((length, 1), bool)
    done[-1] = True
    episode = Episode(
        {
            "timestamp": np.arange(length) / 60.0,
            "action": np.zeros((length, 2), np.float32),
            "next.success": success,
            "next.done": done,
            "task": np.array(["t"] * length),
        },
        {"source_episode_index": 0},
    )
    outputs = list(stage.process(episode, np.random.default_rng(0)))
    for out in outputs:
        assert out.frames["next.success"][-1].all(), f"{name} {params} lost the success of a {length}-frame episode"
        assert out.frames["next.done"][-1].all() and not out.frames["next.done"][:-1].any()
        assert out.frames["next.success"].dtype == bool


def test_subsample_keeps_success_in_readme_tour(tmp_path):
    """The README tour case: scripted episodes flag success on their last frame only, and `every = 2`
    on even-length episodes dropped it (3 of 6 success episodes lost their flag)."""
    from shiftkit.datasets.reader import open_lerobot_dataset
    from shiftkit.pipelines.runner import run_pipeline

    raw = write_synthetic_raw(tmp_path / "raw", episodes=6, length=12, seed=4)
    lengths = []
    for i in range(6):
        path = raw / f"episode_{i:06d}/arrays/success.npy"
        success = np.zeros(len(np.load(path)), bool)
        success[-1] = i % 3 != 2  # episodes 2 and 5 fail
        np.save(path, success)
        lengths.append(len(success))
    assert any(n % 2 == 0 for n in lengths)
    config = PipelineConfig(
        sources=[SourceConfig(path=str(raw))],
        destination=DestinationConfig(root=str(tmp_path / "out")),
        stages=[StageSpec(name="subsample", params={"every": 2})],
    )
    run_pipeline(config, progress=False)
    out = [ep.frames["next.success"] for ep in open_lerobot_dataset(tmp_path / "out").iter_episodes()]
    assert [bool(s[-1].any()) for s in out] == [i % 3 != 2 for i in range(6)]
    assert [int(s.sum()) for s in out] == [int(i % 3 != 2) for i in range(6)]  # no success invented


def _interrupted_run(config, monkeypatch, after: int) -> None:
    """A run that dies (not a user error) after `after` finished parts, leaving its work directory."""
    from shiftkit.pipelines import runner, work

    real = work.PartStore.write
    calls = {"n": 0}

    def write(self, *args, **kwargs):
        if calls["n"] == after:
            raise RuntimeError("simulated crash")
        calls["n"] += 1
        return real(self, *args, **kwargs)

    monkeypatch.setattr(work.PartStore, "write", write)
    with pytest.raises(RuntimeError):
        runner.run_pipeline(config, progress=False)
    monkeypatch.setattr(work.PartStore, "write", real)


def test_stale_parts_are_not_reused_after_the_source_changed(tmp_path, monkeypatch):
    from shiftkit.pipelines.runner import run_pipeline
    from shiftkit.pipelines.work import PART_SUFFIX, work_dir_for

    raw = tmp_path / "raw"
    write_synthetic_raw(raw, episodes=5, length=10, seed=1)
    config = lambda dest: PipelineConfig(  # noqa: E731
        sources=[SourceConfig(path=str(raw))], destination=DestinationConfig(root=str(tmp_path / dest))
    )
    _interrupted_run(config("out"), monkeypatch, after=3)
    assert len(list((work_dir_for(tmp_path / "out") / "parts").glob(f"*.{PART_SUFFIX}"))) == 3
    shutil.rmtree(raw)
    write_synthetic_raw(raw, episodes=5, length=10, seed=2)  # re-recorded: same path, same count
    run_pipeline(config("out"), progress=False)
    run_pipeline(config("clean"), progress=False)
    data = lambda root: {k: v for k, v in tree_hashes(root).items() if k.startswith("data/")}  # noqa: E731
    assert data(tmp_path / "out") == data(tmp_path / "clean")


def test_parts_are_reused_when_the_source_is_unchanged(tmp_path, monkeypatch, caplog):
    from shiftkit.pipelines.runner import run_pipeline

    raw = write_synthetic_raw(tmp_path / "raw", episodes=5, length=10, seed=1)
    config = PipelineConfig(
        sources=[SourceConfig(path=str(raw))], destination=DestinationConfig(root=str(tmp_path / "o"))
    )
    _interrupted_run(config, monkeypatch, after=3)
    run_pipeline(config, progress=False)
    assert "resuming: 3 of 5" in caplog.text


def test_16_bit_png_is_refused_not_squashed(tmp_path, rel_raw):
    import cv2

    from shiftkit.datasets.sources.raw import open_raw_dataset

    raw = shutil.copytree(rel_raw, tmp_path / "raw")
    png = next(raw.glob("episode_000000/images/*/frame_000000.png"))
    ok, data = cv2.imencode(".png", np.full((12, 16, 3), 4095, np.uint16))
    png.write_bytes(data.tobytes())
    with pytest.raises(DatasetError, match="16-bit"):
        open_raw_dataset(raw).read_episode(0)


def test_images_survive_a_non_utf8_folder(tmp_path):
    from shiftkit.datasets.sources.raw import RawDatasetWriter, open_raw_dataset

    out = tmp_path / os.fsdecode(b"raw\xfe\xff")
    frames = np.random.default_rng(0).integers(0, 255, (3, 6, 8, 3), dtype=np.uint8)
    with RawDatasetWriter(out, fps=10) as w:
        w.add_episode(
            {"timestamp": np.arange(3) / 10.0, "action": np.zeros((3, 1), np.float32)},
            {"cam": frames},
            meta={"task": "t"},
        )
    assert np.array_equal(open_raw_dataset(out).read_episode(0).frames["observation.images.cam"], frames)


def test_validate_deep_finds_data_not_matching_stats(tmp_path, rel_ds):
    import pyarrow.parquet as pq

    ds = shutil.copytree(rel_ds, tmp_path / "ds")
    assert cli(["validate", "--deep", str(ds)]).code == 0
    path = next((ds / "data").rglob("*.parquet"))
    table = pq.read_table(path)
    column = table.column("action").to_pylist()
    negated = [[-x for x in row] for row in column]
    import pyarrow as pa

    table = table.set_column(
        table.schema.get_field_index("action"), "action", pa.array(negated, table.schema.field("action").type)
    )
    pq.write_table(table, path)
    assert cli(["validate", str(ds)]).code == 0  # the shallow check cannot see it
    outcome = cli(["validate", "--deep", str(ds)])
    assert outcome.code == 2 and "'action'" in outcome.error_line and "stats.json" in outcome.error_line


def test_invalid_repo_ids_are_refused_before_any_work(tmp_path, rel_raw):
    toml = tmp_path / "p.toml"
    toml.write_text(f'[[sources]]\npath = "{rel_raw}"\n[destination]\nroot = "out"\nrepo_id = "bad id!!"\n')
    outcome = cli(["run", str(toml)])
    assert outcome.code == 2 and "invalid repo id" in outcome.error_line
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out*"))
    outcome = cli(["collect", "--task", "lift", "--lerobot", "bad id!!", "--root", str(tmp_path / "c")])
    assert outcome.code == 2 and "invalid repo id" in outcome.error_line


def test_train_bc_refuses_an_id_that_is_not_the_roots(tmp_path, rel_ds):
    outcome = cli(["train", "bc", "--dataset", "me/other", "--root", str(rel_ds), "--output", str(tmp_path / "run")])
    assert outcome.code == 2 and "me/lift" in outcome.error_line
    assert not (tmp_path / "run").exists()


def test_vpace_examples_must_be_an_example_set(tmp_path, rel_ds):
    from shiftkit.policies.trainers.vpace.example_buffer import load_dataset_examples

    with pytest.raises(DatasetError, match="success_examples"):
        load_dataset_examples([str(rel_ds)], ["reach"], require_example_set=True)
    from shiftkit.datasets.reader import open_lerobot_dataset

    examples, _ = load_dataset_examples([str(rel_ds)], ["reach"], require_example_set=False)
    assert len(examples["reach"].obs) == open_lerobot_dataset(rel_ds).info["total_frames"]  # the flag: every frame


def test_vpace_buffer_negative_pointer(tmp_path):
    from shiftkit.app.importers.vpace import read_vpace_buffer
    from tests.reliability.test_cli_errors import _buffer

    with pytest.raises(DatasetError, match="pointer -3"):
        read_vpace_buffer(_buffer(tmp_path, pointer=-3))


def test_collect_lerobot_provenance_names_real_seeds(tmp_path):
    outcome = cli(
        [
            "collect",
            "--task",
            "reach",
            "--episodes",
            "2",
            "--seed",
            "7",
            "--lerobot",
            "me/reach",
            "--root",
            str(tmp_path / "c"),
            "--no-progress",
        ]
    )
    assert outcome.code == 0, outcome
    text = (tmp_path / "c" / "meta" / "shiftkit_provenance.json").read_text()
    provenance = json.loads(text)
    assert provenance["sources"][0]["seeds"] == [7, 8] and provenance["seed"] == 7
    assert ".collect-" not in text and "/raw" not in text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c"]  # no temporary folder left
