"""The README's "Reliability" section states the counts the suite computes (tests/reliability/counts.py)."""

from __future__ import annotations

from pathlib import Path

from tests.reliability.counts import counts, readme_section


def test_readme_reliability_section_is_current():
    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    assert readme_section() in readme, "update README.md with `python -m tests.reliability.counts`"


def test_counts_are_substantial():
    c = counts()
    assert c["bad_inputs"] >= 50 and c["fuzzed"] >= 100 and c["faults"] >= 8 and c["integrity"] >= 20
