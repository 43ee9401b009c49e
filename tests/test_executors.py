"""Executors on datatrove (local processes, a local Ray instance, SLURM job files): the same
pipeline gives the same dataset bytes as the default local executor; failing shards are retried
and a shard that keeps failing leaves no dataset and an error naming the episode. A real SLURM
cluster and a two-node Ray cluster: tests/test_cluster_slurm.py, tests/test_cluster_ray.py."""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import pytest

from shiftkit.datasets.errors import ConfigError, DatasetError
from shiftkit.pipelines.config import load_pipeline_config
from shiftkit.pipelines.runner import run_pipeline
from shiftkit.pipelines.stage import Stage, register_stage
from shiftkit.pipelines.work import work_dir_for
from tests.helpers import dataset_bytes

PIPELINE = """
seed = 3
[[sources]]
path = "{raw}"
[[stages]]
name = "trim"
params = {{ head = 1 }}
{extra}
[destination]
root = "{dest}"
repo_id = "test/executors"
"""


@pytest.fixture
def raw(tmp_path):
    """6 episodes with a camera and two tasks (task indices must survive the merge)."""
    from shiftkit.datasets.synthetic import write_synthetic_raw

    return write_synthetic_raw(tmp_path / "raw", episodes=6, length=8, seed=4, camera=(12, 16), tasks=("reach", "push"))


def write_config(tmp_path: Path, raw: Path, name: str, extra: str = "") -> Path:
    """`tmp_path/<name>.toml`: `raw` trimmed (plus the stages in `extra`) into `tmp_path/<name>`."""
    path = tmp_path / f"{name}.toml"
    path.write_text(PIPELINE.format(raw=raw, dest=tmp_path / name, extra=extra))
    return path


def config_for(tmp_path, raw, name, extra=""):
    return load_pipeline_config(write_config(tmp_path, raw, name, extra))


def assert_same_dataset(a: Path, b: Path) -> None:
    """The same bytes in every file but the provenance and the card rendered from it, and those
    equal apart from the executor fields and the destination (every executor writes its dataset
    with the same ordered writer pass)."""
    assert dataset_bytes(a) == dataset_bytes(b)
    pa_, pb = (json.loads((r / "meta/shiftkit_provenance.json").read_text()) for r in (a, b))
    for p in (pa_, pb):
        p.pop("executor")
        p["pipeline"]["destination"].pop("root")
    assert pa_ == pb


@pytest.fixture(scope="module")
def local_ray():
    os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
    ray = pytest.importorskip("ray")
    for attempt in range(3):
        try:
            ray.init(num_cpus=2, include_dashboard=False, object_store_memory=100 * 1024**2, logging_level="WARNING")
            break
        except Exception as exc:  # Ray waits 30 s for its raylet: at load 20 on 2 cores it can miss that
            ray.shutdown()
            if attempt == 2 or "timed out during startup" not in str(exc):
                raise
    yield ray
    ray.shutdown()


# A stage that drops episodes and counts them (`Stage.report`): the counts come back from every
# executor's workers into the provenance.
FILTER = '[[stages]]\nname = "filter"\nparams = { keep_fraction = 0.6 }'


def test_ray_and_datatrove_local_match_the_local_executor(tmp_path, raw, local_ray):
    local = run_pipeline(config_for(tmp_path, raw, "local", FILTER), progress=False)
    ray_out = run_pipeline(
        config_for(tmp_path, raw, "ray", FILTER),
        workers=2,
        executor="ray",
        executor_options={"shard_episodes": 2},
        progress=False,
    )
    dt = run_pipeline(
        config_for(tmp_path, raw, "dt", FILTER),
        workers=2,
        executor="datatrove-local",
        executor_options={"shard_episodes": 4},
        progress=False,
    )
    for other in (ray_out, dt):
        assert_same_dataset(local, other)  # provenance included
        assert not work_dir_for(other).exists()
    prov = json.loads((ray_out / "meta/shiftkit_provenance.json").read_text())
    assert prov["executor"] == {"name": "ray", "workers": 2, "nodes": 1, "address": None}
    kept = prov["output"]["episodes"]
    assert 0 < kept < 6 and prov["stages"][1]["report"] == {"episodes_dropped": 6 - kept}
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset("test/executors", root=ray_out)
    assert ds.num_episodes == kept and int(ds[len(ds) - 1]["index"]) == len(ds) - 1


def _state_file(raw: Path, i: int) -> Path:
    index = json.loads((raw / "dataset.json").read_text())
    return raw / index["episodes"][i]["name"] / "arrays" / "state.npy"


@pytest.mark.parametrize("executor", ["datatrove-local", "ray"])
def test_a_shard_that_keeps_failing_leaves_no_dataset(tmp_path, raw, executor, request):
    if executor == "ray":
        request.getfixturevalue("local_ray")
    state = _state_file(raw, 3)
    good = state.read_bytes()
    state.write_bytes(b"not an array")
    config = config_for(tmp_path, raw, "out")
    with pytest.raises(DatasetError) as err:
        run_pipeline(config, workers=2, executor=executor, executor_options={"shard_episodes": 2}, progress=False)
    message = str(err.value)
    assert "\n" not in message
    assert "source 0 episode 3" in message and "unreadable array" in message and "3 times" in message
    assert not (tmp_path / "out").exists()
    assert not list(tmp_path.glob(".out.partial-*"))
    # Repaired input: the re-run resumes (finished parts and shards are kept) and completes.
    state.write_bytes(good)
    out = run_pipeline(config, workers=2, executor=executor, executor_options={"shard_episodes": 2}, progress=False)
    assert_same_dataset(run_pipeline(config_for(tmp_path, raw, "local"), progress=False), out)


@register_stage
class FlakyStage(Stage):
    """Test stage: fails the first time it sees each listed episode (a marker file remembers)."""

    name = "test-flaky"
    version = 1

    @dataclasses.dataclass
    class Config:
        marker_dir: str = ""
        """Where the first failure of each episode is remembered."""
        episodes: list = dataclasses.field(default_factory=list)
        """Source episode indices that fail once."""

    def transform_features(self, features):
        return features

    def process(self, episode, rng):
        index = int(episode.meta["source_episode_index"])
        marker = Path(self.config.marker_dir) / f"failed-{index}"
        if index in self.config.episodes and not marker.exists():
            marker.touch()
            raise RuntimeError(f"transient failure on episode {index}")
        yield episode


def test_a_failed_shard_is_retried(tmp_path, raw):
    markers = tmp_path / "markers"
    markers.mkdir()
    extra = f'[[stages]]\nname = "test-flaky"\nparams = {{ marker_dir = "{markers}", episodes = [1, 4] }}'
    out = run_pipeline(
        config_for(tmp_path, raw, "flaky", extra),
        executor="datatrove-local",
        executor_options={"shard_episodes": 2},
        progress=False,
    )
    assert sorted(p.name for p in markers.iterdir()) == ["failed-1", "failed-4"]  # each failed once
    local = run_pipeline(config_for(tmp_path, raw, "plain", extra), progress=False)  # markers exist: no failure
    assert_same_dataset(local, out)


def test_slurm_writes_job_files_and_assembles_when_done(tmp_path, raw, monkeypatch):
    config = config_for(tmp_path, raw, "out")
    options = {"partition": "cpu", "shard_episodes": 2, "submit": False}
    assert run_pipeline(config, workers=2, executor="slurm", executor_options=options, progress=False) is None
    job = work_dir_for(tmp_path / "out") / "datatrove" / "slurm"
    script = (job / "launch_script.slurm").read_text()
    assert "#SBATCH --array=0-1" in script and "#SBATCH --partition=cpu" in script
    assert "launch_pickled_pipeline" in script and (job / "executor.pik").is_file() and (job / "README.md").is_file()
    assert not (tmp_path / "out").exists()
    # Run the array tasks as `launch_pickled_pipeline` does on the nodes (no scontrol here).
    import datatrove.executor.slurm
    import dill

    monkeypatch.setattr(datatrove.executor.slurm, "expand_slurm_nodelist", lambda nodes: [nodes])
    monkeypatch.setenv("SLURM_NODELIST", "localhost")
    for task in range(2):
        monkeypatch.setenv("SLURM_ARRAY_TASK_ID", str(task))
        dill.loads((job / "executor.pik").read_bytes()).run()
    out = run_pipeline(config, workers=2, executor="slurm", executor_options=options, progress=False)
    assert_same_dataset(run_pipeline(config_for(tmp_path, raw, "local"), progress=False), out)


def test_bad_executor_options_are_config_errors(tmp_path, raw):
    with pytest.raises(ConfigError, match="--partition"):
        run_pipeline(config_for(tmp_path, raw, "x"), executor="slurm", progress=False)
    with pytest.raises(ConfigError, match="does not take these options: address"):
        run_pipeline(
            config_for(tmp_path, raw, "x"), executor="local", executor_options={"address": "a:1"}, progress=False
        )
    with pytest.raises(ConfigError, match="unknown executor"):
        run_pipeline(config_for(tmp_path, raw, "x"), executor="dask", progress=False)


@register_stage
class KeepEveryOther(Stage):
    """Test stage with a dataset-level selection: keeps every other output episode."""

    name = "test-keep-every-other"
    version = 1

    @dataclasses.dataclass
    class Config:
        pass

    def transform_features(self, features):
        return features

    def process(self, episode, rng):
        yield episode

    def select(self, metas):
        return [k % 2 == 1 for k in range(len(metas))]


def test_dataset_level_selection_spans_shards(tmp_path, raw):
    extra = '[[stages]]\nname = "test-keep-every-other"'
    out = run_pipeline(
        config_for(tmp_path, raw, "sel", extra),
        executor="datatrove-local",
        executor_options={"shard_episodes": 2},
        progress=False,
    )
    local = run_pipeline(config_for(tmp_path, raw, "sel-local", extra), progress=False)
    assert json.loads((out / "meta/info.json").read_text())["total_episodes"] == 3
    assert_same_dataset(local, out)


def test_run_command_gives_the_slurm_executor_only_the_options_given(tmp_path, raw, capsys):
    # the job asks for the executor's own defaults (`SlurmSettings`) unless the command line sets one
    from shiftkit.app.cli import main

    argv = [
        "run",
        str(write_config(tmp_path, raw, "out")),
        "--executor",
        "slurm",
        "--partition",
        "cpu",
        "--no-submit",
        "--no-progress",
    ]
    assert main([*argv, "--cpus-per-task", "3"]) == 0
    script = (work_dir_for(tmp_path / "out") / "datatrove" / "slurm" / "launch_script.slurm").read_text()
    assert "#SBATCH --time=04:00:00" in script and "#SBATCH --cpus-per-task=3" in script
    assert "not written yet" in capsys.readouterr().out
