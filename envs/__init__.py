"""shiftkit.envs: MuJoCo scenes, gymnasium tasks, controllers, cameras and scripted experts.

Imports nothing else of shiftkit. Shared pieces (the Panda model, Cartesian controllers, cameras,
the family registry `family.py`, and `registry.py`, the one registry class every layer of shiftkit
uses) are modules here; each environment family is a package of its own (`panda_play/`, ...) that
registers itself with its gymnasium ids (`shiftkit/PandaPlay-<Task>-v0`, ...). The families are
imported on the first question asked of the registry, not with this package, so the shared modules
load without MuJoCo (and this package without gymnasium); `make(env_name, task, **kw)` builds envs
by CLI name, `env_family(name)` gives a family's dataset facts and `ENV_TASKS` every env's tasks.
"""

from typing import Any

_FAMILY_NAMES = (
    "EnvFamily",
    "FAMILIES",
    "env_family",
    "env_tasks",
    "families",
    "gym_id",
    "import_families",
    "make",
    "register_family",
)


def __getattr__(name: str) -> Any:
    if name == "ENV_TASKS":  # computed on use: it needs every family imported
        from shiftkit.envs.family import env_tasks

        return env_tasks()
    if name in _FAMILY_NAMES:  # the family registry imports gymnasium: loaded on first use
        from shiftkit.envs import family

        return getattr(family, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["ENV_TASKS", *_FAMILY_NAMES]
