"""The simulated expert of FIRE (thesis Algorithm 2's human H; docs/fire.md): it answers "will the agent
fail?" by forking the simulator and rolling the current policy ahead, stops failures nobody predicted,
and takes over with the environment's scripted expert. A real deployment puts a person behind the same
three calls (`will_fail`, `stops_unpredicted`, `take_over`).

Forking copies the whole environment object (MuJoCo `MjData` with qpos, qvel, act, ctrl, warm-start
accelerations and every derived quantity, the controller's targets, timers, the env's RNG), sharing
only what never changes while stepping (the compiled `MjModel`) and the renderers, which draw whatever
data they are handed; the original episode's state is left bit-identical, and the fork steps exactly
as a fully independent deep copy of the env would.

The policy is deterministic between updates, so a look-ahead from step t foretells the rest of the
episode: the oracle keeps its verdict and the look-ahead's states and answers later questions from it
as long as the episode still follows those states exactly (checked on qpos/qvel), forking again
otherwise. When nothing was predicted by `check_step` (the latest step from which the expert can still
finish the task), the oracle looks ahead itself and stops a failing run there: a false negative.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

from shiftkit.datasets.errors import ConfigError

# one policy step in a (forked) env: obs -> (action, per-step record such as D and doubt)
AgentStep = Callable[[Any, np.ndarray], tuple[np.ndarray, dict[str, Any]]]


def _shared(env: Any, depth: int = 4) -> dict[int, Any]:
    """deepcopy memo that keeps the env's MjModel objects and renderers shared with the original and
    copies its MjData with `copy.copy` (mj_copyData on the same model): a deep copy of an MjData also
    copies its model, ~50 ms of the Panda scene's ~25 MB buffer per fork, for the same state."""
    memo: dict[int, Any] = {}

    def visit(obj: Any, level: int) -> None:
        if isinstance(obj, (mujoco.MjModel, mujoco.Renderer)):
            memo[id(obj)] = obj
            return
        if isinstance(obj, mujoco.MjData):
            memo.setdefault(id(obj), copy.copy(obj))
            return
        attrs = getattr(obj, "__dict__", None)
        if attrs is None or level == 0 or id(obj) in memo:
            return
        if any(isinstance(v, mujoco.Renderer) for v in attrs.values()):  # a renderer wrapper
            memo[id(obj)] = obj
            return
        for value in attrs.values():
            visit(value, level - 1)

    visit(env, depth)
    return memo


def fork_env(env: Any) -> Any:
    """An independent copy of `env` at its current state (see the module docstring)."""
    return copy.deepcopy(env, _shared(env))


def sim_state(env: Any) -> tuple[np.ndarray, np.ndarray]:
    """(qpos, qvel) of the env's MuJoCo data, copied (the state a look-ahead is matched against)."""
    data = env.unwrapped.physics.data if hasattr(env.unwrapped, "physics") else env.unwrapped.data
    return data.qpos.copy(), data.qvel.copy()


def scripted_expert(env_name: str, env: Any) -> Any:
    """The env family's scripted expert as a policy acting from the env's current state (the
    family's registered `expert_policy`, with `reset()` and `act(obs)`)."""
    from shiftkit.envs import env_family

    family = env_family(env_name)
    if family.expert_policy is None:
        raise ConfigError(f"env {env_name!r} has no scripted expert that acts from any state")
    return family.expert_policy(env)


@dataclass
class LookAhead:
    """The policy's uninterrupted future from one step: outcome, records and states per step."""

    start: int
    failed: bool
    records: list[dict[str, Any]] = field(default_factory=list)
    states: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)

    def follows(self, t: int, state: tuple[np.ndarray, np.ndarray]) -> bool:
        """Whether the episode at step t is exactly where this look-ahead had it."""
        i = t - self.start
        if not 0 <= i < len(self.states):
            return False
        qpos, qvel = self.states[i]
        return np.array_equal(qpos, state[0]) and np.array_equal(qvel, state[1])


class SimulatedOracle:
    """Answers failure predictions by look-ahead, stops unpredicted failures, takes over (see module)."""

    def __init__(self, env_name: str, agent_step: AgentStep, check_step: int) -> None:
        self.env_name = env_name
        self.agent_step = agent_step
        self.check_step = check_step
        self.look_ahead: LookAhead | None = None
        self.forks = 0
        self.look_ahead_steps = 0

    def start_episode(self) -> None:
        """Forgets the previous episode's look-ahead."""
        self.look_ahead = None

    def _future(self, env: Any, obs: np.ndarray, t: int) -> LookAhead:
        state = sim_state(env)
        if self.look_ahead is not None and self.look_ahead.follows(t, state):
            return self.look_ahead
        sim = fork_env(env)
        self.forks += 1
        ahead = LookAhead(start=t, failed=True)
        while True:
            ahead.states.append(sim_state(sim))
            action, record = self.agent_step(sim, obs)
            obs, _, terminated, truncated, info = sim.step(action)
            self.look_ahead_steps += 1
            ahead.records.append(record)
            if info.get("is_success", False):
                ahead.failed = False
                break
            if terminated or truncated:
                break
        self.look_ahead = ahead
        return ahead

    def will_fail(self, env: Any, obs: np.ndarray, t: int) -> bool:
        """The answer to a predicted failure at step t: True agrees (true positive), False disagrees."""
        return self._future(env, obs, t).failed

    def stops_unpredicted(self, env: Any, obs: np.ndarray, t: int) -> bool:
        """Whether the oracle stops the run at step t on its own (an unpredicted failure): at
        `check_step`, unless a look-ahead already showed the run succeeding."""
        if t != self.check_step:
            return False
        return self._future(env, obs, t).failed

    def take_over(self, env: Any) -> Any:
        """The scripted expert, starting from the env's current state."""
        expert = scripted_expert(self.env_name, env)
        expert.reset()
        return expert
