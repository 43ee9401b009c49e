"""The science scripts in bench/science/ run end to end: each `--quick` smoke run goes through every
command of the full run and prints its JSON result last."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

# `_`-prefixed modules are the scripts' shared helpers, not scripts
SCRIPTS = sorted(
    p for p in (Path(__file__).resolve().parents[1] / "bench" / "science").glob("*.py") if p.name[0] != "_"
)


@pytest.mark.slow
@pytest.mark.parametrize("script", SCRIPTS, ids=[s.stem for s in SCRIPTS])
def test_science_script_quick_run(script, tmp_path):
    done = subprocess.run(
        [sys.executable, str(script), "--quick", "--workdir", str(tmp_path)], capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["quick"] is True and result["bench"].startswith("science_")
    assert all(0.0 <= p["success"] <= 1.0 for p in result["policies"].values())
