"""shiftkit.envs: MuJoCo scenes, gymnasium tasks, controllers, cameras and scripted experts.

Imports nothing else of shiftkit. Shared pieces (the Panda model, Cartesian controllers, cameras,
the family registry) are modules here; each environment family is a package of its own
(`panda_play/`, ...) that registers itself with its gymnasium ids (`shiftkit/PandaPlay-<Task>-v0`,
...). The families are imported on the first question asked of the registry, not with this package,
so the shared modules load without MuJoCo; `make(env_name, task, **kw)` builds envs by CLI name,
`env_family(name)` gives a family's dataset facts and `ENV_TASKS` every env's tasks.
"""

from shiftkit.envs.registry import (
    EnvFamily,
    env_family,
    env_tasks,
    families,
    gym_id,
    import_families,
    make,
    register_family,
)


def __getattr__(name: str) -> dict[str, tuple[str, ...]]:
    if name == "ENV_TASKS":  # computed on use: it needs every family imported
        return env_tasks()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "ENV_TASKS",
    "EnvFamily",
    "env_family",
    "env_tasks",
    "families",
    "gym_id",
    "import_families",
    "make",
    "register_family",
]
