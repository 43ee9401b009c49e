"""Shared pieces of the reliability suite: run the CLI in-process and classify what happened.

An outcome is *clean* when the command either succeeded or printed exactly one line
`shiftkit COMMAND: error: ...` with exit code 2. Anything else (an exception escaping `main`, a
multi-line message, another exit code) is a *traceback* and fails the test that saw it.
"""

from __future__ import annotations

import contextlib
import io
import traceback
from dataclasses import dataclass
from pathlib import Path

from shiftkit.app.cli import main
from shiftkit.datasets.errors import ShiftkitError


@dataclass
class Outcome:
    code: int | None
    stdout: str
    stderr: str
    crash: str | None = None  # the traceback of an exception that escaped `main`

    @property
    def error_line(self) -> str | None:
        lines = [ln for ln in self.stderr.splitlines() if ln.startswith("shiftkit ") and ": error: " in ln]
        return lines[0] if len(lines) == 1 else None

    @property
    def clean(self) -> bool:
        return self.crash is None and (self.code == 0 or (self.code == 2 and self.error_line is not None))

    def __str__(self) -> str:
        return f"exit {self.code}; stderr: {self.stderr[-2000:]!r}; crash: {self.crash}"


def cli(argv: list[str]) -> Outcome:
    """`shiftkit ARGV` in this process (no progress bars), with stdout/stderr captured."""
    out, err = io.StringIO(), io.StringIO()
    crash = None
    code: int | None = None
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(argv)
        except SystemExit as exc:  # argparse usage errors exit 2 with a usage line
            code = exc.code if isinstance(exc.code, int) else 1
        except BaseException:  # noqa: BLE001 - anything escaping main is what we count
            crash = traceback.format_exc()
    outcome = Outcome(code, out.getvalue(), err.getvalue(), crash)
    if code == 2 and crash is None and outcome.error_line is None and "usage:" in outcome.stderr:
        # argparse's own rejection (usage + one error line) is a clean one-line error too.
        outcome.stderr = "shiftkit usage: error: " + outcome.stderr.strip().splitlines()[-1]
    return outcome


def clean_or_error(call) -> str:
    """Run `call()`: "ok", or "error" for a ShiftkitError; any other exception propagates."""
    try:
        call()
    except ShiftkitError as exc:
        assert "\n" not in str(exc), f"multi-line error: {exc!r}"
        return "error"
    return "ok"


def tree_state(root: Path) -> dict[str, tuple[int, int]]:
    """(size, mtime) of every file under `root`: equal before and after means it was not modified."""
    if not root.exists():
        return {}
    return {
        str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns)
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }
