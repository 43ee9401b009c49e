"""The `shiftkit` commands, one module each: `HELP`, `add_arguments(parser)` and `run(args) -> int`
(see `shiftkit.app.cli`). `COMMANDS` finds them: every module of this package is a command, named
after the module (`sim_robot` -> `sim-robot`, a trailing `_` dropped: `import_` -> `import`), so a new
command is one new module."""

from __future__ import annotations

import importlib
import pkgutil
from types import ModuleType

from shiftkit.envs.registry import Registry


def command_name(module: str) -> str:
    """The command a module of this package is: its name with `_` as `-`, a trailing `_` dropped."""
    return module.rstrip("_").replace("_", "-")


def _discover() -> None:
    for info in pkgutil.iter_modules(__path__):
        COMMANDS.register(importlib.import_module(f"{__name__}.{info.name}"), command_name(info.name))


COMMANDS: Registry[ModuleType] = Registry("command", discover=[_discover])
