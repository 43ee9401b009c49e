"""The IQM and stratified-bootstrap interval of the science scripts (`bench/science/_study.py`)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench" / "science"))
from _study import iqm_ci  # noqa: E402


def test_iqm_is_the_mean_of_the_middle_half():
    scores = [0.9, 0.1, 0.5, 0.3, 1.0, 0.0, 0.7, 0.2]  # sorted: 0 .1 .2 .3 .5 .7 .9 1; middle half .2 .3 .5 .7
    iqm, low, high = iqm_ci(scores)
    assert iqm == pytest.approx((0.2 + 0.3 + 0.5 + 0.7) / 4)
    assert 0.0 <= low <= iqm <= high <= 1.0 and low < high


def test_three_runs_keep_every_score():
    assert iqm_ci([0.0, 0.5, 1.0])[0] == pytest.approx(0.5)  # floor(0.75) = 0 cut from each end


def test_same_seed_same_interval_and_another_seed_resamples_anew():
    scores = {"lift": [0.1, 0.4, 0.8, 0.9, 0.6], "stack": [0.0, 0.2, 0.3]}
    assert iqm_ci(scores, seed=3) == iqm_ci(scores, seed=3)
    assert iqm_ci(scores, seed=3)[1:] != iqm_ci(scores, seed=4)[1:]


def test_stratified_resampling_keeps_each_task_apart():
    # Within-task resampling: every bootstrap sample has 2 lift runs (1.0) and 2 stack runs (0.0), so
    # the IQM is 0.5 in every resample; pooled resampling would spread it.
    iqm, low, high = iqm_ci({"lift": [1.0, 1.0], "stack": [0.0, 0.0]})
    assert iqm == low == high == pytest.approx(0.5)


def test_single_runs_give_the_iqm_as_interval():
    assert iqm_ci([0.4]) == (0.4, 0.4, 0.4)
    # a's one run is in every resample; b's two give (0, 0), (0, 1) or (1, 1): IQMs 0.2/3, 1.2/3, 2.2/3
    iqm, low, high = iqm_ci({"a": [0.2], "b": [0.0, 1.0]})
    assert (iqm, low, high) == pytest.approx((1.2 / 3, 0.2 / 3, 2.2 / 3))
    with pytest.raises(ValueError):
        iqm_ci({"a": []})
