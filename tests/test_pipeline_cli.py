"""Pipelines through the real `shiftkit` CLI: plan, run, kill + resume, bad inputs, lerobot-train."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from shiftkit.app.cli import main
from tests.helpers import lerobot_train_two_steps, tree_hashes

PIPELINE = """
seed = 1
[[sources]]
path = "{raw}"
[[stages]]
name = "trim"
params = {{ head = 1 }}
[destination]
root = "{dest}"
repo_id = "test/pipe"
"""


def write_config(tmp_path, raw, dest, text=PIPELINE, name="p.toml"):
    path = tmp_path / name
    path.write_text(text.format(raw=raw, dest=dest))
    return path


def shiftkit(*args, **kw):
    return subprocess.run(
        [sys.executable, "-m", "shiftkit.app.cli", *map(str, args)], capture_output=True, text=True, **kw
    )


def test_help_lists_commands():
    out = shiftkit("--help")
    assert out.returncode == 0
    for cmd in ("demo", "plan", "run", "info", "validate"):
        assert cmd in out.stdout


def test_plan_prints_schema_and_writes_nothing(tmp_path, synthetic_raw, capsys):
    config = write_config(tmp_path, synthetic_raw, tmp_path / "out")
    assert main(["plan", str(config)]) == 0
    out = capsys.readouterr().out
    assert "observation.state" in out and "trim v2" in out
    assert not (tmp_path / "out").exists()


def test_run_info_validate(tmp_path, synthetic_raw, capsys):
    config = write_config(tmp_path, synthetic_raw, tmp_path / "out")
    assert main(["run", str(config), "--no-progress"]) == 0
    assert main(["validate", str(tmp_path / "out")]) == 0
    assert "quality: " in capsys.readouterr().out  # the verdict on what `run` wrote
    assert main(["info", str(tmp_path / "out"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["episodes"] == 5 and info["provenance"]["stages"][0]["name"] == "trim"
    assert info["provenance"]["pipeline"]["destination"]["repo_id"] == "test/pipe"
    card = (tmp_path / "out" / "README.md").read_text()
    assert f"{info['episodes']} episodes, {info['frames']} frames at 10 fps" in card and "`trim` v2" in card


def test_two_workers_give_the_same_bytes(tmp_path, synthetic_raw):
    config = write_config(tmp_path, synthetic_raw, tmp_path / "a")
    assert main(["run", str(config), "--no-progress", "--workers", "2"]) == 0
    one = write_config(tmp_path, synthetic_raw, tmp_path / "b", name="q.toml")
    assert main(["run", str(one), "--no-progress"]) == 0
    a, b = tree_hashes(tmp_path / "a"), tree_hashes(tmp_path / "b")
    # Only the provenance (executor fields, destination) and the card may differ.
    differing = {k for k in a if a[k] != b.get(k)}
    assert differing <= {"meta/shiftkit_provenance.json", "README.md"}


@pytest.mark.slow
def test_sigkill_then_resume(tmp_path):
    from shiftkit.datasets.synthetic import write_synthetic_raw

    raw = write_synthetic_raw(tmp_path / "raw", episodes=120, length=30, seed=3, camera=(48, 64))
    before = tree_hashes(raw)
    dest = tmp_path / "out"
    config = write_config(tmp_path, raw, dest)
    work = tmp_path / ".out.shiftkit-work" / "parts"
    proc = subprocess.Popen(
        [sys.executable, "-m", "shiftkit.app.cli", "run", str(config), "--no-progress"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        if work.exists() and len([p for p in work.iterdir() if ".tmp-" not in p.name]) >= 5:
            break
        time.sleep(0.01)
    assert proc.poll() is None, "the run finished before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not dest.exists(), "a killed run must leave no dataset at the destination"
    done_before = len([p for p in work.iterdir() if ".tmp-" not in p.name])

    resumed = shiftkit("run", config, "--no-progress")
    assert resumed.returncode == 0, resumed.stderr
    n_resumed = int(resumed.stderr.split("resuming: ")[1].split(" of ")[0])
    assert n_resumed >= min(done_before, 5) - 1
    assert tree_hashes(raw) == before
    assert not (tmp_path / ".out.shiftkit-work").exists()

    clean = write_config(tmp_path, raw, tmp_path / "clean", name="clean.toml")
    assert shiftkit("run", clean, "--no-progress").returncode == 0
    a, b = tree_hashes(dest), tree_hashes(tmp_path / "clean")
    assert {k for k in a if a[k] != b.get(k)} <= {"meta/shiftkit_provenance.json", "README.md"}


def _corrupt_parquet(tmp_path, raw):
    from tests.helpers import write_raw_as_lerobot

    ds = write_raw_as_lerobot(raw, "test/c", tmp_path / "lr")
    data = ds / "data" / "chunk-000" / "file-000.parquet"
    data.write_bytes(data.read_bytes()[: len(data.read_bytes()) // 2])
    return write_config(tmp_path, ds, tmp_path / "out")


def _nan_action(tmp_path, raw):
    path = raw / "episode_000002" / "arrays" / "action.npy"
    a = np.load(path)
    a[3, 0] = np.nan
    np.save(path, a)
    return write_config(tmp_path, raw, tmp_path / "out")


def _mismatched_lengths(tmp_path, raw):
    path = raw / "episode_000001" / "arrays" / "state.npy"
    np.save(path, np.load(path)[:-2])
    return write_config(tmp_path, raw, tmp_path / "out")


@pytest.mark.parametrize(
    "make_config, message",
    [
        (lambda t, r: write_config(t, t / "missing", t / "out"), "source path not found"),
        (lambda t, r: write_config(t, r, t / "out", PIPELINE.replace('"trim"', '"trimm"')), "unknown stage 'trimm'"),
        (lambda t, r: write_config(t, r, t / "out", PIPELINE.replace("head = 1", "haed = 1")), "unknown key 'haed'"),
        (
            lambda t, r: write_config(t, r, t / "out", PIPELINE.replace("head = 1", 'head = "one"')),
            "head: expected int",
        ),
        (lambda t, r: (t / "out").mkdir() or write_config(t, r, t / "out"), "destination already exists"),
        (lambda t, r: write_config(t, r, t / "out", PIPELINE + "bogus = 1\n"), "unknown key 'bogus'"),
        (lambda t, r: t / "nope.toml", "pipeline config not found"),
        (_corrupt_parquet, "unreadable parquet file"),
        (_nan_action, "'action' contains NaN"),
        (_mismatched_lengths, "'state' has 10 frames, 'timestamp' has 12"),
    ],
    ids=[
        "missing-source",
        "unknown-stage",
        "unknown-key",
        "wrong-type",
        "destination-exists",
        "unknown-top-key",
        "missing-config",
        "corrupt-parquet",
        "nan-action",
        "mismatched-lengths",
    ],
)
def test_bad_input_one_line_error(tmp_path, synthetic_raw, capsys, make_config, message):
    config = make_config(tmp_path, synthetic_raw)
    raw_before = tree_hashes(synthetic_raw)
    code = main(["run", str(config), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert message in err and "Traceback" not in err and len(err.splitlines()) == 1, err
    if "destination" not in message:
        assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())
    assert tree_hashes(synthetic_raw) == raw_before
    assert not list(tmp_path.glob(".out.partial-*"))


def test_cli_error_is_one_line_in_a_real_process(tmp_path):
    out = shiftkit("run", tmp_path / "missing.toml")
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == [
        f"shiftkit run: error: pipeline config not found: {tmp_path / 'missing.toml'}"
    ]


@pytest.mark.slow
def test_lerobot_train_act_on_pipeline_output(tmp_path, synthetic_raw):
    """lerobot's own trainer (ACT, CPU, offline, 2 steps) trains on a shiftkit dataset."""
    config = write_config(tmp_path, synthetic_raw, tmp_path / "ds")
    assert main(["run", str(config), "--no-progress"]) == 0
    lerobot_train_two_steps("test/pipe", tmp_path / "ds", tmp_path / "train")


def test_validate_reports_broken_datasets(tmp_path, synthetic_raw, capsys):
    from tests.helpers import write_raw_as_lerobot

    ds = write_raw_as_lerobot(synthetic_raw, "test/v", tmp_path / "ds")
    assert main(["validate", str(ds)]) == 0
    info = json.loads((ds / "meta" / "info.json").read_text())
    (ds / "meta" / "info.json").write_text(json.dumps({**info, "total_frames": info["total_frames"] + 3}))
    capsys.readouterr()
    assert main(["validate", str(ds)]) == 2
    assert "frames in the data, info.json says" in capsys.readouterr().err
    (ds / "data" / "chunk-000" / "file-000.parquet").unlink()
    assert main(["validate", str(ds)]) == 2
    assert "data file is missing" in capsys.readouterr().err
    assert main(["info", str(tmp_path / "nothing")]) == 2
    assert "dataset not found" in capsys.readouterr().err
