"""Environment registry: `make(env_name, task, **kw)` for the CLI names and gymnasium ids.

Gymnasium ids: `shiftkit/PandaPlay-<Task>-v0` (e.g. `shiftkit/PandaPlay-Lift-v0`), registered when
`shiftkit.envs` is imported; `gymnasium.make(id, control_hz=5, render_mode="rgb_array")` passes the
keyword arguments through.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym

from shiftkit.envs.panda_play_tasks import TASKS

ENV_TASKS: dict[str, tuple[str, ...]] = {"panda-play": tuple(TASKS)}
PANDA_PLAY_ENTRY = "shiftkit.envs.panda_play_env:PandaPlayEnv"


def gym_id(env_name: str, task: str) -> str:
    """The gymnasium id of a registered env/task pair."""
    if env_name != "panda-play" or task not in TASKS:
        raise ValueError(f"unknown env/task {env_name}/{task}")
    return f"shiftkit/PandaPlay-{TASKS[task].gym_name}-v0"


def make(env_name: str, task: str, **kwargs: Any) -> gym.Env:
    """Build an environment by CLI name; ValueError (one line) for unknown names."""
    if env_name not in ENV_TASKS:
        raise ValueError(f"unknown env {env_name!r}; known: {', '.join(ENV_TASKS)}")
    if task not in ENV_TASKS[env_name]:
        raise ValueError(f"unknown task {task!r} for env {env_name}; known: {', '.join(ENV_TASKS[env_name])}")
    from shiftkit.envs.panda_play_env import PandaPlayEnv

    return PandaPlayEnv(task=task, **kwargs)


def register_all() -> None:
    for task in TASKS:
        env_id = gym_id("panda-play", task)
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=PANDA_PLAY_ENTRY, kwargs={"task": task},
                         disable_env_checker=False)
