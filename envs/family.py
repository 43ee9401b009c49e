"""The environment families (`FAMILIES`, a `registry.Registry`): CLI names, tasks, gymnasium ids and
the facts that the dataset tools need (how an observation splits into LeRobot features, cameras,
experts).

A family is a package under `shiftkit/envs/` whose `__init__` calls `register_family(EnvFamily(...))`
with everything the rest of shiftkit uses of it (dataset layout, recorders, the expert as a policy);
the first question asked of the registry imports every such package under `shiftkit/envs/` (pkgutil),
so a new family only adds a folder, and importing a shared module (`geometry`, `base_pose`) loads no
family and no MuJoCo. Gymnasium ids are `shiftkit/<gym_prefix>-<TaskName>-v0` (e.g.
`shiftkit/PandaPlay-Lift-v0`), registered with the family; `gymnasium.make(id, control_hz=5,
render_mode="rgb_array")` passes keyword arguments through once the family is imported
(`gymnasium.make("shiftkit.envs.panda_play:shiftkit/PandaPlay-Lift-v0")` imports it).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np

from shiftkit.envs.registry import Registry, import_modules


@dataclass(frozen=True)
class EnvFamily:
    """One environment family (a scene with its tasks, experts and dataset layout)."""

    name: str
    """CLI name (`--env`)."""
    tasks: dict[str, str]
    """CLI task name -> CamelCase part of the gymnasium id."""
    gym_prefix: str
    """Family part of the gymnasium id."""
    entry_point: str
    """`module:Class` of the gymnasium env; its constructor takes `task=` plus keyword arguments."""
    robot: str
    """Robot type written into datasets."""
    sim_model_id: str
    """Identifier of the MuJoCo model recorded with simulator states (replay/re-render check it)."""
    cameras: tuple[str, ...]
    """Camera names that can be rendered into datasets."""
    observation_names: tuple[str, ...]
    """Names of the flat observation vector's dimensions."""
    state_indices: np.ndarray
    """Observation dims that form `observation.state` (robot proprioception)."""
    environment_state_indices: np.ndarray
    """Observation dims that form `observation.environment_state` (privileged object state)."""
    action_names: tuple[str, ...]
    """Names of the action dimensions."""
    observation_layout: str
    """One line saying how the observation splits (recorded in raw datasets)."""
    rollout: Callable[..., Any]
    """`rollout(env, seed, cameras=(), depth=False, extra_steps=0)`: one scripted-expert episode."""
    control_rates: tuple[int, ...] = (20,)
    """Supported control frequencies in Hz (the first is the default)."""
    experts: dict[str, Callable[..., Any]] = field(default_factory=dict)
    """Other ways to record an episode than `rollout`, by name (e.g. "kinesthetic"); same signature."""
    play_rollout: Callable[..., Any] | None = None
    """`play_rollout(env, seed, sequence, cameras=(), depth=False)`: one play episode, if supported."""
    play_sequences: dict[str, tuple[str, ...]] = field(default_factory=dict)
    """Default play sequence per main task."""
    action_conventions: dict[str, Callable[[np.ndarray], np.ndarray]] = field(default_factory=dict)
    """Converters from other codebases' action conventions (e.g. "vpace") into this family's."""
    expert_policy: Callable[[Any], Any] | None = None
    """`expert_policy(env)`: the scripted expert as a policy that acts from the env's current state
    (`reset()`, `act(obs)`), if the family has one: FIRE's simulated oracle takes over with it."""
    expert_policies: dict[str, Callable[..., Any]] = field(default_factory=dict)
    """The other experts of `experts` that act from any state, as policies by the same name:
    `expert_policies[name](env, seed)` (the seed draws a stochastic expert's variance); FIRE's oracle
    takes over with the one its run names (`shiftkit fire --expert-policy`)."""

    def gym_id(self, task: str) -> str:
        """The gymnasium id of `task` (`shiftkit/<gym_prefix>-<Task>-v0`)."""
        return f"shiftkit/{self.gym_prefix}-{self.tasks[task]}-v0"


def import_families(path: list[str] | None = None) -> None:
    """Import every family package on `path` (default: the `shiftkit.envs` package's path), which registers it."""
    package = __name__.rpartition(".")[0]
    import_modules(package, importlib.import_module(package).__path__ if path is None else path, packages_only=True)


FAMILIES: Registry[EnvFamily] = Registry("env", error=ValueError, discover=[import_families])


def register_family(family: EnvFamily) -> EnvFamily:
    """Add a family to `FAMILIES` and register its gymnasium ids (idempotent)."""
    FAMILIES.register(family)
    for task in family.tasks:
        env_id = family.gym_id(task)
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=family.entry_point, kwargs={"task": task})
    return family


def env_family(env_name: str) -> EnvFamily:
    """The registered family `env_name`; ValueError (one line) for unknown names."""
    return FAMILIES.get(env_name)


def families() -> dict[str, EnvFamily]:
    """Every registered family by CLI name."""
    return dict(FAMILIES.items())


def env_tasks() -> dict[str, tuple[str, ...]]:
    """CLI env name -> its task names."""
    return {name: tuple(f.tasks) for name, f in families().items()}


def gym_id(env_name: str, task: str) -> str:
    """The gymnasium id of a registered env/task pair."""
    family = FAMILIES.get(env_name)
    if task not in family.tasks:
        raise ValueError(f"unknown task {task!r} for env {env_name} (known: {', '.join(family.tasks)})")
    return family.gym_id(task)


def make(env_name: str, task: str, **kwargs: Any) -> gym.Env:
    """Build an environment by CLI name (unwrapped, with its own episode limit); ValueError (one
    line) for unknown names."""
    gym_id(env_name, task)  # checks both names
    module, _, cls = env_family(env_name).entry_point.partition(":")
    return getattr(importlib.import_module(module), cls)(task=task, **kwargs)
