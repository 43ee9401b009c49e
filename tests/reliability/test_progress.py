"""Long work shows progress: `train bc` and `collect` draw tqdm bars (loss / success rate), and
early stopping's step bound is stated before training."""

from __future__ import annotations

from tests.reliability.harness import cli


def test_train_bc_and_collect_show_progress(tmp_path, rel_ds):
    outcome = cli(["train", "bc", "--dataset", str(rel_ds), "--output", str(tmp_path / "run"), "--steps", "3"])
    assert outcome.code == 0, outcome
    assert "train bc" in outcome.stderr and "step" in outcome.stderr
    assert "early-stop: at most 3 steps" in outcome.stdout
    outcome = cli(["collect", "--task", "reach", "--episodes", "2", "--out", str(tmp_path / "raw")])
    assert outcome.code == 0 and "collect" in outcome.stderr and "success=" in outcome.stderr, outcome
