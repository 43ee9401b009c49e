"""A checkpoint that does not fit on the disk: one line "no space left on device", nothing partial."""

from __future__ import annotations

import errno

import pytest

from shiftkit.pipelines.errors import ShiftkitError
from shiftkit.policies.run_dir import RunDir


@pytest.mark.parametrize(
    "failure",
    [
        OSError(errno.ENOSPC, "No space left on device"),
        RuntimeError("[enforce fail at inline_container.cc:668] . unexpected pos 64 vs 0: file write failed"),
    ],
    ids=["oserror", "torch"],
)
def test_full_disk_while_saving_a_checkpoint(tmp_path, monkeypatch, failure):
    import torch

    run = RunDir(tmp_path / "run", resume=False)
    run.write_config({"trainer": "bc", "args": {}})

    def full(obj, f, *args, **kwargs):
        f.write(b"partial")
        raise failure

    monkeypatch.setattr(torch, "save", full)
    with pytest.raises(ShiftkitError, match="no space left on device"):
        run.save_checkpoint(1, {"x": 1})
    assert sorted(p.name for p in run.checkpoint_dir.iterdir()) == []
    assert run.latest_checkpoint() is None
