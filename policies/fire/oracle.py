"""The simulated expert of FIRE (thesis Algorithm 2's human H; docs/fire.md): it answers "will the agent
fail?" by forking the simulator and rolling the current policy ahead, stops failures nobody predicted
once they become observable, takes over with one of the environment's experts, and hands control back
as soon as the policy can finish from where the correction has brought it (Fig. 5.1: the person moves
the robot "into a new state where they believe the existing policy can complete the task";
Algorithm 2, lines 27-28). A real deployment puts a person behind the same calls (`will_fail`,
`stops_unpredicted`, `take_over`, `can_finish`).

Forking copies the whole environment object (MuJoCo `MjData` with qpos, qvel, act, ctrl, warm-start
accelerations and every derived quantity, the controller's targets, timers, the env's RNG), sharing
only what never changes while stepping (the compiled `MjModel`) and the renderers, which draw whatever
data they are handed; the original episode's state is left bit-identical, and the fork steps exactly
as a fully independent deep copy of the env would.

The policy is deterministic between updates, so a look-ahead from step t foretells the rest of the
episode: the oracle keeps its verdict and the look-ahead's states and answers later questions from it
as long as the episode still follows those states exactly (checked on qpos/qvel), forking again
otherwise. A failure nobody predicted is stopped (a false negative) where a person watching would see
it: once the robot and objects have stood still for `stall_steps` policy steps without success, or at
the latest at `check_step` (the episode's last step minus the time a demonstration takes), in both
cases only when the look-ahead confirms that the policy would not finish.
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


def scripted_expert(env_name: str, env: Any, expert: str = "scripted", seed: int = 0) -> Any:
    """The env family's expert `expert` as a policy acting from the env's current state (`reset()` and
    `act(obs)`): "scripted" is the family's `expert_policy`, any other name one of its
    `expert_policies` (a stochastic one draws its variance from `seed`)."""
    from shiftkit.envs import env_family

    family = env_family(env_name)
    if expert != "scripted":
        if expert not in family.expert_policies:
            known = ", ".join(["scripted", *family.expert_policies])
            raise ConfigError(f"env {env_name!r} has no expert {expert!r} that acts from any state (known: {known})")
        return family.expert_policies[expert](env, seed)
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
    """Answers failure predictions by look-ahead, stops unpredicted failures once observable, takes over
    and hands back (see the module docstring)."""

    def __init__(
        self,
        env_name: str,
        agent_step: AgentStep,
        check_step: int,
        expert: str = "scripted",
        stall_steps: int = 5,
        stall_tolerance: float = 1e-3,
    ) -> None:
        self.env_name, self.agent_step, self.expert = env_name, agent_step, expert
        self.check_step, self.stall_steps, self.stall_tolerance = check_step, stall_steps, stall_tolerance
        self.look_ahead: LookAhead | None = None
        self.recent: list[np.ndarray] = []
        self.forks = 0
        self.look_ahead_steps = 0

    def start_episode(self) -> None:
        """Forgets the previous episode's look-ahead and motion."""
        self.look_ahead = None
        self.recent = []

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
            # a policy that has come to a standstill stays failed (it is deterministic): no need to
            # watch it stand until the episode's end
            if terminated or truncated or self._still([q for q, _ in ahead.states[-self.stall_steps :]]):
                break
        self.look_ahead = ahead
        return ahead

    def _still(self, positions: list[np.ndarray]) -> bool:
        """Whether `positions` (qpos, oldest first) span `stall_steps` steps within `stall_tolerance`."""
        return len(positions) >= self.stall_steps and all(
            np.max(np.abs(q - positions[-1])) < self.stall_tolerance for q in positions[-self.stall_steps :]
        )

    def will_fail(self, env: Any, obs: np.ndarray, t: int) -> bool:
        """The answer to a predicted failure at step t: True agrees (true positive), False disagrees."""
        return self._future(env, obs, t).failed

    def stops_unpredicted(self, env: Any, obs: np.ndarray, t: int) -> str | None:
        """Whether the oracle stops the policy at step t on its own (an unpredicted failure), and why:
        "stalled" (nothing has moved for `stall_steps` policy steps) or "deadline" (`check_step` is
        reached), each only when the look-ahead shows the policy failing; None to let it run."""
        self.recent = [*self.recent[-(self.stall_steps - 1) :], sim_state(env)[0]]
        reason = "stalled" if self._still(self.recent) else "deadline" if t >= self.check_step else None
        if reason is None or not self._future(env, obs, t).failed:
            return None
        return reason

    def take_over(self, env: Any, seed: int = 0) -> Any:
        """The expert, starting from the env's current state (`seed`: a stochastic expert's draws)."""
        expert = scripted_expert(self.env_name, env, self.expert, seed)
        expert.reset()
        return expert

    def can_finish(self, env: Any, obs: np.ndarray, t: int) -> bool:
        """Whether the policy, given control back at step t, finishes the task (the expert then hands
        back; the look-ahead is kept, so the policy's further questions are answered from it)."""
        if self._future(env, obs, t).failed:
            return False
        self.recent = []  # the policy's own motion counts from here
        return True
