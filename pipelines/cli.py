"""The `shiftkit` command line: a thin dispatcher over `shiftkit.pipelines.commands.*`.

Each command module defines `HELP` (one line, plain text), `add_arguments(parser)` and `run(args) -> int`, and
imports its heavy dependencies inside `run`, so `shiftkit --help` stays fast. User mistakes raise
`ShiftkitError`, printed here as one line with exit code 2.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys

from shiftkit.pipelines.errors import ShiftkitError

# command name -> module under shiftkit.pipelines.commands
COMMANDS: dict[str, str] = {
    "demo": "demo",
    "collect": "collect",
    "plan": "plan",
    "run": "run",
    "info": "info",
    "validate": "validate",
    "import": "import_",
    "push": "push",
    "pull": "pull",
    "train": "train",
    "eval": "eval",
    "fire": "fire",
    "plot": "plot",
    "calibrate": "calibrate",
}


def _available_commands() -> dict[str, object]:
    modules = {}
    for name, module in COMMANDS.items():
        try:
            modules[name] = importlib.import_module(f"shiftkit.pipelines.commands.{module}")
        except ModuleNotFoundError as exc:
            if exc.name != f"shiftkit.pipelines.commands.{module}":
                raise
    return modules


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="shiftkit",
        description="Datasets, environments and trainers against distribution shift in imitation learning.",
    )
    parser.add_argument("--verbose", "-v", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, module in _available_commands().items():
        p = sub.add_parser(name, help=module.HELP.replace("%", "%%"), description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    os.environ.setdefault("MUJOCO_GL", "egl")
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING, format="%(message)s")
    try:
        return int(args._run(args) or 0)
    except ShiftkitError as exc:
        print(f"shiftkit {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"shiftkit {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
