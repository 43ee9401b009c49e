"""How the `shiftkit` process ends: with the command's exit code, whatever threads are still running.

Before Python 3.14 the interpreter's finalization stops daemon threads with `pthread_exit`; one that is
inside C++ code then aborts the process ("terminate called without an active exception", exit 134)
after the command has finished and printed its summary: a good result reported as a failure. The
console script (`app.cli.entry`) ends the process itself once the command's results are safe."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

# A daemon thread busy in torch's C++ code at exit (as a library's worker thread can be), a non-daemon
# thread still finishing, and a temporary folder left for atexit to remove.
SCRIPT = textwrap.dedent(
    """
    import pathlib, sys, tempfile, threading, time
    import torch

    torch.set_num_threads(1)
    a = torch.randn(300, 300)

    def spin():
        while True:
            a @ a

    threading.Thread(target=spin, daemon=True).start()
    scratch = tempfile.TemporaryDirectory()
    names, joined = map(pathlib.Path, sys.argv[1:3])
    names.write_text(scratch.name)

    def late():
        time.sleep(0.3)
        joined.write_text("joined")

    threading.Thread(target=late).start()
    time.sleep(0.1)
    sys.argv = ["shiftkit", "--help"]
    from shiftkit.app import cli

    {exit}
    """
)


@pytest.mark.parametrize(
    ("exit_call", "code"),
    [("cli.entry()", 0), ("sys.exit(cli.main())", 134)],
    ids=["console-entry", "plain-finalization"],
)
def test_a_finished_command_exits_with_its_code_despite_a_daemon_thread_in_cpp(tmp_path, exit_call, code):
    """The console entry exits 0 (help printed, the non-daemon thread joined, the temporary folder
    removed); returning through Python's finalization, as the script did before, aborts with 134 (the
    second case shows the test can fail)."""
    names, joined = tmp_path / "scratch.txt", tmp_path / "joined.txt"
    script = tmp_path / "run.py"
    script.write_text(SCRIPT.format(exit=exit_call))
    proc = subprocess.run([sys.executable, str(script), str(names), str(joined)], capture_output=True, text=True)
    assert proc.returncode in ({code, -6} if code == 134 else {code}), proc.stderr[-2000:]
    if code == 0:
        assert "usage: shiftkit" in proc.stdout
        assert joined.read_text() == "joined"
        assert not Path(names.read_text()).exists()
