"""The test suite. The clone's root is on sys.path (pytest's rootdir, `python -m pytest`'s working
directory): its folder `datasets/` (shiftkit.datasets) would shadow the installed Hugging Face
`datasets` that lerobot imports. The root goes after the installed packages here, before any test
module or conftest is imported (`tests.*` still imports from it; pytest's `--import-mode=append` in
pyproject.toml keeps it there), and child processes (`python -m shiftkit.app.cli`, `python -c`) do not
put their working directory first (PYTHONSAFEPATH, Python's -P)."""

import os
import sys
from pathlib import Path

_ROOT = Path(__file__).resolve().parents[1]
_AT_ROOT = [p for p in sys.path if Path(p or ".").resolve() == _ROOT]
sys.path[:] = [p for p in sys.path if p not in _AT_ROOT] + _AT_ROOT
os.environ["PYTHONSAFEPATH"] = "1"
