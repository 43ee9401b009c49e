"""Each checkout runs its own code: `scripts/ensure-env.sh` gives every clone its own small venv on
the shared dependency venv, so two clones at different commits never swap code, deleting one does
not break the other, and outputs record the commit that made them."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import shiftkit.pipelines

REPO = Path(shiftkit.pipelines.__file__).resolve().parents[1]
DEPS_RECORD = Path(sys.prefix) / ".shiftkit-deps"

pytestmark = pytest.mark.skipif(
    not (REPO / ".git").exists() or not DEPS_RECORD.exists(),
    reason="needs a git checkout set up by scripts/ensure-env.sh",
)

PROBE = """
import json, shiftkit.pipelines
from shiftkit.datasets.provenance import versions
print(json.dumps({"file": shiftkit.pipelines.__file__, "mark": getattr(shiftkit.pipelines, "MARK", None), **versions()}))
"""


def git(cwd: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(cwd), *args], capture_output=True, text=True, check=True).stdout.strip()


def checkout(clone: Path) -> None:
    """A git checkout holding this working tree's files (tracked and new, not ignored), committed."""
    files = git(REPO, "ls-files", "-co", "--exclude-standard").splitlines()
    for name in files:
        if (REPO / name).is_file():
            (clone / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / name, clone / name)
    git(clone.parent, "init", "-q", str(clone))
    git(clone, "add", "-A")
    git(clone, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "working tree")


def ensure_env(clone: Path) -> Path:
    env = {"PATH": "/usr/bin:/bin", "HOME": str(Path.home()), "SHIFTKIT_DEPS_VENV": DEPS_RECORD.read_text().strip()}
    out = subprocess.run(
        ["bash", str(clone / "scripts" / "ensure-env.sh")],
        capture_output=True,
        text=True,
        env={**env, "PYTHON": sys.base_prefix + "/bin/python3"},
        timeout=600,
    )
    assert out.returncode == 0, out.stderr
    return Path(out.stdout.strip().splitlines()[-1])


def probe(venv: Path) -> dict:
    out = subprocess.run([str(venv / "bin" / "python"), "-c", PROBE], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_two_clones_at_different_commits_each_run_their_own_code(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    for clone in (a, b):
        checkout(clone)
    (b / "pipelines" / "__init__.py").write_text('"""Clone b."""\n\nMARK = "b"\n')
    git(b, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qam", "clone b")
    venv_a, venv_b = ensure_env(a), ensure_env(b)
    assert venv_a == a / ".venv" and venv_b == b / ".venv"

    seen_a, seen_b = probe(venv_a), probe(venv_b)
    assert Path(seen_a["file"]).is_relative_to(a) and seen_a["mark"] is None
    assert Path(seen_b["file"]).is_relative_to(b) and seen_b["mark"] == "b"
    # the provenance names each clone's commit
    assert seen_a["shiftkit_commit"] == git(a, "rev-parse", "HEAD") and not seen_a["shiftkit_dirty"]
    assert seen_b["shiftkit_commit"] == git(b, "rev-parse", "HEAD") != seen_a["shiftkit_commit"]
    # a change to a tracked file shows as a dirty checkout, and which change it is: another change of
    # the same commit is other code (a run's work folder is not resumed across them), a new module too
    assert "shiftkit_changes" not in seen_a
    original = (a / "pipelines" / "__init__.py").read_text()
    (a / "pipelines" / "__init__.py").write_text(original + "\n")
    first = probe(venv_a)
    assert first["shiftkit_dirty"] is True and first["shiftkit_commit"] == seen_a["shiftkit_commit"]
    (a / "pipelines" / "__init__.py").write_text(original + "\nMARK = 1\n")
    second = probe(venv_a)
    (a / "pipelines" / "extra.py").write_text("X = 1\n")
    third = probe(venv_a)
    assert len({first["shiftkit_changes"], second["shiftkit_changes"], third["shiftkit_changes"]}) == 3
    (a / "pipelines" / "extra.py").unlink()
    assert probe(venv_a)["shiftkit_changes"] == second["shiftkit_changes"]  # the same change, the same hash
    # data and configs a user keeps in the clone do not
    (b / "data").mkdir()
    (b / "data" / "lift.toml").write_text("seed = 0\n")
    assert probe(venv_b)["shiftkit_dirty"] is False

    # an older install's egg-info in the clone would shadow the venv's entry points (the stage plug-ins)
    # for commands run from the clone; setting up again removes it
    stale = a / "shiftkit.egg-info"
    stale.mkdir()
    (stale / "PKG-INFO").write_text("Metadata-Version: 2.1\nName: shiftkit\nVersion: 0.0.1\n")
    (stale / "entry_points.txt").write_text("[console_scripts]\nshiftkit = shiftkit.app.cli:main\n")
    plugins = "from importlib import metadata; print(len(metadata.entry_points(group='shiftkit.plugins')))"

    def plugin_groups() -> str:
        run = [str(venv_a / "bin" / "python"), "-c", plugins]
        return subprocess.run(run, cwd=a, capture_output=True, text=True, timeout=120).stdout.strip()

    assert plugin_groups() == "0"
    # setting up a again does not move b, and deleting b leaves a working
    ensure_env(a)
    assert not stale.exists() and plugin_groups() == "1"
    assert probe(venv_b)["mark"] == "b"
    shutil.rmtree(b)
    assert Path(probe(venv_a)["file"]).is_relative_to(a)
    cli = subprocess.run([str(venv_a / "bin" / "shiftkit"), "--help"], capture_output=True, text=True, timeout=120)
    assert cli.returncode == 0 and "usage: shiftkit" in cli.stdout
