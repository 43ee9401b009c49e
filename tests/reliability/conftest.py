"""Fixtures of the reliability suite: a small raw dataset and the LeRobot dataset made from it,
built once per session and never modified by a test (tests copy them before mutating)."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def rel_raw(tmp_path_factory):
    from shiftkit.datasets.synthetic import write_synthetic_raw

    return write_synthetic_raw(tmp_path_factory.mktemp("rel") / "raw", episodes=4, length=10, seed=3, camera=(12, 16))


@pytest.fixture(scope="session")
def rel_ds(rel_raw):
    """LeRobot dataset `me/lift` converted from `rel_raw`."""
    from tests.helpers import write_raw_as_lerobot

    return write_raw_as_lerobot(rel_raw, "me/lift", rel_raw.parent / "ds")


@pytest.fixture(scope="session")
def bc_run(tmp_path_factory, rel_ds):
    """A BC run folder trained for two steps on `rel_ds` (a checkpoint per step)."""
    from tests.reliability.harness import cli

    run = tmp_path_factory.mktemp("bc") / "run"
    argv = ["train", "bc", "--dataset", str(rel_ds), "--output", str(run), "--regime", "fixed", "--steps", "2"]
    outcome = cli([*argv, "--ensemble", "1", "--hidden", "8", "--no-progress", "--checkpoint-every", "1"])
    assert outcome.code == 0, outcome
    return run
