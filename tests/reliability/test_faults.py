"""Faults: SIGKILL of `shiftkit run` at random points (resume gives the clean run's bytes and no
worker outlives its parent), two runs on one destination, a full disk, runs that cannot resume,
a killed `collect`, and evaluating a run stopped mid-training."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from shiftkit.datasets.synthetic import write_synthetic_raw
from tests.helpers import dataset_bytes, finished_parts, shiftkit_process, sigkill_when, survivors
from tests.reliability.harness import cli

KILL_SEEDS = (0, 1, 2)  # one SIGKILL at a random point of the run per seed
WORKERS = 2


def _config(tmp: Path, raw: Path, dest: str, stages: str = "") -> Path:
    path = tmp / f"{dest}.toml"
    path.write_text(f'[[sources]]\npath = "{raw}"\n{stages}\n[destination]\nroot = "{dest}"\nrepo_id = "me/k"\n')
    return path


def test_sigkill_then_resume(tmp_path):
    """SIGKILL the main process at a seeded random point (after k finished parts, or while the
    dataset is being written) while its pool works; every worker exits with it; the re-run
    resumes and writes the clean run's bytes."""
    from shiftkit.pipelines.config import load_pipeline_config
    from shiftkit.pipelines.runner import run_pipeline

    raw = write_synthetic_raw(tmp_path / "raw", episodes=10, length=20, seed=5, camera=(16, 24))
    stages = '[[stages]]\nname = "subsample"\nparams = { every = 2 }'
    run_pipeline(load_pipeline_config(_config(tmp_path, raw, "clean", stages)), progress=False)
    injected = 0
    for seed in KILL_SEEDS:
        rng = np.random.default_rng(seed)
        dest = f"killed{seed}"
        config = _config(tmp_path, raw, dest, stages)
        at_parts = int(rng.integers(1, 10)) if rng.random() < 0.75 else None  # else: while writing

        def ready(dest=dest, at_parts=at_parts) -> bool:
            if at_parts is None:
                return any(tmp_path.glob(f".{dest}.partial-*"))
            return finished_parts(tmp_path / dest) >= at_parts

        proc = shiftkit_process("run", str(config), "--no-progress", "--workers", str(WORKERS), cwd=tmp_path)
        seen = sigkill_when(proc, ready)
        injected += seen is not None
        workers = seen or set()
        assert not survivors(workers), f"seed {seed}: workers outlived their killed parent"
        run_pipeline(load_pipeline_config(config), progress=False)  # resume (any executor gives the same bytes)
        assert dataset_bytes(tmp_path / dest) == dataset_bytes(tmp_path / "clean"), (
            f"seed {seed}: resumed output differs"
        )
        assert not list(tmp_path.glob(f".{dest}*")), "work directory or lock left behind"
    assert injected >= 1, "no kill landed inside a run"


@pytest.mark.slow
def test_sigkill_of_a_ray_run_leaves_no_ray_process(tmp_path):
    """SIGKILL `shiftkit run --executor ray` while its Ray workers transform episodes: every process
    the run started (its local Ray cluster, rank workers, agents) exits. Ray tears its cluster down
    with the driver; its agents notice the dead raylet within about a minute (measured ~70 s)."""
    import psutil

    from shiftkit.pipelines.work import PART_SUFFIX, work_dir_for

    raw = write_synthetic_raw(tmp_path / "raw", episodes=40, length=20, seed=5, camera=(16, 24))
    config = _config(tmp_path, raw, "ray_out")
    parts_dir = work_dir_for(tmp_path / "ray_out") / "parts"
    proc = subprocess.Popen(
        [sys.executable, "-m", "shiftkit.app.cli", "run", str(config), "--no-progress", "--executor", "ray"]
        + ["--workers", str(WORKERS)],
        cwd=tmp_path,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    started: set[int] = set()
    deadline = time.monotonic() + 180
    while proc.poll() is None and time.monotonic() < deadline:
        try:
            started |= {c.pid for c in psutil.Process(proc.pid).children(recursive=True)}
        except psutil.NoSuchProcess:
            break
        if parts_dir.is_dir() and len(list(parts_dir.glob(f"*.{PART_SUFFIX}"))) >= 2:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before its workers wrote two parts: nothing to kill"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    left = survivors(started, within=150, poll=1.0)
    assert len(started) > WORKERS, "the Ray processes were not seen"
    assert not left, "Ray processes outlived the killed run"


def test_second_run_on_same_destination_is_refused(tmp_path, rel_raw):
    from shiftkit.datasets.staging import DestinationLock

    config = _config(tmp_path, rel_raw, "out")
    with DestinationLock(tmp_path / "out"):
        outcome = cli(["run", str(config), "--no-progress"])
    assert outcome.code == 2 and f"pid {os.getpid()}" in outcome.error_line, outcome
    assert cli(["run", str(config), "--no-progress"]).code == 0  # released: the next run works


@pytest.mark.parametrize("command", ["train bc", "train vpace", "fire"])
def test_second_training_run_on_same_output_is_refused(tmp_path, rel_ds, command):
    """Two trainers on one --output: the second is told another run holds it (not a resume mismatch)."""
    from shiftkit.datasets.staging import DestinationLock

    run = tmp_path / "run"
    argv = {
        "train bc": ["train", "bc", "--dataset", str(rel_ds), "--steps", "2", "--no-progress"],
        "train vpace": ["train", "vpace", "--examples", str(rel_ds), "--main-task", "reach"],
        "fire": ["fire", "--dataset", str(rel_ds), "--env", "panda-play", "--task", "reach"],
    }[command]
    with DestinationLock(run):
        outcome = cli([*argv, "--output", str(run)])
    assert outcome.code == 2 and f"another shiftkit run (pid {os.getpid()})" in outcome.error_line, outcome
    assert not run.exists()


def test_a_trainer_failing_early_leaves_no_folder(tmp_path):
    """The output's lock makes its parent folders; a run refused before any work removes them again."""
    outcome = cli(["train", "bc", "--dataset", str(tmp_path / "none"), "--output", str(tmp_path / "a" / "b" / "run")])
    assert outcome.code == 2 and not (tmp_path / "a").exists(), outcome


def test_stale_lock_of_a_dead_run_is_taken_over(tmp_path, rel_raw):
    config = _config(tmp_path, rel_raw, "out")
    (tmp_path / ".out.shiftkit-work.lock").write_text("999999\n")  # a SIGKILLed run's lock file
    outcome = cli(["run", str(config), "--no-progress"])
    assert outcome.code == 0, outcome
    assert not (tmp_path / ".out.shiftkit-work.lock").exists()


def test_disk_full_is_one_line_and_restart_discards_work(tmp_path, rel_raw, monkeypatch):
    from shiftkit.pipelines import work

    config = _config(tmp_path, rel_raw, "out")
    real = work.PartStore.write
    calls = {"n": 0}

    def write(self, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] > 2:
            raise OSError(errno.ENOSPC, "No space left on device", str(self.dir / "x.tree"))
        return real(self, *args, **kwargs)

    monkeypatch.setattr(work.PartStore, "write", write)
    outcome = cli(["run", str(config), "--no-progress"])
    assert outcome.code == 2 and "no space left" in outcome.error_line and ".out.shiftkit-work" in outcome.error_line
    assert " MB" in outcome.error_line and "--restart" in outcome.error_line
    monkeypatch.setattr(work.PartStore, "write", real)
    outcome = cli(["run", str(config), "--no-progress", "--restart"])
    assert outcome.code == 0, outcome
    assert not (tmp_path / ".out.shiftkit-work").exists()


def test_run_that_cannot_resume_removes_its_work(tmp_path, rel_raw):
    stages = '[[stages]]\nname = "filter"\nparams = { min_length = 1000 }'
    outcome = cli(["run", str(_config(tmp_path, rel_raw, "out", stages)), "--no-progress"])
    assert outcome.code == 2, outcome
    assert not list(tmp_path.glob(".out*")), "a run that can never resume left its work directory"


def test_killed_collect_leftovers_are_cleaned_safely(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    leftovers = [tmp_path / f".raw.partial-{dead.pid}-0123abcd", tmp_path / f".raw.collect-{dead.pid}-0123abcd"]
    live = tmp_path / f".raw.partial-{os.getpid()}-0123abcd"  # a recorder still running: not ours to remove
    foreign = tmp_path / ".other.partial-1-0123abcd"
    for folder in [*leftovers, live, foreign]:
        folder.mkdir()
    outcome = cli(["collect", "--task", "reach", "--episodes", "1", "--out", str(tmp_path / "raw"), "--no-progress"])
    assert outcome.code == 0, outcome
    assert not any(p.exists() for p in leftovers) and live.exists() and foreign.exists()


def _dead_pid() -> int:
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    return dead.pid


def _writers(tmp: Path, raw: Path) -> dict[str, list[str]]:
    from tests.test_import_lerobot_v21 import _write_v21
    from tests.test_import_robomimic import _write

    return {
        "import lerobot-v2.1": ["import", "lerobot-v2.1", str(_write_v21(tmp / "src")), "--repo-id", "me/x"],
        "import robomimic": ["import", "robomimic", str(_write(tmp / "d.hdf5")), "--repo-id", "me/x"],
        "run": ["run", str(_config(tmp, raw, "out")), "--no-progress"],
    }


@pytest.mark.parametrize("command", ["import lerobot-v2.1", "import robomimic", "run"])
def test_every_writer_removes_a_dead_writers_staging_folder(tmp_path, rel_raw, command):
    """What a SIGKILLed writer into `out` left (`.out.partial-<pid>-<hex>`) goes with the next
    successful writer into `out`, whichever command; a live writer's folder stays."""
    argv = _writers(tmp_path, rel_raw)[command]
    if command != "run":
        argv += ["--root", str(tmp_path / "out")]
    dead = tmp_path / f".out.partial-{_dead_pid()}-0123abcd"
    live = tmp_path / f".out.partial-{os.getpid()}-0123abcd"
    for folder in (dead, live):
        (folder / "data").mkdir(parents=True)
    outcome = cli(argv)
    assert outcome.code == 0, outcome
    assert not dead.exists() and live.exists() and (tmp_path / "out" / "meta" / "info.json").is_file()


def test_sigkilled_v21_import_leftovers_go_with_the_next_import(tmp_path):
    """SIGKILL `import lerobot-v2.1` while it converts: its staging folder stays; the re-run succeeds
    and removes it (the killed process's pid is in the folder's name)."""
    from tests.test_import_lerobot_v21 import _write_v21

    src = _write_v21(tmp_path / "src")
    args = ("import", "lerobot-v2.1", str(src), "--repo-id", "me/x", "--root", str(tmp_path / "out"))
    proc = shiftkit_process(*args, cwd=tmp_path)
    assert sigkill_when(proc, lambda: any(tmp_path.glob(".out.partial-*"))) is not None, "the import ended first"
    assert list(tmp_path.glob(f".out.partial-{proc.pid}-*")) and not (tmp_path / "out").exists()
    outcome = cli(list(args))
    assert outcome.code == 0, outcome
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "src"]


def test_collect_beaten_to_its_destination_leaves_nothing(tmp_path, monkeypatch):
    """Two `collect --out raw` at once: the one that finishes second gets a one-line error and its
    staging folder goes (the other's dataset stays)."""
    from shiftkit.datasets.sources import raw as raw_module

    write_index = raw_module.RawDatasetWriter._write_index

    def beaten(self) -> None:
        write_index(self)
        self.out_dir.mkdir()  # the other recorder renamed its dataset into place meanwhile
        (self.out_dir / "dataset.json").write_text("{}")

    monkeypatch.setattr(raw_module.RawDatasetWriter, "_write_index", beaten)
    outcome = cli(["collect", "--task", "reach", "--episodes", "1", "--out", str(tmp_path / "raw"), "--no-progress"])
    assert outcome.code == 2 and "another run wrote it meanwhile" in outcome.error_line, outcome
    assert sorted(p.name for p in tmp_path.iterdir()) == ["raw"]
    assert (tmp_path / "raw" / "dataset.json").read_text() == "{}"


@pytest.mark.parametrize("command", ["collect", "run", "import robomimic"])
def test_a_destination_name_of_250_characters_works(tmp_path, rel_raw, command):
    """A legal 250-character destination name never fails on shiftkit's temporary or work names."""
    name = "d" * 250
    argv = {
        "collect": ["collect", "--task", "reach", "--episodes", "1", "--out", str(tmp_path / name), "--no-progress"],
        "run": ["run", str(_config(tmp_path, rel_raw, name)), "--no-progress"],
        "import robomimic": [*_writers(tmp_path, rel_raw)["import robomimic"], "--root", str(tmp_path / name)],
    }[command]
    outcome = cli(argv)
    assert outcome.code == 0, outcome
    assert (tmp_path / name).is_dir() and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_reader_closing_stdout_early_is_not_an_error(tmp_path, rel_ds):
    """`shiftkit info ds | head -0`: the reader is gone before info prints; info ends quietly, exit 0."""
    proc = shiftkit_process("info", str(rel_ds), cwd=tmp_path)
    proc.stdout.close()  # the reader leaves before the first line
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 0 and err.decode().strip() == "", err.decode()


def test_eval_warns_when_the_run_did_not_finish(tmp_path, rel_ds, caplog):
    from shiftkit.policies.run_dir import CARD_METRICS

    run = tmp_path / "run"
    args = ["train", "bc", "--dataset", str(rel_ds), "--output", str(run), "--regime", "fixed", "--steps", "2"]
    assert cli([*args, "--ensemble", "1", "--hidden", "8", "--no-progress"]).code == 0
    (run / CARD_METRICS).unlink()  # as if training had been killed before its end
    outcome = cli(
        ["eval", "--policy", str(run), "--task", "reach", "--episodes", "1", "--out", str(tmp_path / "e.json")]
    )
    assert outcome.clean, outcome  # (this synthetic policy's inputs do not fit panda-play: a one-line error)
    assert "has not finished training" in caplog.text and "step-00000002.safetensors" in caplog.text


def test_watchdog_ends_a_worker_whose_parent_was_killed():
    """The parent-death watchdog that every executor's workers arm (init_worker, datatrove's step)."""
    code = (
        "import os, sys, time\n"
        "from shiftkit.pipelines import work\n"
        "pid = os.fork()\n"
        "if pid == 0:\n"
        "    work._WORKER.clear(); work.exit_with_parent(os.getppid(), period=0.1)\n"
        "    print(os.getpid(), flush=True); time.sleep(60); sys.exit(0)\n"
        "time.sleep(60)\n"
    )
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, start_new_session=True)
    child = int(parent.stdout.readline())
    os.kill(parent.pid, signal.SIGKILL)
    parent.wait()
    assert not survivors({child}, within=10, poll=0.1)
