"""A checkpoint that does not fit on the disk: one line "no space left on device", nothing partial."""

from __future__ import annotations

import errno

import pytest

from shiftkit.datasets.errors import ShiftkitError
from shiftkit.policies.run_dir import RunDir


def test_full_disk_while_saving_a_checkpoint(tmp_path, monkeypatch):
    import shiftkit.policies.run_dir as run_dir

    run = RunDir(tmp_path / "run", resume=False)
    run.write_config({"trainer": "bc", "args": {}})

    def full(fd):  # the data is written, the disk cannot take it when it is flushed
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(run_dir.os, "fsync", full)
    with pytest.raises(ShiftkitError, match="no space left on device"):
        run.save_checkpoint(1, {"x": 1})
    assert sorted(p.name for p in run.checkpoint_dir.iterdir()) == []
    assert run.latest_checkpoint() is None
