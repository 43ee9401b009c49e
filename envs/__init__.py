"""shiftkit.envs: MuJoCo scenes, gymnasium tasks, controllers and scripted experts.

Imports nothing else of shiftkit. Importing this package registers the gymnasium ids
(`shiftkit/PandaPlay-<Task>-v0`); `make(env_name, task, **kw)` builds envs by CLI name.
"""

from shiftkit.envs.registry import ENV_TASKS, gym_id, make, register_all

register_all()

__all__ = ["ENV_TASKS", "gym_id", "make", "register_all"]
