"""shiftkit.envs: MuJoCo scenes, gymnasium tasks, controllers, cameras and scripted experts.

Imports nothing else of shiftkit. Shared pieces (the Panda model, Cartesian controllers, cameras,
the family registry) are modules here; each environment family is a package of its own
(`panda_play/`, ...) that registers itself. Importing this package imports every family and
registers its gymnasium ids (`shiftkit/PandaPlay-<Task>-v0`, ...); `make(env_name, task, **kw)`
builds envs by CLI name and `env_family(name)` gives a family's dataset facts.
"""

import importlib
import pkgutil

from shiftkit.envs.registry import EnvFamily, env_family, env_tasks, families, gym_id, make, register_family


def import_families(path: list[str] | None = None) -> None:
    """Import every family package on `path` (default: this package's folder), which registers it."""
    for module in pkgutil.iter_modules(__path__ if path is None else path):
        if module.ispkg:
            importlib.import_module(f"{__name__}.{module.name}")


import_families()
ENV_TASKS: dict[str, tuple[str, ...]] = env_tasks()

__all__ = ["ENV_TASKS", "EnvFamily", "env_family", "env_tasks", "families", "gym_id", "make", "register_family"]
