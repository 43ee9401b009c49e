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
    "collect height 0": (lambda t, r, d: ["collect", "--task", "lift", "--height", "0", "--out", str(t / "o")], 2),
    "collect negative extra steps": (
        lambda t, r, d: ["collect", "--task", "lift", "--extra-steps", "-1", "--out", str(t / "o")],
        2,
    ),
    "collect control rate 7": (
        lambda t, r, d: ["collect", "--task", "lift", "--control-hz", "7", "--out", str(t / "o")],
        2,
    ),
    "collect unknown env": (lambda t, r, d: ["collect", "--env", "nope", "--task", "lift", "--out", str(t / "o")], 2),
    "collect unknown task": (lambda t, r, d: ["collect", "--task", "fly", "--out", str(t / "o")], 2),
    "collect unknown expert": (
        lambda t, r, d: ["collect", "--task", "lift", "--expert", "x", "--out", str(t / "o")],
        2,
    ),
    "collect both outputs": (
        lambda t, r, d: [
            "collect",
            "--task",
            "lift",
            "--out",
            str(t / "o"),
            "--lerobot",
            "me/x",
            "--root",
            str(t / "r"),
        ],
        2,
    ),
    "collect lerobot without root": (lambda t, r, d: ["collect", "--task", "lift", "--lerobot", "me/x"], 2),
    "collect no output": (lambda t, r, d: ["collect", "--task", "lift"], 2),
    "collect render quality": (lambda t, r, d: ["collect", "--task", "lift", "--render-quality", "x", "--out", "o"], 2),
    "collect bad env kwarg": (lambda t, r, d: ["collect", "--task", "lift", "--env-kwarg", "novalue", "--out", "o"], 2),
    "collect unknown env kwarg": (
        lambda t, r, d: [
            "collect",
            "--task",
            "lift",
            "--env-kwarg",
            "nope=1",
            "--episodes",
            "1",
            "--out",
            str(t / "o"),
        ],
        2,
    ),
    "collect bad env kwarg value": (
        lambda t, r, d: [
            "collect",
            "--env",
            "mv-lift",
            "--task",
            "lift",
            "--env-kwarg",
            "view=sideways",
            "--episodes",
            "1",
            "--out",
            str(t / "o"),
        ],
        2,
    ),
    "calibrate env without the task": (
        lambda t, r, d: ["calibrate", "--env", "panda-play", "--out", str(t / "cal.json")],
        2,
    ),
    "collect episodes not a number": (
        lambda t, r, d: ["collect", "--task", "lift", "--episodes", "x", "--out", "o"],
        2,
    ),
    "collect cameras into a non-UTF-8 folder": (
        lambda t, r, d: [
            "collect",
            "--task",
            "reach",
            "--episodes",
            "1",
            "--cameras",
            "front",
            "--out",
            str(t / NON_UTF8),
        ],
        0,
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
    "plan unreconciled sources": (
        lambda t, r, d: [
            "plan",
            pipeline(t, d, extra=f'[[sources]]\npath = "{raw_with(t, r, _json_edit("dataset.json", fps=20))}"'),
        ],
        2,
    ),
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
    "run unknown config suffix": (lambda t, r, d: ["run", str(_write(t / "p.txt", "x"))], 2),
    "run invalid json": (lambda t, r, d: ["run", str(_write(t / "p.json", "{"))], 2),
    "run invalid yaml": (lambda t, r, d: ["run", str(_write(t / "p.yaml", "a: [\n"))], 2),
    "run yaml not a mapping": (lambda t, r, d: ["run", str(_write(t / "p.yaml", "- 1\n"))], 2),
    "run json list": (lambda t, r, d: ["run", str(_write(t / "p.json", "[1, 2]"))], 2),
    "run unknown top-level key": (lambda t, r, d: ["run", str(_write(t / "p.toml", "sed = 1\n" + _src(r)))], 2),
    "run no sources": (
        lambda t, r, d: ["run", str(_write(t / "p.json", '{"sources": [], "destination": {"root": "o"}}'))],
        2,
    ),
    "run source with path and repo id": (
        lambda t, r, d: [
            "run",
            str(_write(t / "p.toml", f'[[sources]]\npath = "{r}"\nrepo_id = "a/b"\n[destination]\nroot = "o"\n')),
        ],
        2,
    ),
    "run no destination": (lambda t, r, d: ["run", str(_write(t / "p.toml", f'[[sources]]\npath = "{r}"\n'))], 2),
    "run destination root is a number": (
        lambda t, r, d: ["run", str(_write(t / "p.toml", f'[[sources]]\npath = "{r}"\n[destination]\nroot = 5\n'))],
        2,
    ),
    "run seed is text": (lambda t, r, d: ["run", pipeline(t, r, seed='"x"')], 2),
    "run seed is a float": (lambda t, r, d: ["run", pipeline(t, r, seed="1.5")], 2),
    "run stage unknown param": (
        lambda t, r, d: ["run", pipeline(t, r, extra='[[stages]]\nname = "trim"\nparams = { nope = 1 }')],
        2,
    ),
    "run stage param wrong type": (
        lambda t, r, d: ["run", pipeline(t, r, extra='[[stages]]\nname = "subsample"\nparams = { every = "2" }')],
        2,
    ),
    "run stage version mismatch": (
        lambda t, r, d: ["run", pipeline(t, r, extra='[[stages]]\nname = "trim"\nversion = 99')],
        2,
    ),
    "run subsample not dividing fps": (
        lambda t, r, d: ["run", pipeline(t, r, extra='[[stages]]\nname = "subsample"\nparams = { every = 3 }')],
        2,
    ),
    "run drop unknown feature": (
        lambda t, r, d: ["run", pipeline(t, r, extra='[[stages]]\nname = "drop"\nparams = { features = ["nope"] }')],
        2,
    ),
    "run cast to unknown dtype": (
        lambda t, r, d: [
            "run",
            pipeline(t, r, extra='[[stages]]\nname = "cast"\nparams = { dtypes = { action = "x" } }'),
        ],
        2,
    ),
    "run every episode filtered out": (
        lambda t, r, d: ["run", pipeline(t, r, extra='[[stages]]\nname = "filter"\nparams = { min_length = 999 }')],
        2,
    ),
    "run push invalid repo id": (lambda t, r, d: ["run", pipeline(t, r), "--push", "bad id!!"], 2),
    "run local executor with address": (lambda t, r, d: ["run", pipeline(t, r), "--address", "x"], 2),
    "run workers not a number": (lambda t, r, d: ["run", pipeline(t, r), "--workers", "x"], 2),
    "run raw version 2": (
        lambda t, r, d: ["run", pipeline(t, raw_with(t, r, _json_edit("dataset.json", version=2)))],
        2,
    ),
    "run raw wrong format": (
        lambda t, r, d: ["run", pipeline(t, raw_with(t, r, _json_edit("dataset.json", format="x")))],
        2,
    ),
    "run raw no episodes": (
        lambda t, r, d: ["run", pipeline(t, raw_with(t, r, _json_edit("dataset.json", episodes=[])))],
        2,
    ),
    "run raw fps 0": (lambda t, r, d: ["run", pipeline(t, raw_with(t, r, _json_edit("dataset.json", fps=0)))], 2),
    "run raw episode folder missing": (
        lambda t, r, d: ["run", pipeline(t, raw_with(t, r, lambda c: _rmtree(c / "episode_000002")))],
        2,
    ),
    "run raw meta.json length wrong": (
        lambda t, r, d: ["run", pipeline(t, raw_with(t, r, _json_edit("episode_000001/meta.json", length=3)))],
        2,
    ),
    "run raw meta.json truncated": (
        lambda t, r, d: ["run", pipeline(t, raw_with(t, r, lambda c: _truncate(c / "episode_000001/meta.json")))],
        2,
    ),
    "run raw array truncated": (
        lambda t, r, d: [
            "run",
            pipeline(t, raw_with(t, r, lambda c: _truncate(c / "episode_000001/arrays/action.npy"))),
        ],
        2,
    ),
    "run raw action NaN": (lambda t, r, d: ["run", pipeline(t, raw_with(t, r, _nan_action))], 2),
    "run raw timestamps decreasing": (lambda t, r, d: ["run", pipeline(t, raw_with(t, r, _reverse_time))], 2),
    "run raw image missing": (
        lambda t, r, d: [
            "run",
            pipeline(t, raw_with(t, r, lambda c: next(c.glob("episode_000001/images/*/*.png")).unlink())),
        ],
        2,
    ),
    "run raw image garbage": (
        lambda t, r, d: [
            "run",
            pipeline(t, raw_with(t, r, lambda c: next(c.glob("episode_000001/images/*/*.png")).write_bytes(b"x"))),
        ],
        2,
    ),
    "run raw array with another width": (lambda t, r, d: ["run", pipeline(t, raw_with(t, r, _wide_action))], 2),
    "run lerobot codebase v2.1": (
        lambda t, r, d: ["run", pipeline(t, raw_with(t, d, _json_edit("meta/info.json", codebase_version="v2.1")))],
        2,
    ),
    "run lerobot features not an object": (
        lambda t, r, d: ["run", pipeline(t, raw_with(t, d, _json_edit("meta/info.json", features=[1])))],
        2,
    ),
    "run lerobot data file missing": (
        lambda t, r, d: ["run", pipeline(t, raw_with(t, d, lambda c: next(c.glob("data/*/*.parquet")).unlink()))],
        2,
    ),
    "run lerobot episodes metadata garbage": (
        lambda t, r, d: [
            "run",
            pipeline(t, raw_with(t, d, lambda c: next(c.glob("meta/episodes/*/*.parquet")).write_bytes(b"x"))),
        ],
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
    "validate stats.json missing": (
        lambda t, r, d: ["validate", str(raw_with(t, d, lambda c: (c / "meta/stats.json").unlink()))],
        2,
    ),
    "validate empty folder": (lambda t, r, d: ["validate", str(_mkdir(t / "e"))], 2),
    "info invalid id": (lambda t, r, d: ["info", "a/b/c"], 2),
    # train / eval
    "train bc batch size 0": (
        lambda t, r, d: ["train", "bc", "--dataset", str(d), "--output", str(t / "run"), "--batch-size", "0"],
        2,
    ),
    "train bc ensemble 0": (
        lambda t, r, d: ["train", "bc", "--dataset", str(d), "--output", str(t / "run"), "--ensemble", "0"],
        2,
    ),
    "train bc val fraction 2": (
        lambda t, r, d: ["train", "bc", "--dataset", str(d), "--output", str(t / "run"), "--val-fraction", "2"],
        2,
    ),
    "train bc unknown input": (
        lambda t, r, d: ["train", "bc", "--dataset", str(d), "--output", str(t / "run"), "--inputs", "x"],
        2,
    ),
    "train bc encoder weights missing": (
        lambda t, r, d: [
            "train",
            "bc",
            "--dataset",
            str(d),
            "--output",
            str(t / "r"),
            "--encoder",
            "resnet18",
            "--encoder-weights",
            "nope.pt",
        ],
        2,
    ),
    "train bc steps 0": (
        lambda t, r, d: [
            "train",
            "bc",
            "--dataset",
            str(d),
            "--output",
            str(t / "r"),
            "--regime",
            "fixed",
            "--steps",
            "0",
        ],
        2,
    ),
    "train bc device nope": (
        lambda t, r, d: ["train", "bc", "--dataset", str(d), "--output", str(t / "r"), "--device", "nope"],
        2,
    ),
    "train bc dataset missing": (
        lambda t, r, d: ["train", "bc", "--dataset", str(t / "none"), "--output", str(t / "r")],
        2,
    ),
    "eval episodes 0": (lambda t, r, d: ["eval", "--policy", str(t), "--task", "lift", "--episodes", "0"], 2),
    "eval policy not a run": (lambda t, r, d: ["eval", "--policy", str(t), "--task", "lift"], 2),
    "eval videos is a file": (
        lambda t, r, d: ["eval", "--policy", str(t), "--task", "lift", "--videos", str(a_file(t))],
        2,
    ),
    "eval out is a folder": (lambda t, r, d: ["eval", "--policy", str(t), "--task", "lift", "--out", str(t)], 2),
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
    "import vpace missing file": (
        lambda t, r, d: ["import", "vpace", str(t / "none.gz"), "--repo-id", "me/x", "--root", str(t / "x")],
        2,
    ),
    "import vpace not gzip": (
        lambda t, r, d: [
            "import",
            "vpace",
            str(_write(t / "3_lift.gz", "x")),
            "--repo-id",
            "me/x",
            "--root",
            str(t / "x"),
        ],
        2,
    ),
    "import vpace root exists": (
        lambda t, r, d: ["import", "vpace", str(_buffer(t, pointer=0)), "--repo-id", "me/x", "--root", str(r)],
        2,
    ),
    "push not a dataset": (lambda t, r, d: ["push", str(r), "--repo-id", "me/x"], 2),
    "pull invalid id": (lambda t, r, d: ["pull", "bad id!!"], 2),
    "pull with HF_ENDPOINT=notaurl": (
        lambda t, r, d: _env(HF_ENDPOINT="notaurl", HF_HUB_OFFLINE="0") + ["pull", "me/x"],
        2,
    ),
    # outputs derived from another output, formats, labels, defaults
    "eval yaw sweep out is the PNG": (
        lambda t, r, d: [*_sweep(t), "--out", str(t / "sweep.png")],
        2,
    ),
    "eval yaw sweep with videos": (lambda t, r, d: [*_sweep(t), "--videos", str(t / "v")], 2),
    "eval yaw sweep with view=fixed": (lambda t, r, d: [*_sweep(t), "--env-kwarg", "view=fixed"], 2),
    "plot fire unsupported format": (lambda t, r, d: ["plot", "fire", str(t), "--out", str(t / "f.txt")], 2),
    "plot roc unsupported format": (lambda t, r, d: ["plot", "roc", str(t), "--out", str(t / "f.txt")], 2),
    "plot fire duplicate labels": (
        lambda t, r, d: ["plot", "fire", f"a={t}", f"a={a_file(t)}", "--out", str(t / "f.png")],
        2,
    ),
    "fire default repo id with a space": (
        lambda t, r, d: ["fire", "--dataset", str(d), "--env", "panda-play", "--task", "lift", "--output", "my run"],
        2,
    ),
    "import non-ASCII repo id": (
        lambda t, r, d: ["import", "lerobot-v2.1", str(d), "--repo-id", "me/donn\u00e9es", "--root", str(t / "o")],
        2,
    ),
    "validate truncated provenance": (
        lambda t, r, d: ["validate", str(raw_with(t, d, lambda c: _truncate(c / "meta/shiftkit_provenance.json")))],
        2,
    ),
    # one rule per numeric option and env kwarg
    "collect env kwarg max_episode_seconds 0": (
        lambda t, r, d: [
            "collect",
            "--env",
            "mv-lift",
            "--task",
            "lift",
            "--env-kwarg",
            "max_episode_seconds=0",
            "--out",
            str(t / "o"),
        ],
        2,
    ),
    "collect env kwarg width 1.5": (
        lambda t, r, d: ["collect", "--task", "lift", "--env-kwarg", "width=1.5", "--out", str(t / "o")],
        2,
    ),
    "eval env kwarg max_episode_seconds nan": (
        lambda t, r, d: ["eval", "--policy", str(t), "--task", "lift", "--env-kwarg", "max_episode_seconds=NaN"],
        2,
    ),
    "fire env kwarg control_hz -5": (
        lambda t, r, d: [
            "fire",
            "--dataset",
            str(d),
            "--env",
            "panda-play",
            "--task",
            "lift",
            "--env-kwarg",
            "control_hz=-5",
            "--output",
            str(t / "f"),
        ],
        2,
    ),
    "train bc lr inf": (
        lambda t, r, d: ["train", "bc", "--dataset", str(d), "--output", str(t / "b"), "--lr", "inf"],
        2,
    ),
    "train vpace examples per task 0": (
        lambda t, r, d: [
            "train",
            "vpace",
            "--examples",
            str(d),
            "--main-task",
            "lift",
            "--output",
            str(t / "v"),
            "--examples-per-task",
            "0",
        ],
        2,
    ),
    "train lfgp total steps 1.5": (
        lambda t, r, d: ["train", "lfgp", "--examples", str(d), "--main-task", "lift", "--total-steps", "1.5"],
        2,
    ),
    "train bc hidden width 0": (
        lambda t, r, d: ["train", "bc", "--dataset", str(d), "--output", str(t / "b"), "--hidden", "64,0"],
        2,
    ),
    "fire beta 0": (
        lambda t, r, d: [
            "fire",
            "--dataset",
            str(d),
            "--env",
            "panda-play",
            "--task",
            "lift",
            "--output",
            str(t / "f"),
            "--beta",
            "0",
        ],
        2,
    ),
    "fire aggregate gamma nan": (
        lambda t, r, d: [
            "fire",
            "aggregate",
            "--expert",
            str(d),
            "--rollouts",
            str(d),
            "--out",
            str(t / "a"),
            "--repo-id",
            "me/a",
            "--gamma",
            "nan",
        ],
        2,
    ),
    "fire abbreviated option": (lambda t, r, d: ["fire", "--expert", "local/exp"], 2),
    "plot fire window 0": (lambda t, r, d: ["plot", "fire", str(t), "--out", str(t / "f.png"), "--window", "0"], 2),
    "run destination inside its source": (lambda t, r, d: ["run", pipeline(t, r, dest=str(r / "out"))], 2),
    "calibrate out is the plot": (lambda t, r, d: ["calibrate", "--out", str(t / "cal.png")], 2),
    "calibrate plot is the out": (
        lambda t, r, d: ["calibrate", "--out", str(t / "cal.json"), "--plot", str(t / "cal.json")],
        2,
    ),
    "calibrate plot format": (lambda t, r, d: ["calibrate", "--out", str(t / "c.json"), "--plot", str(t / "c.txt")], 2),
    # malformed file contents in importers and readers
    "import vpace ragged observations": (
        lambda t, r, d: ["import", "vpace", str(_buffer(t, 0, observations=[[0.0] * 60] * 3 + [[0.0]])), *_to(t)],
        2,
    ),
    "import vpace pointer is a float": (lambda t, r, d: ["import", "vpace", str(_buffer(t, 1.5)), *_to(t)], 2),
    "import ros2 joint vector changes width mid-bag": (
        lambda t, r, d: ["import", "ros2", *_ros2_widening(t), *_to(t)],
        2,
    ),
    "import lerobot-v2.1 fps is text": (
        lambda t, r, d: ["import", "lerobot-v2.1", str(_v21(t, fps="fast")), *_to(t)],
        2,
    ),
    "import lerobot-v2.1 episode length is text": (
        lambda t, r, d: ["import", "lerobot-v2.1", str(_v21(t, line=("episodes.jsonl", "length", "4"))), *_to(t)],
        2,
    ),
    "import lerobot-v2.1 task is a number": (
        lambda t, r, d: ["import", "lerobot-v2.1", str(_v21(t, line=("tasks.jsonl", "task", 7))), *_to(t)],
        2,
    ),
    "import robomimic control_freq is text": (
        lambda t, r, d: ["import", "robomimic", str(_robomimic(t, control_freq="fast")), *_to(t)],
        2,
    ),
    "import robomimic demo without actions": (
        lambda t, r, d: ["import", "robomimic", str(_robomimic(t, drop="actions")), *_to(t)],
        2,
    ),
    "import robomimic total is text": (
        lambda t, r, d: ["import", "robomimic", str(_robomimic(t, total="x")), *_to(t)],
        2,
    ),
    "import robomimic dones of 0.5": (
        lambda t, r, d: ["import", "robomimic", str(_robomimic(t, dones=0.5)), *_to(t)],
        2,
    ),
    "run raw success of 0.5": (lambda t, r, d: ["run", pipeline(t, raw_with(t, r, _half_success))], 2),
    # misleading messages
    "fire on another env's dataset": (
        lambda t, r, d: ["fire", "--dataset", str(_with_provenance(t, d, env="mv-lift")), *_fire_to(t)],
        2,
    ),
    "info non-UTF-8 dataset folder": (lambda t, r, d: ["info", str(_copy(d, t / NON_UTF8))], 2),
    "validate non-UTF-8 dataset folder": (lambda t, r, d: ["validate", str(_copy(d, t / NON_UTF8))], 2),
    # ambiguous acceptances, decided
    "train bc on a success-example set": (
        lambda t, r, d: ["train", "bc", "--dataset", str(_with_provenance(t, d, stage="success_examples")), *_run(t)],
        2,
    ),
    "train lfgp on a success-example set": (
        lambda t, r, d: [
            "train",
            "lfgp",
            "--examples",
            str(_with_provenance(t, d, kind="examples")),
            "--main-task",
            "lift",
            "--output",
            str(t / "run"),
        ],
        2,
    ),
    "fire on a success-example set": (
        lambda t, r, d: ["fire", "--dataset", str(_with_provenance(t, d, stage="success_examples")), *_fire_to(t)],
        2,
    ),
    "collect lerobot non-ASCII repo id": (
        lambda t, r, d: ["collect", "--task", "lift", "--lerobot", "me/donn\u00e9es", "--root", str(t / "o")],
        2,
    ),
    "run non-ASCII destination repo id": (
        lambda t, r, d: ["run", _ascii_repo(t, r)],
        2,
    ),
}

# What the error line must say, where the wording is the point (the misleading messages it replaced).
MESSAGES = {
    "calibrate out is the plot": "would be one file",
    "calibrate plot is the out": "would be one file",
    "calibrate plot format": "--plot",
    "import vpace ragged observations": "observations is not a numeric array (rows of different lengths)",
    "import vpace pointer is a float": "memory_size, pointer and count must be integers",
    "import ros2 joint vector changes width mid-bag": "field 'position' changes width mid-bag (3 values, then 2",
    "import lerobot-v2.1 fps is text": "info.json: 'fps' must be a positive integer, got 'fast'",
    "import lerobot-v2.1 episode length is text": "episodes.jsonl: line 2: 'length' must be a positive integer",
    "import lerobot-v2.1 task is a number": "tasks.jsonl: line 2: 'task' must be a string",
    "import robomimic control_freq is text": "control_freq",
    "import robomimic demo without actions": "data/demo_1/actions must be a numeric (frames[, dims]) array (missing)",
    "import robomimic total is text": "data attribute total must be an integer, got 'x'",
    "import robomimic dones of 0.5": "data/demo_0/dones: a flag holds only 0 and 1 (or bools), found",
    "run raw success of 0.5": "arrays/success.npy: a flag holds only 0 and 1 (or bools), found",
    "fire on another env's dataset": "was recorded in mv-lift, not panda-play",
    "info non-UTF-8 dataset folder": "is not a UTF-8 path; LeRobot datasets can only be read from UTF-8 paths",
    "validate non-UTF-8 dataset folder": "is not a UTF-8 path; LeRobot datasets can only be read from UTF-8 paths",
    "train bc on a success-example set": "is a success-example set (made by the success_examples stage)",
    "train lfgp on a success-example set": "is a success-example set (made by `import vpace` of example files)",
    "fire on a success-example set": "FIRE learns from trajectories",
    "collect lerobot non-ASCII repo id": "ASCII letters",
    "run non-ASCII destination repo id": "ASCII letters",
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


def _src(r: Path) -> str:
    return f'[[sources]]\npath = "{r}"\n[destination]\nroot = "o"\n'


def _rmtree(path: Path) -> None:
    import shutil

    shutil.rmtree(path)


def _nan_action(root: Path) -> None:
    import numpy as np

    path = root / "episode_000001/arrays/action.npy"
    a = np.load(path)
    a[2, 0] = np.nan
    np.save(path, a)


def _reverse_time(root: Path) -> None:
    import numpy as np

    path = root / "episode_000001/arrays/timestamp.npy"
    np.save(path, np.load(path)[::-1].copy())


def _wide_action(root: Path) -> None:
    import numpy as np

    path = root / "episode_000002/arrays/action.npy"
    a = np.load(path)
    np.save(path, np.concatenate([a, a], axis=1))


def _non_utf8_pipeline(t: Path, r: Path, dest: str = "out") -> str:
    """A pipeline (and its raw source, with images) inside a folder whose name is not UTF-8."""
    folder = _mkdir(t / NON_UTF8)
    _copy(r, folder / "raw")
    return pipeline(folder, Path("raw"), dest)


def _sweep(t: Path) -> list[str]:
    return ["eval", "--policy", str(t), "--env", "mv-lift", "--task", "lift", "--episodes", "1", "--yaw-sweep"]


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


def _buffer(t: Path, pointer: int | float, **arrays) -> Path:
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
        **arrays,
    }
    path = t / "3_lift.gz"
    with gzip.open(path, "wb") as f:
        pickle.dump(data, f)
    return path


def _to(t: Path) -> list[str]:
    return ["--repo-id", "me/x", "--root", str(t / "x")]


def _run(t: Path) -> list[str]:
    return ["--output", str(t / "run"), "--no-progress"]


def _fire_to(t: Path) -> list[str]:
    return ["--env", "panda-play", "--task", "reach", "--output", str(t / "run")]


def _ros2_widening(t: Path) -> list[str]:
    """A bag whose joint vector has 3 values, then 2 from its fourth message on."""
    import numpy as np

    from tests import test_import_ros2 as bags

    sent = []

    def joint_state(stamp):
        sent.append(stamp)
        q = np.full(3 if len(sent) < 4 else 2, 1.0)
        return bags.TS.types["sensor_msgs/msg/JointState"](
            header=bags._header(stamp), name=bags.JOINTS, position=q, velocity=np.zeros(3), effort=np.zeros(0)
        )

    typ, period, offset, _ = bags.STREAMS["/joint_states"]
    bag = bags._write_bag(t / "bag", streams={**bags.STREAMS, "/joint_states": (typ, period, offset, joint_state)})
    (t / "m.toml").write_text(bags.MAPPING)
    return [str(bag), "--mapping", str(t / "m.toml")]


def _v21(t: Path, fps=None, line: tuple[str, str, object] | None = None) -> Path:
    from tests.test_import_lerobot_v21 import _write_v21

    src = _write_v21(t / "v21")
    if fps is not None:
        _json_edit("meta/info.json", fps=fps)(src)
    if line is not None:
        name, key, value = line
        path = src / "meta" / name
        rows = [json.loads(row) for row in path.read_text().splitlines()]
        rows[-1][key] = value
        path.write_text("".join(json.dumps(row) + "\n" for row in rows))
    return src


def _robomimic(t: Path, control_freq=20, drop: str | None = None, dones: float | None = None, total=None) -> Path:
    import h5py
    import numpy as np

    from tests.test_import_robomimic import _write

    path = _write(
        t / "rm.hdf5",
        env_args={"env_name": "Lift", "env_type": 1, "env_kwargs": {"control_freq": control_freq, "robots": ["Panda"]}},
    )
    with h5py.File(path, "a") as f:
        if total is not None:
            f["data"].attrs["total"] = total
        if drop is not None:
            del f[f"data/demo_1/{drop}"]
        if dones is not None:
            n = len(f["data/demo_0/dones"])
            del f["data/demo_0/dones"]
            f.create_dataset("data/demo_0/dones", data=np.full(n, dones))
    return path


def _half_success(root: Path) -> None:
    import numpy as np

    path = root / "episode_000001/arrays/success.npy"
    np.save(path, np.full(len(np.load(path)), 0.5))


def _with_provenance(
    t: Path, d: Path, env: str | None = None, stage: str | None = None, kind: str | None = None
) -> Path:
    """A copy of dataset `d` whose provenance says it was recorded in `env`, or made by a `stage`, or
    imported as `kind`."""
    copy = _copy(d, t / "ds")
    path = copy / "meta/shiftkit_provenance.json"
    provenance = json.loads(path.read_text())
    if env is not None:
        provenance["sources"] = [{"kind": "simulator", "env": env, "task": "lift"}]
    if stage is not None:
        provenance["stages"] = [*provenance.get("stages", []), {"name": stage, "params": {}}]
    if kind is not None:
        provenance["importer"] = {"name": "vpace", "kind": kind}
    path.write_text(json.dumps(provenance))
    return copy


def _ascii_repo(t: Path, r: Path) -> str:
    return str(
        _write(t / "u.toml", f'[[sources]]\npath = "{r}"\n[destination]\nroot = "out"\nrepo_id = "me/donn\u00e9es"\n')
    )


# --- the file boundary: files of the right syntax but the wrong types, shapes or ranges (loaders)
def _set_json(rel: str, value) -> object:
    def edit(root: Path) -> None:
        (root / rel).write_text(json.dumps(value))

    return edit


def _edit_provenance(**values):
    return _json_edit("meta/shiftkit_provenance.json", **values)


def _fire_run(t: Path, **line) -> Path:
    """A FIRE run folder with two per-episode metric lines (the second edited by `line`, a None value
    removing its key), as `shiftkit fire` writes them."""
    run = _mkdir(t / "fire-run")
    (run / "config.json").write_text(json.dumps({"trainer": "fire", "args": {}}))
    rows = []
    for i, failed in enumerate((True, False)):
        row = {
            "step": i + 1,
            "split": "episode",
            "d_ready": True,
            "policy_success": not failed,
            "expert_samples": 10 + i,
            "execution_time_s": 1.5 * i,
            "scores": {"beta": 0.5 + i, "gda": 0.25 * i, "doubt": 0.1},
            "feedback": [],
        }
        if i == 1:
            row.update(line)
            row = {k: v for k, v in row.items() if v is not None}
        rows.append(json.dumps(row))
    (run / "metrics.jsonl").write_text("\n".join(rows) + "\n")
    return run


def _robomimic_edit(t: Path, edit) -> Path:
    import h5py

    from tests.test_import_robomimic import _write

    path = _write(t / "rm.hdf5")
    with h5py.File(path, "a") as f:
        edit(f)
    return path


def _replace(f, name: str, data) -> None:
    del f[name]
    f.create_dataset(name, data=data)


def _demo_as_dataset(f) -> None:
    import numpy as np

    del f["data/demo_1"]
    f.create_dataset("data/demo_1", data=np.zeros(3))


def _calibration_plan(t: Path, edit) -> Path:
    """A calibration plan (`calibrate --plan`) with one of its arrays edited."""
    from shiftkit.app.cli import main

    plan = t / "plan"
    assert main(["calibrate", "--plan", str(plan), "--pushes", "1", "--held-out", "0"]) == 0
    edit(plan)
    return plan


def _merge(t: Path, *sources) -> list[str]:
    return [
        "merge",
        *map(str, sources),
        "--fps",
        "10",
        "--out",
        str(t / "merged"),
        "--repo-id",
        "me/m",
        "--no-progress",
    ]


def _two_sources(t: Path, first: str, second: str) -> str:
    path = t / "two.toml"
    path.write_text(f'[[sources]]\npath = "{first}"\n[[sources]]\npath = "{second}"\n[destination]\nroot = "o"\n')
    return str(path)


CASES.update(
    {
        "info info.json is a list": (
            lambda t, r, d: ["info", str(raw_with(t, d, _set_json("meta/info.json", [1])))],
            2,
        ),
        "validate info.json is a list": (
            lambda t, r, d: ["validate", str(raw_with(t, d, _set_json("meta/info.json", [1])))],
            2,
        ),
        "run lerobot info.json is a list": (
            lambda t, r, d: ["run", pipeline(t, raw_with(t, d, _set_json("meta/info.json", [1])))],
            2,
        ),
        "import lerobot-v2.1 info.json is a list": (
            lambda t, r, d: ["import", "lerobot-v2.1", str(_set_v21_info(t, [1])), *_to(t)],
            2,
        ),
        "import lerobot-v2.1 feature is a list": (
            lambda t, r, d: ["import", "lerobot-v2.1", str(_v21_features(t, {"action": [1]})), *_to(t)],
            2,
        ),
        "info feature shape is text": (
            lambda t, r, d: [
                "info",
                str(raw_with(t, d, _json_edit("meta/info.json", features={"action": {"dtype": "f", "shape": "4"}}))),
            ],
            2,
        ),
        "info total_frames is text": (
            lambda t, r, d: ["info", str(raw_with(t, d, _json_edit("meta/info.json", total_frames="x")))],
            2,
        ),
        "info stats entry is a list": (
            lambda t, r, d: ["info", str(raw_with(t, d, _json_edit("meta/stats.json", action=[1, 2])))],
            2,
        ),
        "info stats values are text": (
            lambda t, r, d: ["info", str(raw_with(t, d, _json_edit("meta/stats.json", action={"mean": "x"})))],
            2,
        ),
        "info provenance is a list": (
            lambda t, r, d: ["info", str(raw_with(t, d, _set_json("meta/shiftkit_provenance.json", [1])))],
            2,
        ),
        "info provenance stages is an object": (
            lambda t, r, d: ["info", str(raw_with(t, d, _edit_provenance(stages={"a": 1})))],
            2,
        ),
        "validate provenance sources hold a number": (
            lambda t, r, d: ["validate", str(raw_with(t, d, _edit_provenance(sources=[5])))],
            2,
        ),
        "train bc provenance output is text": (
            lambda t, r, d: [
                "train",
                "bc",
                "--dataset",
                "me/lift",
                "--root",
                str(raw_with(t, d, _edit_provenance(output="me/lift"))),
                *_run(t),
            ],
            2,
        ),
        "fire provenance sources is an object": (
            lambda t, r, d: [
                "fire",
                "--dataset",
                str(raw_with(t, d, _edit_provenance(sources={"env": 1}))),
                *_fire_to(t),
            ],
            2,
        ),
        "import robomimic actions of three dimensions": (
            lambda t, r, d: [
                "import",
                "robomimic",
                str(
                    _robomimic_edit(
                        t, lambda f: _replace(f, "data/demo_0/actions", __import__("numpy").zeros((4, 2, 2)))
                    )
                ),
                *_to(t),
            ],
            2,
        ),
        "import robomimic demo is a dataset": (
            lambda t, r, d: ["import", "robomimic", str(_robomimic_edit(t, _demo_as_dataset)), *_to(t)],
            2,
        ),
        "import robomimic data is a dataset": (
            lambda t, r, d: [
                "import",
                "robomimic",
                str(_robomimic_edit(t, lambda f: (f.__delitem__("data"), f.create_dataset("data", data=[1])))),
                *_to(t),
            ],
            2,
        ),
        "import robomimic obs is a dataset": (
            lambda t, r, d: [
                "import",
                "robomimic",
                str(_robomimic_edit(t, lambda f: _replace(f, "data/demo_0/obs", __import__("numpy").zeros(3)))),
                *_to(t),
            ],
            2,
        ),
        "import robomimic env_args is a list": (
            lambda t, r, d: [
                "import",
                "robomimic",
                str(_robomimic_edit(t, lambda f: f["data"].attrs.__setitem__("env_args", "[1]"))),
                *_to(t),
            ],
            2,
        ),
        "plot roc metrics line without scores": (
            lambda t, r, d: ["plot", "roc", str(_fire_run(t, scores=None)), "--out", str(t / "r.png")],
            2,
        ),
        "plot roc score is text": (
            lambda t, r, d: [
                "plot",
                "roc",
                str(_fire_run(t, scores={"beta": "x", "gda": 0, "doubt": 0})),
                "--out",
                str(t / "r.png"),
            ],
            2,
        ),
        "plot fire expert samples missing": (
            lambda t, r, d: ["plot", "fire", str(_fire_run(t, expert_samples=None)), "--out", str(t / "f.png")],
            2,
        ),
        "plot fire execution time is text": (
            lambda t, r, d: ["plot", "fire", str(_fire_run(t, execution_time_s="1s")), "--out", str(t / "f.png")],
            2,
        ),
        "plot fire metrics line is a list": (
            lambda t, r, d: ["plot", "fire", str(_fire_run_with_line(t, "[1, 2]")), "--out", str(t / "f.png")],
            2,
        ),
        "plot fire config is a list": (
            lambda t, r, d: ["plot", "fire", str(_fire_run_config(t, [1])), "--out", str(t / "f.png")],
            2,
        ),
        "plot fire a good run": (lambda t, r, d: ["plot", "fire", str(_fire_run(t)), "--out", str(t / "f.png")], 0),
        "collect env kwarg 1e308": (
            lambda t, r, d: [
                "collect",
                "--env",
                "door-tactile",
                "--task",
                "flat-handle-open",
                "--env-kwarg",
                "max_episode_seconds=1e308",
                "--out",
                str(t / "o"),
            ],
            2,
        ),
        "eval env kwarg 1e308": (
            lambda t, r, d: [
                "eval",
                "--policy",
                str(t),
                "--env",
                "mv-lift",
                "--task",
                "lift",
                "--env-kwarg",
                "max_episode_seconds=1e308",
            ],
            2,
        ),
        "sim-robot truncated plan array": (
            lambda t, r, d: [
                "sim-robot",
                str(_calibration_plan(t, lambda p: _truncate(next(p.glob("episode_*/arrays/action.npy"))))),
                "--out",
                str(t / "rec"),
            ],
            2,
        ),
        "sim-robot plan array of text": (
            lambda t, r, d: [
                "sim-robot",
                str(
                    _calibration_plan(
                        t,
                        lambda p: __import__("numpy").save(
                            next(p.glob("episode_*/arrays/action.npy")), __import__("numpy").array(["a"])
                        ),
                    )
                ),
                "--out",
                str(t / "rec"),
            ],
            2,
        ),
        "sim-robot plan dataset.json info is a list": (
            lambda t, r, d: [
                "sim-robot",
                str(_calibration_plan(t, _json_edit("dataset.json", info=[1]))),
                "--out",
                str(t / "rec"),
            ],
            2,
        ),
        # --- outputs never inside inputs, inputs never twice
        "run the same source twice": (lambda t, r, d: ["run", _two_sources(t, str(d), str(d))], 2),
        "run one source spelled two ways": (lambda t, r, d: ["run", _two_sources(t, str(d), f"{d}/./")], 2),
        "run a copy of a source": (lambda t, r, d: ["run", _two_sources(t, str(d), str(_copy(d, t / "copy")))], 2),
        "merge the same source twice": (lambda t, r, d: _merge(t, d, f"{d}/"), 2),
        "merge a copy of a source": (lambda t, r, d: _merge(t, d, _copy(d, t / "copy")), 2),
        "merge into its source": (
            lambda t, r, d: ["merge", str(d), "--fps", "10", "--out", str(d / "merged"), "--repo-id", "me/m"],
            2,
        ),
        "sim-robot out inside its plan": (lambda t, r, d: ["sim-robot", str(r), "--out", str(r / "rec")], 2),
        "calibrate out inside its recording": (
            lambda t, r, d: ["calibrate", "--from", str(r), "--out", str(r / "cal.json")],
            2,
        ),
        "calibrate plot inside its recording": (
            lambda t, r, d: ["calibrate", "--from", str(r), "--out", str(t / "c.json"), "--plot", str(r / "c.png")],
            2,
        ),
        "import vpace the same file twice": (
            lambda t, r, d: ["import", "vpace", str(_buffer(t, 0)), str(t / "." / "3_lift.gz"), *_to(t)],
            2,
        ),
        "import lerobot-v2.1 root inside its source": (
            lambda t, r, d: [
                "import",
                "lerobot-v2.1",
                str(_v21(t)),
                "--repo-id",
                "me/x",
                "--root",
                str(t / "v21" / "x"),
            ],
            2,
        ),
        "fire aggregate out inside the expert": (
            lambda t, r, d: [
                "fire",
                "aggregate",
                "--expert",
                str(d),
                "--rollouts",
                str(d),
                "--out",
                str(d / "agg"),
                "--repo-id",
                "me/a",
            ],
            2,
        ),
        "fire aggregate the same rollouts twice": (
            lambda t, r, d: [
                "fire",
                "aggregate",
                "--expert",
                str(_copy(d, t / "expert")),
                "--rollouts",
                str(d),
                f"{d}/",
                "--out",
                str(t / "agg"),
                "--repo-id",
                "me/a",
            ],
            2,
        ),
    }
)
MESSAGES.update(
    {
        "info info.json is a list": "info.json: the file must be an object, got a list",
        "import lerobot-v2.1 info.json is a list": "info.json: the file must be an object, got a list",
        "import lerobot-v2.1 feature is a list": "'features.action' must be an object",
        "info feature shape is text": "'features.action.shape' must be a list",
        "info stats entry is a list": "stats.json: 'action' must be an object, got a list",
        "info provenance stages is an object": "'stages' must be a list",
        "train bc provenance output is text": "'output' must be an object",
        "import robomimic actions of three dimensions": "data/demo_0/actions",
        "import robomimic demo is a dataset": "data/demo_1",
        "plot roc metrics line without scores": "'scores' is missing",
        "plot roc score is text": "'scores.beta' must be a number",
        "plot fire expert samples missing": "'expert_samples' is missing",
        "plot fire execution time is text": "'execution_time_s' must be a finite number",
        "collect env kwarg 1e308": "--env-kwarg max_episode_seconds must be at most 1e+09",
        "eval env kwarg 1e308": "--env-kwarg max_episode_seconds must be at most 1e+09",
        "sim-robot truncated plan array": "action.npy",
        "run the same source twice": "again",
        "run one source spelled two ways": "again",
        "run a copy of a source": "holds the same data as",
        "merge the same source twice": "again",
        "merge a copy of a source": "holds the same data as",
        "merge into its source": "lies inside the input",
        "sim-robot out inside its plan": "lies inside the input plan",
        "calibrate out inside its recording": "lies inside the input --from",
        "calibrate plot inside its recording": "--plot",
        "import vpace the same file twice": "again",
        "import lerobot-v2.1 root inside its source": "lies inside the input",
        "fire aggregate out inside the expert": "lies inside the input --expert",
        "fire aggregate the same rollouts twice": "give each input once",
    }
)


def _set_v21_info(t: Path, value) -> Path:
    src = _v21(t)
    (src / "meta/info.json").write_text(json.dumps(value))
    return src


def _v21_features(t: Path, features) -> Path:
    src = _v21(t)
    _json_edit("meta/info.json", features=features)(src)
    return src


def _fire_run_with_line(t: Path, line: str) -> Path:
    run = _fire_run(t)
    with open(run / "metrics.jsonl", "a") as f:
        f.write(line + "\n")
    return run


def _fire_run_config(t: Path, config) -> Path:
    run = _fire_run(t)
    (run / "config.json").write_text(json.dumps(config))
    return run


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
    if name in MESSAGES:
        assert MESSAGES[name] in outcome.error_line, f"{name}: {outcome.error_line}"
    assert (tree_state(rel_raw), tree_state(rel_ds)) == before, f"{name} modified an input"


OS_ERRORS = (
    PermissionError(errno.EACCES, "Permission denied", "/x/locked"),
    NotADirectoryError(errno.ENOTDIR, "Not a directory", "/x/file/sub"),
    OSError(errno.EIO, "Input/output error", "/x/disk"),
    OSError(errno.EROFS, "Read-only file system", "/x/ro"),
)


@pytest.mark.parametrize("exc", OS_ERRORS, ids=lambda e: e.strerror)
def test_os_errors_are_one_line(exc, tmp_path, rel_raw, monkeypatch):
    """An OSError on a user path anywhere under a command: one line naming the path and the cause
    (as root, permissions cannot be taken away here, so the error is raised where the work dir is made)."""
    import shiftkit.pipelines.runner as runner

    def fail(*args, **kwargs):
        raise exc

    monkeypatch.setattr(runner, "_prepare_work_dir", fail)
    outcome = cli(["run", pipeline(tmp_path, rel_raw), "--no-progress"])
    assert outcome.clean and outcome.code == 2, outcome
    assert exc.strerror in outcome.error_line and exc.filename in outcome.error_line


def test_plain_validate_says_statistics_are_not_recomputed(rel_ds):
    outcome = cli(["validate", str(rel_ds)])
    assert outcome.code == 0 and "statistics not recomputed from the data (--deep does)" in outcome.stdout, outcome


def test_fire_aggregate_policy_trained_on_other_data(bc_run, rel_ds):
    """`fire aggregate --policy` of a policy trained in another env: same feature names, other sizes,
    is one line before any work (it used to fail deep in D's first batch)."""
    from shiftkit.datasets.errors import DatasetError
    from shiftkit.policies.bc_policy import load_policy
    from shiftkit.policies.fire.aggregate import AggregateArgs, _spec

    spec = load_policy(bc_run).spec
    recorded = {**spec.features, "action": spec.action}
    recorded["observation.state"] = {**recorded["observation.state"], "shape": [99]}
    args = AggregateArgs(expert=str(rel_ds), rollouts=[str(rel_ds)], out="o", repo_id="me/a", policy=str(bc_run))
    with pytest.raises(DatasetError, match="it was trained on other data") as error:
        _spec(args, rel_ds, recorded)
    assert "\n" not in str(error.value)
    assert _spec(args, rel_ds, {**spec.features, "action": spec.action}) == spec  # the data it was trained on
