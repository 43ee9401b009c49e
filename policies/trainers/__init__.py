"""The trainer registry: every `shiftkit train` trainer registers itself here once.

A trainer is one folder in this package (`bc/`, `vpace/`): its `__init__.py` calls
`register(Trainer(...))` with everything the rest of shiftkit needs: its name (the `train`
subcommand and the `trainer` of its run's config.json), a one-line help, its args dataclass, its CLI
glue (options and run, in that `__init__.py`), the loader `shiftkit eval` uses for its policies, and
the citation its model cards carry; the folder's other modules hold the training itself. The heavy
parts (torch) are named as `module:attribute` and imported only when used, so `shiftkit train
--help` lists the trainers without importing any of them. `commands/train.py` builds its subcommands from `trainers()`,
`evaluation.load_policy` loads through `TRAINERS.get(name)`, `run_dir` passes the citation to the card.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any

from shiftkit.datasets.errors import ConfigError
from shiftkit.envs.registry import Registry, import_modules


@dataclass(frozen=True)
class Trainer:
    """One trainer, as it registers itself."""

    name: str
    """Subcommand of `shiftkit train`, and the `trainer` its runs record in config.json."""
    help: str
    """One line for `shiftkit train --help`."""
    args: str
    """`module:Class` of its args dataclass (the options of `shiftkit train NAME`)."""
    cli: str
    """Module with `add_arguments(parser, trainer)` and `run(namespace) -> int` (imports no torch)."""
    load_policy: str
    """`module:function(path, device)` loading a trained policy for `shiftkit eval`."""
    citation: str | None = None
    """The method's reference, cited by the model cards of its runs (the thesis is always cited)."""

    def args_class(self) -> type:
        """The args dataclass `args` names."""
        return _resolve(self.args)

    def cli_module(self) -> Any:
        """The imported `cli` module."""
        return importlib.import_module(self.cli)

    def policy_loader(self) -> Any:
        """The function `load_policy` names."""
        return _resolve(self.load_policy)


# Every trainer, found by importing each trainer folder of this package on the first lookup.
TRAINERS: Registry[Trainer] = Registry(
    "trainer", error=ConfigError, discover=[lambda: import_modules(__name__, __path__, packages_only=True)]
)
register = TRAINERS.register  # a trainer folder's `__init__.py` calls `register(Trainer(...))` once


def _resolve(ref: str) -> Any:
    module, _, attr = ref.partition(":")
    return getattr(importlib.import_module(module), attr)
