"""Hub push/pull through the real huggingface_hub / lerobot client code against a loopback Hub.

The CLI runs in subprocesses with the hub environment set before anything is imported
(huggingface_hub reads HF_ENDPOINT and HF_HUB_OFFLINE at import time), pointed at the loopback
server from `hub_server.py`; nothing here reaches beyond 127.0.0.1.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from tests.helpers import tree_hashes
from tests.hub_server import LoopbackHub

WRITE, READ = "hf_test_write_token", "hf_test_read_token"
REPO = "shiftkit-test/tiny"


@pytest.fixture(scope="module")
def hub(tmp_path_factory):
    with LoopbackHub(tmp_path_factory.mktemp("hub-store"), {WRITE: "write", READ: "read"}) as server:
        yield server


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """A tiny state-only LeRobot v3.0 dataset: 2 episodes x 8 frames, seeded."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root = tmp_path_factory.mktemp("local") / "tiny"
    features = {
        "observation.state": {"dtype": "float32", "shape": (3,), "names": ["x", "y", "z"]},
        "action": {"dtype": "float32", "shape": (2,), "names": ["dx", "dy"]},
    }
    ds = LeRobotDataset.create(REPO, fps=10, features=features, root=root, robot_type="point", use_videos=False)
    rng = np.random.default_rng(0)
    for _ in range(2):
        for _ in range(8):
            ds.add_frame(
                {
                    "observation.state": rng.normal(size=3).astype(np.float32),
                    "action": rng.uniform(-1, 1, size=2).astype(np.float32),
                    "task": "reach",
                }
            )
        ds.save_episode()
    ds.finalize()
    return root


def _env(hub_endpoint: str, home: Path) -> dict[str, str]:
    """The environment of a client process: this hub, a private HF home and LeRobot cache, online."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("HF_", "HUGGING"))}
    env.update(
        HF_ENDPOINT=hub_endpoint,
        HF_HUB_OFFLINE="0",
        HF_HOME=str(home / "hf-home"),
        HF_LEROBOT_HOME=str(home / "lerobot"),
        HF_DATASETS_CACHE=str(home / "datasets-cache"),
        HF_HUB_DISABLE_PROGRESS_BARS="1",
        HF_HUB_DISABLE_TELEMETRY="1",
        MUJOCO_GL="egl",
    )
    return env


# Runs the cases in ONE interpreter, in order (importing lerobot costs seconds on these machines): a
# list is the argv of the real `shiftkit` entry point, a string is Python code (e.g. training through
# the library API); HF_TOKEN is set per case (huggingface_hub reads it on every call).
_BATCH = textwrap.dedent("""
    import contextlib, io, json, os, sys
    from shiftkit.app.cli import main
    results = []
    for case in json.loads(sys.argv[1]):
        os.environ.pop("HF_TOKEN", None)
        if case["token"]:
            os.environ["HF_TOKEN"] = case["token"]
        err, out = io.StringIO(), io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
            if isinstance(case["run"], list):
                rc = main(case["run"])
            else:
                exec(case["run"], {})
                rc = 0
        results.append({"run": case["run"], "rc": rc, "stderr": err.getvalue(), "stdout": out.getvalue()})
    print(json.dumps(results))
""")


def start_batch(cases: list[tuple[list[str] | str, str | None]], endpoint: str, home: Path) -> subprocess.Popen:
    """Start running each (ARGV or Python code, HF_TOKEN) case in a client process."""
    payload = json.dumps([{"run": run, "token": token} for run, token in cases])
    return subprocess.Popen(
        [sys.executable, "-c", _BATCH, payload],
        env=_env(endpoint, home),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def batch_results(proc: subprocess.Popen) -> list[dict]:
    """rc, stdout and stderr of each case of a started batch."""
    stdout, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 0, stderr
    return json.loads(stdout.strip().splitlines()[-1])


def shiftkit_batch(cases: list[tuple[list[str] | str, str | None]], endpoint: str, home: Path) -> list[dict]:
    return batch_results(start_batch(cases, endpoint, home))


def assert_ok(results: list[dict]) -> None:
    for result in results:
        assert result["rc"] == 0, result


def file_hashes(root: Path) -> dict[str, str]:
    """sha256 of every file under root by relative path, without huggingface_hub's local `.cache`."""
    return {k: v for k, v in tree_hashes(root).items() if not k.startswith(".cache/")}


def files_under(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if p.is_file()] if root.exists() else []


def copy_tree(src: Path, dst: Path) -> Path:
    for p in files_under(src):
        (dst / p.relative_to(src)).parent.mkdir(parents=True, exist_ok=True)
        (dst / p.relative_to(src)).write_bytes(p.read_bytes())
    return dst


def test_push_pull_round_trip_is_identical_and_loads(hub, dataset, tmp_path):
    home = tmp_path / "home"
    # For a branch: the same data with its own card, pushed with an extra file, then without it.
    variant = copy_tree(dataset, tmp_path / "variant")
    (variant / "README.md").write_text("---\nlicense: apache-2.0\ntags: [LeRobot, shiftkit]\n---\n# variant\n")
    extra = copy_tree(variant, tmp_path / "variant-extra")
    (extra / "meta" / "notes.json").write_text("{}")
    from shiftkit.datasets.synthetic import write_synthetic_raw

    raw = write_synthetic_raw(tmp_path / "raw", episodes=2, length=6)
    (tmp_path / "p.toml").write_text(f'[[sources]]\npath = "{raw}"\n[destination]\nroot = "{tmp_path / "piped"}"\n')
    results = shiftkit_batch(
        [
            (["run", str(tmp_path / "p.toml"), "--no-progress", "--push", "shiftkit-test/piped"], WRITE),
            (["push", str(dataset), "--repo-id", REPO], WRITE),
            (["pull", REPO], None),
            (["push", str(extra), "--repo-id", REPO, "--revision", "exp"], WRITE),
            (["push", str(variant), "--repo-id", REPO, "--revision", "exp"], WRITE),
            (["pull", REPO, "--revision", "exp", "--root", str(tmp_path / "exp")], None),
            (["pull", REPO, "--force"], None),
            (
                f"from lerobot.datasets.lerobot_dataset import LeRobotDataset\nprint(LeRobotDataset({REPO!r}).root)",
                None,
            ),
            ("import sys\nprint('hf_xet loaded:', 'hf_xet' in sys.modules)", None),
        ],
        hub.endpoint,
        home,
    )
    assert_ok(results)
    # `shiftkit run --push` pushed the finished pipeline output, card and version tag included.
    piped = hub.store.meta("dataset", "shiftkit-test/piped")
    assert piped["tags"]["v3.0"] == piped["branches"]["main"]
    _, piped_tree = hub.store.tree("dataset", "shiftkit-test/piped", "main")
    assert {"README.md", "meta/info.json", "meta/shiftkit_provenance.json"} <= set(piped_tree)
    results = results[1:]
    assert "tagged v3.0" in results[0]["stdout"] and "tagged" not in results[2]["stdout"] + results[3]["stdout"]
    # The card was validated by the configured endpoint (never the fixed public one) and travelled in
    # the same single commit as the data.
    assert ("POST", "/api/validate-yaml") in hub.requests
    assert sum(m == "POST" and p.startswith(f"/api/datasets/{REPO}/commit/main") for m, p in hub.requests) == 1
    meta = hub.store.meta("dataset", REPO)
    assert meta["tags"]["v3.0"] == meta["branches"]["main"] != meta["branches"]["exp"]

    root = home / "lerobot" / REPO
    assert f"into {root}" in results[1]["stdout"]
    local, remote = file_hashes(dataset), file_hashes(root)
    assert {k: remote[k] for k in local} == local
    assert set(remote) - set(local) == {"README.md", ".gitattributes"}  # lerobot's card, the hub's attributes
    assert "LeRobot" in (root / "README.md").read_text()
    assert not [p for p in root.parent.iterdir() if p.name.startswith(".")]  # no staging folder left behind

    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    pulled, original = LeRobotDataset(REPO, root=root), LeRobotDataset(REPO, root=dataset)
    assert (pulled.meta.total_episodes, len(pulled)) == (2, 16)
    np.testing.assert_array_equal(pulled[11]["observation.state"].numpy(), original[11]["observation.state"].numpy())

    # The branch holds the variant: the file dropped by the second push is gone remotely too.
    exp_head = hub.store.commit("dataset", REPO, meta["branches"]["exp"])
    assert "meta/notes.json" in hub.store.commit("dataset", REPO, exp_head["parent"])["tree"]
    assert "meta/notes.json" not in exp_head["tree"]
    exp = file_hashes(tmp_path / "exp")
    assert exp == {**file_hashes(variant), ".gitattributes": exp[".gitattributes"]}
    assert file_hashes(root) == remote  # re-pulled with --force: still the v3.0 tag on main
    # lerobot loads the pulled copy by ID: huggingface_hub's download bookkeeping is not left in it,
    # which lerobot 0.6 takes for a stale mirror and downloads again into its own hub cache.
    assert str(root) in results[6]["stdout"].splitlines()
    assert not (root / ".cache").exists()
    # Every file went inline in its commit and came back as a plain download: hf_xet (installed with
    # huggingface_hub 1.x) was never needed, and the loopback hub has no xet or LFS service.
    assert results[7]["stdout"].strip() == "hf_xet loaded: False"


def test_pulled_dataset_trains_by_id_and_checkpoint_round_trips(hub, dataset, tmp_path):
    home, run, model = tmp_path / "home", tmp_path / "run", "shiftkit-test/bc-tiny"
    bare = tmp_path / "bare"  # a checkpoint folder without a model card
    bare.mkdir()
    (bare / "weights.bin").write_bytes(b"\x00" * 64)
    seed = [] if hub.store.exists("dataset", REPO) else [(["push", str(dataset), "--repo-id", REPO], WRITE)]
    train = (
        "from shiftkit.policies.trainers.bc.args import BCArgs\nfrom shiftkit.policies.trainers.bc.training import train\n"
        f"train(BCArgs(datasets=[{REPO!r}], output_dir={str(run)!r}, regime='fixed', steps=3, "
        "ensemble_size=1, hidden=[16], checkpoint_every=3, log_every=1))"
    )
    assert_ok(
        shiftkit_batch(
            [
                *seed,
                (train, None),  # an empty local cache: the ID resolves through the hub
                (["push", str(run), "--checkpoint", "--repo-id", model], WRITE),
                (["pull", model, "--checkpoint", "--root", str(tmp_path / "pulled-run")], None),
                (["push", str(bare), "--checkpoint", "--repo-id", "shiftkit-test/bare"], WRITE),
            ],
            hub.endpoint,
            home,
        )
    )
    config = json.loads((run / "config.json").read_text())
    assert config["datasets"][0]["id"] == REPO
    assert config["datasets"][0]["root"] == str(home / "lerobot" / REPO)
    assert file_hashes(dataset).items() <= file_hashes(home / "lerobot" / REPO).items()

    # The checkpoint came back byte for byte (plus the hub's .gitattributes) and loads the same policy.
    pulled = file_hashes(tmp_path / "pulled-run")
    assert pulled == {**file_hashes(run), ".gitattributes": pulled[".gitattributes"]}
    _, tree = hub.store.tree("model", "shiftkit-test/bare", "main")
    assert "library_name: shiftkit" in hub.store.blob("model", "shiftkit-test/bare", tree["README.md"]).decode()

    import torch

    from shiftkit.policies.bc_policy import load_policy

    obs = {"observation.state": torch.zeros(1, 3)}
    with torch.no_grad():
        assert torch.equal(load_policy(tmp_path / "pulled-run")(obs), load_policy(run)(obs))


def _seed_untagged_and_private(hub, dataset: Path) -> None:
    """Repositories set up directly in the server's store (admin side, not through the client)."""
    files = {p.relative_to(dataset).as_posix(): p.read_bytes() for p in files_under(dataset)}
    for repo_id, private, tag in (
        ("shiftkit-test/untagged", False, None),
        ("shiftkit-test/secret", True, "v3.0"),
        ("shiftkit-test/old", False, "v2.1"),
    ):
        if not hub.store.exists("dataset", repo_id):
            hub.store.create("dataset", repo_id, private=private)
            hub.store.apply_commit("dataset", repo_id, "main", "seed", None, files, [], [])
            if tag:
                hub.store.create_ref("dataset", repo_id, "tags", tag, "main")


def _assert_one_line_errors(results: list[dict], expected: list[str]) -> None:
    for result, needle in zip(results, expected, strict=True):
        lines = result["stderr"].strip().splitlines()
        assert result["rc"] == 2, result
        assert len(lines) == 1 and ": error: " in lines[0] and needle in lines[0], result
        assert "Traceback" not in result["stderr"]


def test_bad_inputs_give_one_line_errors_and_write_nothing(hub, dataset, tmp_path):
    _seed_untagged_and_private(hub, dataset)
    bad_card = copy_tree(dataset, tmp_path / "bad-card")
    (bad_card / "README.md").write_text("---\nlicense: [apache-2.0\n---\n# broken\n")
    bad_info = copy_tree(dataset, tmp_path / "bad-info")  # lerobot's card needs its typed info
    info = json.loads((bad_info / "meta" / "info.json").read_text())
    (bad_info / "meta" / "info.json").write_text(json.dumps({**info, "fps": 0}))
    cases = [
        (["push", str(dataset), "--repo-id", "shiftkit-test/noauth"], None),
        (["push", str(dataset), "--repo-id", "shiftkit-test/noauth"], "hf_not_a_token"),
        (["push", str(dataset), "--repo-id", "shiftkit-test/noauth"], READ),
        (["push", str(dataset), "--repo-id", "shiftkit-test/bad name!"], WRITE),
        (["push", str(bad_card), "--repo-id", "shiftkit-test/noauth"], WRITE),
        (["push", str(bad_info), "--repo-id", "shiftkit-test/noauth"], WRITE),
        (["push", str(tmp_path / "missing"), "--repo-id", "shiftkit-test/noauth"], WRITE),
        (["pull", "shiftkit-test/..bad"], None),
        (["pull", "shiftkit-test/untagged"], None),
        (["pull", "shiftkit-test/untagged", "--revision", "no-such-branch"], None),
        (["pull", "shiftkit-test/does-not-exist"], None),
        (["pull", "shiftkit-test/secret"], None),
        (["pull", "shiftkit-test/secret"], "hf_not_a_token"),
        (["pull", "shiftkit-test/old"], None),
        (["pull", "shiftkit-test/secret", "--root", str(tmp_path)], READ),
    ]
    # The same client against a port where nothing listens (run alongside: each process imports lerobot).
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        closed = f"http://127.0.0.1:{s.getsockname()[1]}"
    home, home_closed = tmp_path / "home", tmp_path / "home-closed"
    unreachable = start_batch(
        [(["push", str(dataset), "--repo-id", REPO], WRITE), (["pull", REPO], None)], closed, home_closed
    )
    results = shiftkit_batch(cases, hub.endpoint, home)
    _assert_one_line_errors(
        results,
        [
            "(401)",
            "(401)",
            "forbidden (403)",
            "invalid repo id",
            "invalid card metadata",
            "info.json: fps must be positive",
            "no such dataset folder",
            "invalid repo id",
            "no codebase version tag",
            "revision 'no-such-branch' not found",
            "shiftkit-test/does-not-exist",
            "(401)",
            "(401)",
            "versions v2.1, none compatible",
            "already exists",
        ],
    )
    _assert_one_line_errors(batch_results(unreachable), ["cannot reach the hub", "cannot reach the hub"])
    assert not hub.store.exists("dataset", "shiftkit-test/noauth")
    assert files_under(home / "lerobot") == files_under(home_closed / "lerobot") == []


def test_private_push_hides_the_repository(hub, dataset, tmp_path):
    checkpoint = tmp_path / "checkpoint"
    checkpoint.mkdir()
    (checkpoint / "weights.bin").write_bytes(b"\x01" * 32)
    results = shiftkit_batch(
        [
            (["push", str(dataset), "--repo-id", "shiftkit-test/private", "--private"], WRITE),
            (["push", str(checkpoint), "--checkpoint", "--repo-id", "shiftkit-test/private-run", "--private"], WRITE),
            (["pull", "shiftkit-test/private", "--root", str(tmp_path / "reader")], READ),
            (["pull", "shiftkit-test/private", "--root", str(tmp_path / "anonymous")], None),
        ],
        hub.endpoint,
        tmp_path / "home",
    )
    assert_ok(results[:3])
    _assert_one_line_errors(results[3:], ["(401)"])
    assert hub.store.meta("dataset", "shiftkit-test/private")["private"]
    assert hub.store.meta("model", "shiftkit-test/private-run")["private"]
    assert file_hashes(dataset).items() <= file_hashes(tmp_path / "reader").items()
    assert not (tmp_path / "anonymous").exists()
