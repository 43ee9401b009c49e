"""SAC-X schedulers: which intention acts during each fixed period of an exploration episode.

Both schedulers first pick, per episode, one of the handcrafted sequences uniformly at the handcraft rate
(thesis 6.6.2: sequences that clearly help the main task, e.g. reach, lift, main, release); otherwise

* `WeightedRandomScheduler` (the thesis default, "WRS + handcrafted") draws each period's task from a
  weighted random distribution: main task `main_rate`, the rest shared equally by the auxiliary tasks;
* `QTableScheduler` (SAC-Q's learned scheduler, thesis eq. 6.8-6.11) draws each period's task from a
  Boltzmann distribution over Q_S(tasks so far, task), where Q_S is an exponential moving average of the
  main task's Monte Carlo return from the start of that period. The return comes from the reward model,
  so the scheduler needs a learned one (DAC); SQIL's fixed labels would give every plan the same value.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import override

import numpy as np

from shiftkit.datasets.errors import ConfigError

MAIN = "main"  # how handcrafted sequences name the main task

# The thesis' reusable handcrafted sequences (`open` is the Panda play env's open-gripper/release task).
HANDCRAFTED_PRESETS: dict[str, tuple[str, ...]] = {
    # VPACE, Panda (thesis 7, ablation section): 8 periods, auxiliary tasks reach, grasp, lift, release.
    "panda": (
        "reach,lift,main,open,reach,lift,main,open",
        "lift,main,open,lift,main,open,lift,main",
        "main,open,main,open,main,open,main,open",
    ),
    # LfGP, Panda (thesis 6.6.2): also moves the object.
    "panda-lfgp": (
        "reach,lift,main,open,reach,lift,main,open",
        "reach,lift,move-object,main,open,reach,lift,move-object",
        "lift,main,open,lift,main,open,lift,main",
        "main,open,main,open,main,open,main,open",
        "move-object,main,open,move-object,main,open,move-object,main",
    ),
    # Sawyer and Adroit environments: 5 periods, auxiliary tasks reach and grasp.
    "reach-grasp": (
        "reach,grasp,main,main,main",
        "main,main,main,main,main",
    ),
}


def expand_handcrafted(entries: Sequence[str]) -> list[str]:
    """Handcrafted sequences with preset names (`panda`, `panda-lfgp`, `reach-grasp`) replaced by theirs."""
    return [seq for entry in entries for seq in HANDCRAFTED_PRESETS.get(entry.strip(), (entry,))]


class _Scheduler:
    """Handcrafted sequences at `handcraft_rate`, otherwise `_draw` (the subclass's own choice)."""

    learned = False

    def __init__(self, tasks: Sequence[str], num_periods: int, handcraft_rate: float, handcrafted: Sequence[str]):
        if not 0.0 <= handcraft_rate <= 1.0:
            raise ConfigError("the handcraft rate must lie in [0, 1]")
        self.num_tasks, self.num_periods = len(tasks), num_periods
        index = {name: i for i, name in enumerate(tasks)} | {MAIN: 0}
        self.sequences = []
        for seq in expand_handcrafted(handcrafted):
            names = [n.strip() for n in seq.split(",") if n.strip()]
            unknown = sorted({n for n in names if n not in index})
            if unknown:
                raise ConfigError(f"handcrafted sequence {seq!r} names unknown task(s) {unknown}; tasks: {list(tasks)}")
            if len(names) != num_periods:
                raise ConfigError(f"handcrafted sequence {seq!r} has {len(names)} entries, need {num_periods} periods")
            self.sequences.append([index[n] for n in names])
        self.handcraft_rate = handcraft_rate if self.sequences else 0.0

    def plan_episode(self, rng: np.random.Generator) -> list[int]:
        """Task index (0 = main) for each period of the next episode."""
        if self.sequences and rng.random() < self.handcraft_rate:
            return list(self.sequences[rng.integers(len(self.sequences))])
        return self._draw(rng)

    def _draw(self, rng: np.random.Generator) -> list[int]:
        raise NotImplementedError

    def update(self, plan: Sequence[int], main_rewards: np.ndarray, period: int) -> None:
        """Learn from an episode that followed `plan` (only learned schedulers use this)."""

    def state_dict(self) -> dict:
        """What the scheduler learned, for a checkpoint (nothing for a fixed one)."""
        return {}

    def load_state_dict(self, state: dict) -> None:
        """Restores what `state_dict` returned."""
        pass


class WeightedRandomScheduler(_Scheduler):
    """Weighted random task choice per period, mixed with handcrafted sequences per episode."""

    def __init__(
        self,
        tasks: Sequence[str],
        num_periods: int,
        main_rate: float = 0.5,
        handcraft_rate: float = 0.5,
        handcrafted: Sequence[str] = (),
    ):
        """`tasks[0]` is the main task. `handcrafted` holds comma-separated task names (`main` allowed)."""
        super().__init__(tasks, num_periods, handcraft_rate, handcrafted)
        if not 0.0 <= main_rate <= 1.0:
            raise ConfigError("the main-task rate must lie in [0, 1]")
        if len(tasks) == 1:
            self.probs = np.ones(1)
        else:
            self.probs = np.full(len(tasks), (1.0 - main_rate) / (len(tasks) - 1))
            self.probs[0] = main_rate

    def _draw(self, rng: np.random.Generator) -> list[int]:
        return [int(i) for i in rng.choice(len(self.probs), size=self.num_periods, p=self.probs)]


class QTableScheduler(_Scheduler):
    """Learned scheduler: Boltzmann over a table Q_S(history, task), fitted to main-task returns."""

    learned = True

    def __init__(
        self,
        tasks: Sequence[str],
        num_periods: int,
        gamma: float,
        temperature: float = 360.0,
        temperature_decay: float = 0.9995,
        temperature_min: float = 0.1,
        ema_rate: float = 0.6,
        handcraft_rate: float = 0.5,
        handcrafted: Sequence[str] = (),
    ):
        """Defaults as in the LfGP code: temperature 360 decayed by 0.9995 per decision down to 0.1, and
        the moving-average rate phi of eq. 6.11 is 0.6."""
        super().__init__(tasks, num_periods, handcraft_rate, handcrafted)
        if temperature <= 0 or temperature_min <= 0 or not 0 < temperature_decay <= 1 or not 0 < ema_rate <= 1:
            raise ConfigError("scheduler temperatures must be > 0, decay and moving-average rate in (0, 1]")
        self.gamma, self.ema_rate = gamma, ema_rate
        self.temperature, self.temperature_decay, self.temperature_min = temperature, temperature_decay, temperature_min
        self.table: dict[tuple[int, ...], np.ndarray] = {}  # history of tasks -> Q per next task

    def q_values(self, history: Sequence[int]) -> np.ndarray:
        """Q_S(history, ·) (zeros for a history never seen)."""
        return self.table.get(tuple(history), np.zeros(self.num_tasks))

    def _draw(self, rng: np.random.Generator) -> list[int]:
        history: list[int] = []
        for _ in range(self.num_periods):
            logits = self.q_values(history) / self.temperature
            probs = np.exp(logits - logits.max())
            history.append(int(rng.choice(self.num_tasks, p=probs / probs.sum())))
            self.temperature = max(self.temperature_min, self.temperature * self.temperature_decay)
        return history

    def update(self, plan: Sequence[int], main_rewards: np.ndarray, period: int) -> None:
        """Eq. 6.11 for every period the episode reached: Q_S(T_0:h-1, T_h) moves towards the discounted
        main-task return from that period's first step to the episode's end."""
        returns = np.zeros(len(main_rewards) + 1)
        for t in range(len(main_rewards) - 1, -1, -1):
            returns[t] = main_rewards[t] + self.gamma * returns[t + 1]
        for h, task in enumerate(plan):
            if h * period >= len(main_rewards):
                break
            q = self.table.setdefault(tuple(plan[:h]), np.zeros(self.num_tasks))
            q[task] += self.ema_rate * (returns[h * period] - q[task])

    @override
    def state_dict(self) -> dict:
        return {"table": {k: v.copy() for k, v in self.table.items()}, "temperature": self.temperature}

    @override
    def load_state_dict(self, state: dict) -> None:
        self.table = {tuple(k): np.array(v, dtype=np.float64) for k, v in state["table"].items()}
        self.temperature = float(state["temperature"])
