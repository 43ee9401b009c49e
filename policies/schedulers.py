"""SAC-X schedulers: which intention acts during each fixed period of an exploration episode.

The default (thesis B.2.6, LfGP's "WRS + handcrafted") picks, per episode, one of the handcrafted
sequences uniformly at the handcraft rate; otherwise each period draws a task from a weighted random
distribution (main task `main_rate`, the rest shared equally by the auxiliary tasks). The learned
Q-table scheduler of SAC-X is not implemented (the thesis found WRS + handcrafted better).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from shiftkit.pipelines.errors import ConfigError

MAIN = "main"  # how handcrafted sequences name the main task

class WeightedRandomScheduler:
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
        if not 0.0 <= main_rate <= 1.0 or not 0.0 <= handcraft_rate <= 1.0:
            raise ConfigError("scheduler rates must lie in [0, 1]")
        self.num_periods = num_periods
        index = {name: i for i, name in enumerate(tasks)} | {MAIN: 0}
        self.sequences = []
        for seq in handcrafted:
            names = [n.strip() for n in seq.split(",") if n.strip()]
            unknown = [n for n in names if n not in index]
            if unknown:
                raise ConfigError(f"handcrafted sequence {seq!r} names unknown task(s) {unknown}; tasks: {list(tasks)}")
            if len(names) != num_periods:
                raise ConfigError(f"handcrafted sequence {seq!r} has {len(names)} entries, need {num_periods} periods")
            self.sequences.append([index[n] for n in names])
        self.handcraft_rate = handcraft_rate if self.sequences else 0.0
        if len(tasks) == 1:
            self.probs = np.ones(1)
        else:
            self.probs = np.full(len(tasks), (1.0 - main_rate) / (len(tasks) - 1))
            self.probs[0] = main_rate

    def plan_episode(self, rng: np.random.Generator) -> list[int]:
        """Task index for each period of the next episode."""
        if self.sequences and rng.random() < self.handcraft_rate:
            return list(self.sequences[rng.integers(len(self.sequences))])
        return [int(i) for i in rng.choice(len(self.probs), size=self.num_periods, p=self.probs)]
