"""Bad inputs a new user or a QA engineer tries against the CLI: each gives a one-line error and
exit 2 (or a correct result), never a traceback, and no input is modified."""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import pytest

from tests.reliability.harness import cli, tree_state

NON_UTF8 = os.fsdecode(b"raw\xff")


def pipeline(tmp: Path, source: Path, dest: str = "out", extra: str = "", seed: str = "0") -> str:
    path = tmp / "p.toml"
    path.write_text(f'seed = {seed}\n[[sources]]\npath = "{source}"\n{extra}\n[destination]\nroot = "{dest}"\n')
    return str(path)


def a_file(tmp: Path) -> Path:
    (tmp / "file").write_text("x")
    return tmp / "file"


def raw_with(tmp: Path, raw: Path, edit) -> Path:
    import shutil

    copy = tmp / "raw_copy"
    shutil.copytree(raw, copy)
    edit(copy)
    return copy


def _json_edit(rel: str, **values):
    def edit(root: Path) -> None:
        path = root / rel
        data = json.loads(path.read_text())
        data.update(values)
        path.write_text(json.dumps(data))

    return edit


# name -> (argv builder (tmp, raw, ds) -> argv, expected exit code)
CASES = {
    # collect
    "collect negative seed": (lambda t, r, d: ["collect", "--task", "lift", "--seed", "-1", "--out", str(t / "o")], 2),
    "collect width 0": (lambda t, r, d: ["collect", "--task", "lift", "--width", "0", "--out", str(t / "o")], 2),
    "collect episodes 0": (lambda t, r, d: ["collect", "--task", "lift", "--episodes", "0", "--out", str(t / "o")], 2),
    "collect unknown play task": (
        lambda t, r, d: ["collect", "--task", "lift", "--play", "--sequence", "reach,fly", "--out", str(t / "o")],
        2,
    ),
    "collect invalid repo id": (
        lambda t, r, d: ["collect", "--task", "lift", "--lerobot", "bad id!!", "--root", str(t / "o")],
        2,
    ),
    "collect out exists": (lambda t, r, d: ["collect", "--task", "lift", "--out", str(r)], 2),
    "collect parent is a file": (
        lambda t, r, d: ["collect", "--task", "lift", "--episodes", "1", "--out", str(a_file(t) / "o")],
        2,
    ),
    "collect unknown camera": (
        lambda t, r, d: ["collect", "--task", "lift", "--cameras", "x", "--out", str(t / "o")],
        2,
    ),
    # run / plan
    "run config missing": (lambda t, r, d: ["run", str(t / "nope.toml")], 2),
    "run config is a folder": (lambda t, r, d: ["run", str(t)], 2),
    "run invalid toml": (lambda t, r, d: ["run", str(_write(t / "p.toml", "[[sources]\n"))], 2),
    "run negative seed": (lambda t, r, d: ["run", pipeline(t, r, seed="-1")], 2),
    "run empty destination root": (lambda t, r, d: ["run", pipeline(t, r, dest="")], 2),
    "run invalid destination repo id": (lambda t, r, d: ["run", _bad_repo(t, r)], 2),
    "run source missing": (lambda t, r, d: ["run", pipeline(t, t / "missing")], 2),
    "run source without info.json": (lambda t, r, d: ["run", pipeline(t, _mkdir(t / "empty"))], 2),
    "run destination exists": (lambda t, r, d: ["run", pipeline(t, r, dest=str(d))], 2),
    "run destination parent is a file": (lambda t, r, d: ["run", pipeline(t, r, dest=str(a_file(t) / "o"))], 2),
    "run workers 0": (lambda t, r, d: ["run", pipeline(t, r), "--workers", "0"], 2),
    "run unknown executor": (lambda t, r, d: ["run", pipeline(t, r), "--executor", "nope"], 2),
    "run unknown stage": (lambda t, r, d: ["run", pipeline(t, r, extra='[[stages]]\nname = "nope"')], 2),
    "run bad stage param": (
        lambda t, r, d: ["run", pipeline(t, r, extra='[[stages]]\nname = "subsample"\nparams = { every = 0 }')],
        2,
    ),
    "plan non-UTF-8 raw folder": (lambda t, r, d: ["plan", _non_utf8_pipeline(t, r)], 0),
    "run non-UTF-8 raw folder": (lambda t, r, d: ["run", _non_utf8_pipeline(t, r, str(t / "out")), "--no-progress"], 0),
    "run into a non-UTF-8 folder": (lambda t, r, d: ["run", _non_utf8_pipeline(t, r), "--no-progress"], 2),
    "collect lerobot into a non-UTF-8 folder": (
        lambda t, r, d: ["collect", "--task", "lift", "--lerobot", "me/x", "--root", str(t / NON_UTF8)],
        2,
    ),
    "run raw meta.json task is a number": (
        lambda t, r, d: ["run", pipeline(t, raw_with(t, r, _json_edit("episode_000001/meta.json", task=5)))],
        2,
    ),
    "run raw meta.json is a list": (
        lambda t, r, d: ["run", pipeline(t, raw_with(t, r, lambda c: _write(c / "episode_000000/meta.json", "[1]")))],
        2,
    ),
    "run raw dataset.json episodes are numbers": (
        lambda t, r, d: ["run", pipeline(t, raw_with(t, r, _json_edit("dataset.json", episodes=[1, 2])))],
        2,
    ),
    "run raw dataset.json names is a list": (
        lambda t, r, d: ["run", pipeline(t, raw_with(t, r, _json_edit("dataset.json", names=["a"])))],
        2,
    ),
    "run raw dataset.json fps is text": (
        lambda t, r, d: ["run", pipeline(t, raw_with(t, r, _json_edit("dataset.json", fps="10")))],
        2,
    ),
    "run raw segments malformed": (
        lambda t, r, d: ["run", pipeline(t, raw_with(t, r, _json_edit("episode_000000/meta.json", segments=[5])))],
        2,
    ),
    "run raw 16-bit PNG": (lambda t, r, d: ["run", pipeline(t, raw_with(t, r, _png16))], 2),
    "run lerobot info.json fps is text": (
        lambda t, r, d: ["run", pipeline(t, raw_with(t, d, _json_edit("meta/info.json", fps="x")))],
        2,
    ),
    # info / validate
    "info raw folder": (lambda t, r, d: ["info", str(r)], 2),
    "validate raw folder": (lambda t, r, d: ["validate", str(r)], 2),
    "info folder without info.json": (lambda t, r, d: ["info", str(_mkdir(t / "empty"))], 2),
    "info a file": (lambda t, r, d: ["info", str(a_file(t))], 2),
    "info nothing": (lambda t, r, d: ["info", str(t / "nothing")], 2),
    "validate truncated info.json": (
        lambda t, r, d: ["validate", str(raw_with(t, d, lambda c: _truncate(c / "meta/info.json")))],
        2,
    ),
    "validate stats not matching (deep)": (
        lambda t, r, d: ["validate", "--deep", str(raw_with(t, d, _negate_stats))],
        2,
    ),
    # train / eval
    "train bc raw folder": (lambda t, r, d: ["train", "bc", "--dataset", str(r), "--output", str(t / "run")], 2),
    "train bc id does not match root": (
        lambda t, r, d: ["train", "bc", "--dataset", "me/other", "--root", str(d), "--output", str(t / "run")],
        2,
    ),
    "train bc output parent is a file": (
        lambda t, r, d: ["train", "bc", "--dataset", str(d), "--output", str(a_file(t) / "run"), "--steps", "1"],
        2,
    ),
    "train vpace trajectories as examples": (
        lambda t, r, d: ["train", "vpace", "--examples", str(d), "--main-task", "reach", "--output", str(t / "v")],
        2,
    ),
    "eval negative seed": (lambda t, r, d: ["eval", "--policy", str(t), "--task", "lift", "--seed", "-5"], 2),
    "eval policy missing": (lambda t, r, d: ["eval", "--policy", str(t / "none"), "--task", "lift"], 2),
    "eval out parent is a file": (
        lambda t, r, d: ["eval", "--policy", str(t), "--task", "lift", "--out", str(a_file(t) / "x.json")],
        2,
    ),
    # import / hub
    "import vpace negative pointer": (
        lambda t, r, d: ["import", "vpace", str(_buffer(t, pointer=-3)), "--repo-id", "me/x", "--root", str(t / "x")],
        2,
    ),
    "import vpace invalid repo id": (
        lambda t, r, d: [
            "import",
            "vpace",
            str(_buffer(t, pointer=0)),
            "--repo-id",
            "bad id!!",
            "--root",
            str(t / "x"),
        ],
        2,
    ),
    "pull with HF_ENDPOINT=notaurl": (
        lambda t, r, d: _env(HF_ENDPOINT="notaurl", HF_HUB_OFFLINE="0") + ["pull", "me/x"],
        2,
    ),
}


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _mkdir(path: Path) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    return path


def _copy(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


def _non_utf8_pipeline(t: Path, r: Path, dest: str = "out") -> str:
    """A pipeline (and its raw source, with images) inside a folder whose name is not UTF-8."""
    folder = _mkdir(t / NON_UTF8)
    _copy(r, folder / "raw")
    return pipeline(folder, Path("raw"), dest)


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _png16(root: Path) -> None:
    import cv2
    import numpy as np

    png = next(root.glob("episode_000000/images/*/frame_000000.png"))
    ok, data = cv2.imencode(".png", np.full((12, 16, 3), 3000, np.uint16))
    png.write_bytes(data.tobytes())


def _negate_stats(root: Path) -> None:
    stats = json.loads((root / "meta/stats.json").read_text())
    stats["action"]["mean"] = [-v - 1.0 for v in stats["action"]["mean"]]
    (root / "meta/stats.json").write_text(json.dumps(stats))


def _bad_repo(t: Path, r: Path) -> str:
    return str(
        _write(t / "bad.toml", f'[[sources]]\npath = "{r}"\n[destination]\nroot = "out"\nrepo_id = "bad id!!"\n')
    )


def _buffer(t: Path, pointer: int) -> Path:
    import gzip
    import pickle

    import numpy as np

    n = 4
    data = {
        "observations": np.zeros((n, 60), np.float32),
        "next_observations": np.zeros((n, 60), np.float32),
        "actions": np.zeros((n, 4), np.float32),
        "rewards": np.zeros((n, 1), np.float32),
        "dones": np.zeros((n, 1), bool),
        "memory_size": n,
        "pointer": pointer,
        "count": n + 2,
    }
    path = t / "3_lift.gz"
    with gzip.open(path, "wb") as f:
        pickle.dump(data, f)
    return path


_ENV: dict[str, str] = {}


def _env(**values: str) -> list[str]:
    _ENV.update(values)
    return []


@pytest.mark.parametrize("name", sorted(CASES))
def test_bad_input_gives_one_line(name, tmp_path, rel_raw, rel_ds, monkeypatch):
    build, expected = CASES[name]
    before = (tree_state(rel_raw), tree_state(rel_ds))
    monkeypatch.chdir(tmp_path)
    _ENV.clear()
    argv = build(tmp_path, rel_raw, rel_ds)
    for key, value in _ENV.items():
        monkeypatch.setenv(key, value)
    outcome = cli(argv)
    assert outcome.clean, f"{name}: {outcome}"
    assert outcome.code == expected, f"{name}: {outcome}"
    assert (tree_state(rel_raw), tree_state(rel_ds)) == before, f"{name} modified an input"


def test_os_errors_are_one_line(tmp_path, rel_raw, monkeypatch):
    """PermissionError / ENOSPC / NotADirectoryError anywhere under a command: one line naming path and cause."""
    import shiftkit.pipelines.runner as runner

    for exc in (
        PermissionError(errno.EACCES, "Permission denied", str(tmp_path / "x")),
        OSError(errno.EIO, "Input/output error", str(tmp_path / "y")),
    ):

        def fail(*args, exc=exc, **kwargs):
            raise exc

        monkeypatch.setattr(runner, "_prepare_work_dir", fail)
        outcome = cli(["run", pipeline(tmp_path, rel_raw), "--no-progress"])
        assert outcome.clean and outcome.code == 2, outcome
        assert exc.strerror in outcome.error_line and exc.filename in outcome.error_line
