"""Checkpoints and work files are data, not code: a checkpoint that carries a pickled payload is
refused in one line by every command that reads one, and its payload never runs."""

from __future__ import annotations

import pickle
import shutil
from pathlib import Path

import pytest

from tests.reliability.harness import cli, tree_state


class Payload:
    """Unpickling this writes `marker`: the code a tampered checkpoint would run on the user's machine."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (exec, (f"open({str(self.marker)!r}, 'w').write('ran')",))


def _tampered(run: Path, tmp: Path, name: str) -> tuple[Path, Path]:
    """A copy of `run` whose newest checkpoint is a pickle with a payload, named `name` (last.txt points
    at it); returns (the copy, the file the payload would write)."""
    import json

    copy = tmp / "tampered"
    shutil.copytree(run, copy)
    config = json.loads((copy / "config.json").read_text())
    config["args"]["output_dir"] = str(copy)  # the run as if trained here (so that --resume continues it)
    (copy / "config.json").write_text(json.dumps(config))
    marker = tmp / "payload-ran"
    for old in (copy / "checkpoints").glob("step-*"):
        old.unlink()
    payload = {"step": 2, "model": Payload(marker)}
    if name.endswith(".pt"):  # as torch.save writes it: a zip archive around the pickle
        import torch

        torch.save(payload, copy / "checkpoints" / name)
    else:
        (copy / "checkpoints" / name).write_bytes(pickle.dumps(payload))
    (copy / "checkpoints" / "last.txt").write_text(name)
    return copy, marker


def _resume(run: Path) -> list[str]:
    """`train bc --resume` of the tampered copy (DS: the dataset it trained on)."""
    small = ["--regime", "fixed", "--steps", "2", "--ensemble", "1", "--hidden", "8", "--checkpoint-every", "1"]
    return ["train", "bc", "--dataset", "DS", "--output", str(run), "--resume", *small, "--no-progress"]


# name -> (checkpoint file name, argv builder (tampered run, its checkpoint, tmp) -> argv)
CASES = {
    "eval a tampered .pt checkpoint": (
        "step-00000002.pt",
        lambda run, ckpt, t: ["eval", "--policy", str(ckpt), "--task", "reach", "--out", str(t / "e.json")],
    ),
    "eval a run whose last checkpoint is tampered": (
        "step-00000002.pt",
        lambda run, ckpt, t: ["eval", "--policy", str(run), "--task", "reach", "--out", str(t / "e.json")],
    ),
    "eval a pickle named .safetensors": (
        "step-00000002.safetensors",
        lambda run, ckpt, t: ["eval", "--policy", str(ckpt), "--task", "reach", "--out", str(t / "e.json")],
    ),
    "train bc --resume on a tampered checkpoint": ("step-00000002.pt", lambda run, ckpt, t: _resume(run)),
    "train bc --resume on a tampered .safetensors": ("step-00000002.safetensors", lambda run, ckpt, t: _resume(run)),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_a_tampered_checkpoint_is_refused_and_never_runs(name, bc_run, rel_ds, tmp_path, monkeypatch):
    file_name, build = CASES[name]
    run, marker = _tampered(bc_run, tmp_path, file_name)
    before = tree_state(run / "checkpoints")
    monkeypatch.chdir(tmp_path)
    argv = [str(rel_ds) if a == "DS" else a for a in build(run, run / "checkpoints" / file_name, tmp_path)]
    outcome = cli(argv)
    assert not marker.exists(), f"{name}: the checkpoint's payload ran"
    assert outcome.clean and outcome.code == 2, f"{name}: {outcome}"
    assert file_name in outcome.error_line, outcome.error_line
    assert tree_state(run / "checkpoints") == before, f"{name} modified the checkpoint folder"


def test_last_txt_cannot_point_outside_the_run(bc_run, tmp_path):
    copy = tmp_path / "run"
    shutil.copytree(bc_run, copy)
    (copy / "checkpoints" / "last.txt").write_text("../../elsewhere.pt")
    outcome = cli(["eval", "--policy", str(copy), "--task", "reach", "--out", str(tmp_path / "e.json")])
    assert outcome.clean and outcome.code == 2 and "does not name a checkpoint" in outcome.error_line, outcome


def test_a_new_checkpoint_is_safetensors_with_json_state(bc_run):
    from safetensors import safe_open

    from shiftkit.policies.run_dir import STATE_KEY, load_checkpoint

    last = (bc_run / "checkpoints" / "last.txt").read_text()
    assert last == "step-00000002.safetensors"
    with safe_open(str(bc_run / "checkpoints" / last), framework="pt") as f:
        assert '"trainer":"bc"' in f.metadata()[STATE_KEY]
    assert load_checkpoint(bc_run / "checkpoints" / last)["step"] == 2


def test_an_older_plain_pt_checkpoint_still_loads(bc_run, tmp_path):
    """A `.pt` of an older shiftkit (tensors and plain values only) loads through the weights-only reader."""
    import torch

    from shiftkit.policies.bc_policy import load_policy
    from shiftkit.policies.run_dir import load_checkpoint

    copy = tmp_path / "old"
    shutil.copytree(bc_run, copy)
    new = copy / "checkpoints" / "step-00000002.safetensors"
    state = load_checkpoint(new)
    torch.save(state, copy / "checkpoints" / "step-00000002.pt")
    new.unlink()
    (copy / "checkpoints" / "last.txt").write_text("step-00000002.pt")
    a, b = load_policy(bc_run).state_dict(), load_policy(copy).state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_a_work_part_holding_a_pickle_is_refused(tmp_path):
    """A pipeline's parts hold plain arrays only: a tree file whose array is an object array (a pickle
    after its header) is a one-line error and does not run."""
    import json

    import numpy as np

    from shiftkit.datasets import data_tree
    from shiftkit.datasets.errors import DatasetError
    from shiftkit.pipelines.work import PartStore

    store = PartStore(tmp_path)
    store.dir.mkdir(parents=True)
    marker = tmp_path / "payload-ran"
    payload = pickle.dumps(np.array([Payload(marker)], dtype=object))
    header = json.dumps({"doc": {"$shiftkit": "array", "k": "a0"}, "arrays": {"a0": ["|O", [1], 0, len(payload)]}})
    head = data_tree.MAGIC + len(header).to_bytes(8, "little") + header.encode()
    store.path(0, 0).write_bytes(head + bytes(-len(head) % 64) + payload)
    with pytest.raises(DatasetError, match="not a plain array"):
        list(store.read(0, 0))
    assert not marker.exists()


def test_a_pulled_checkpoint_with_a_payload_is_refused(bc_run, tmp_path):
    """`pull --checkpoint` checks what it downloaded the way `eval` reads it (here on the folder
    the hub download fills: the hub itself is tested in tests/test_hub.py)."""
    from shiftkit.datasets.errors import DatasetError
    from shiftkit.policies.run_dir import check_checkpoint_files

    run, marker = _tampered(bc_run, tmp_path, "step-00000002.pt")
    check_checkpoint_files(bc_run)  # a good run folder passes
    with pytest.raises(DatasetError, match="refused"):
        check_checkpoint_files(run)
    assert not marker.exists()


@pytest.mark.parametrize(
    "entry",
    [
        ["|O", [1], 0, 8],  # an object array
        [{"names": ["a"]}, [1], 0, 8],  # a dtype numpy cannot build
        ["<f8", [1e400], 0, 8],  # JSON's Infinity as a dimension
        ["<f8", [[1]], 0, 8],
        ["<f8", [-1], 0, -8],
        ["<f8", [2], 0, 8],  # the size does not match the shape
        ["<f8", [1], 8, 8],  # past the end of the file
        ["<f8", [1], 0],
        "a0",
    ],
)
def test_a_tree_file_with_a_foreign_array_entry_is_one_line(entry, tmp_path):
    """A work part's header entry that does not describe a plain array inside the file is a one-line
    error naming the array, whatever numpy or int() would raise for it."""
    import json

    from shiftkit.datasets import data_tree
    from shiftkit.datasets.errors import DatasetError

    header = json.dumps({"doc": {"$shiftkit": "array", "k": "a0"}, "arrays": {"a0": entry}}).encode()
    head = data_tree.MAGIC + len(header).to_bytes(8, "little") + header
    path = tmp_path / "part.tree"
    path.write_bytes(head + bytes(-len(head) % 64) + bytes(8))
    with pytest.raises(DatasetError, match="array 'a0' is not a plain array inside the file") as error:
        data_tree.load_tree(path)
    assert "\n" not in str(error.value)
