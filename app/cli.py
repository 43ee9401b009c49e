"""The `shiftkit` command line: a thin dispatcher over `shiftkit.app.commands.*`.

Each command module of `shiftkit.app.commands` (registered in `COMMANDS` by its name) defines `HELP`
(one line, plain text), `add_arguments(parser)` and `run(args) -> int`, and imports its heavy
dependencies inside `run`. Only the command named on the command line gets its
options built (`shiftkit --help` builds none, so it imports no trainer, torch or simulator); a command
with subcommands may take `add_arguments(parser, argv)`, the words after its name, to build only the
chosen subcommand's. No parser accepts abbreviated options (`--expert` is not `--expert-margin`).
User mistakes raise `ShiftkitError`, printed here as one line with exit code 2.
"""

from __future__ import annotations

import argparse
import inspect
import logging
import os
import sys
import typing

from shiftkit.app.commands import COMMANDS
from shiftkit.datasets.errors import ShiftkitError


class Parser(argparse.ArgumentParser):
    """An argparse parser that takes options only by their full name and reports a bad command
    line in one line (`shiftkit fire: error: argument --beta: must be a positive integer, got '0'`,
    exit 2), as every other user mistake is; `add_subparsers` makes its subparsers of this class, so
    every command and subcommand behaves alike."""

    def __init__(self, *args, **kwargs) -> None:  # noqa: ANN002, ANN003 - argparse's signature
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    @typing.override
    def parse_known_args(self, args=None, namespace=None):  # noqa: ANN001, ANN201 - argparse's signature
        self._words = list(sys.argv[1:] if args is None else args)
        return super().parse_known_args(args, namespace)

    @typing.override
    def error(self, message: str) -> typing.NoReturn:
        # an unknown option's value is otherwise taken for a subcommand ("invalid choice: 'local/exp'")
        unknown = [
            w.split("=")[0]
            for w in getattr(self, "_words", [])
            if w.startswith("--") and w.split("=")[0] not in self._option_string_actions
        ]
        if "invalid choice" in message and unknown:
            message = f"unrecognized arguments: {' '.join(unknown)}"
        command = _chosen(getattr(self, "_words", []))[0] if " " not in self.prog else ""
        where = f"{self.prog} {command}" if command in COMMANDS else self.prog  # as `_fail` names it
        self.exit(2, f"{where}: error: {' '.join(message.split())}\n")


def _chosen(argv: list[str]) -> tuple[str, list[str]]:
    """The command named in `argv` ("" for none, e.g. `shiftkit --help`) and the words after it."""
    for i, word in enumerate(argv):
        if not word.startswith("-"):
            return word, argv[i + 1 :]
        if word in ("-h", "--help"):
            break
    return "", []


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser of `shiftkit`; with `argv`, only the command it names gets its options."""
    parser = Parser(
        prog="shiftkit",
        description="Datasets, environments and trainers against distribution shift in imitation learning.",
    )
    parser.add_argument("--verbose", "-v", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    chosen, rest = _chosen(argv) if argv is not None else (None, None)
    for name, module in COMMANDS.items():
        p = sub.add_parser(name, help=module.HELP.replace("%", "%%"), description=module.HELP)
        if chosen is None or chosen == name:
            nested = len(inspect.signature(module.add_arguments).parameters) > 1
            module.add_arguments(p, rest) if nested else module.add_arguments(p)
            p.set_defaults(_run=module.run)
    return parser


def os_error_text(exc: OSError) -> str:
    """One line naming the path(s) and the cause of an OSError."""
    cause = exc.strerror or str(exc) or type(exc).__name__
    paths = [
        os.fsdecode(p) if isinstance(p, (str, bytes)) else str(p)
        for p in (exc.filename, exc.filename2)
        if p is not None
    ]
    named = " -> ".join(ascii(p)[1:-1] if not p.isprintable() else p for p in paths)
    return f"{named}: {cause}" if named else cause


def _fail(command: str, message: str) -> int:
    # Paths with undecodable bytes (surrogate escapes) are shown escaped rather than crashing print.
    line = " ".join(message.split("\n")).encode("utf-8", "backslashreplace").decode("utf-8")
    print(f"shiftkit {command}: error: {line}", file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    """Run the command named in `argv` (default: `sys.argv[1:]`); return its exit code (2 and one line on stderr for a
    user mistake)."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        args = build_parser(argv).parse_args(argv)
    except SystemExit as exc:  # --help (0) or a bad command line (2, its one line printed)
        return exc.code if isinstance(exc.code, int) else 2
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING, format="%(message)s")
    try:
        return int(args._run(args) or 0)
    except ShiftkitError as exc:
        return _fail(args.command, str(exc))
    except BrokenPipeError:  # the reader of stdout left (`shiftkit info ds | head -2`): not an error
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as exc:  # a user path that cannot be read or written, or a full disk
        return _fail(args.command, os_error_text(exc))
    except UnicodeError as exc:  # a file name that is not valid in the file system's encoding
        return _fail(args.command, f"a path or text is not valid here ({exc.reason})")
    except KeyboardInterrupt:
        print(f"shiftkit {args.command}: interrupted", file=sys.stderr)
        return 130


def entry() -> typing.NoReturn:
    """The `shiftkit` console script: `main`, then the process ends without Python's finalization.

    Before Python 3.14 finalization stops daemon threads with `pthread_exit`; one stopped inside C++
    code (a torch op, a library's worker waiting to take the interpreter back) aborts the whole process
    with "terminate called without an active exception" (exit 134) after the command has succeeded.
    So the exit does what finalization would do for the command's results (non-daemon threads joined,
    atexit handlers such as temporary-folder cleanup and log flushing run, streams flushed) and then
    leaves with the command's code."""
    import atexit
    import contextlib
    import threading

    code = main()
    getattr(threading, "_shutdown", lambda: None)()  # joins non-daemon threads, as finalization does
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):  # a closed pipe or stream has nothing left to write
            stream.flush()
    os._exit(code)


if __name__ == "__main__":
    entry()
