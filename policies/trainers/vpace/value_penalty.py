"""Value penalization (VP, thesis section 7.3.3): keep Q-estimates inside the range of valid returns.

    L_pen = lambda * E_B[ max(Q - Q_max, 0)^2 + max(Q_min - Q, 0)^2 ]

`Q_max` is the mean (or, as an option, the max) of Q(s*, a* ~ pi(s*)) over the example batch, smoothed with a median filter over the
last 50 updates; `Q_min = reward_scale * min_reward / (1 - gamma)`, where a learned reward model's minimum
reward is median-filtered the same way (thesis B.2.6).
"""

from __future__ import annotations

import torch


def value_penalty(q: torch.Tensor, q_max: torch.Tensor, q_min: torch.Tensor, weight: float) -> torch.Tensor:
    """Mean over the last (batch) dim of the squared excursions of `q` outside [q_min, q_max].

    `q` is (..., batch); `q_max`/`q_min` broadcast against `q[..., :1]` (one bound per task). Returns (...).
    """
    over = torch.clamp(q - q_max, min=0.0)
    under = torch.clamp(q_min - q, min=0.0)
    return weight * (over.square() + under.square()).mean(dim=-1)


class MedianFilter:
    """Per-task median of the last `size` values pushed (of all values while fewer have been pushed)."""

    def __init__(self, num_tasks: int, size: int = 50):
        self.size = size
        self.history = torch.zeros(size, num_tasks)
        self.count = 0

    def update(self, values: torch.Tensor) -> torch.Tensor:
        """Push one value per task (shape (num_tasks,)) and return the filtered value per task."""
        self.history[self.count % self.size] = values.detach().to(self.history)
        self.count += 1
        window = self.history[: min(self.count, self.size)]
        return window.median(dim=0).values.to(values.device)

    def state_dict(self) -> dict:
        """The history window and count, for a checkpoint."""
        return {"history": self.history.clone(), "count": self.count}

    def load_state_dict(self, state: dict) -> None:
        """Restores what `state_dict` returned."""
        self.history = state["history"].clone()
        self.count = int(state["count"])


class ValueBounds:
    """Tracks the VP bounds per task: filtered Q_max from example Q-values, Q_min from the minimum reward."""

    def __init__(self, num_tasks: int, reward_scale: float, gamma: float, filter_size: int = 50):
        self.reward_scale = reward_scale
        self.gamma = gamma
        self.q_max_filter = MedianFilter(num_tasks, filter_size)
        self.min_reward_filter = MedianFilter(num_tasks, filter_size)

    def update(
        self, example_q: torch.Tensor, min_reward: torch.Tensor, learned_reward: bool
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Returns (q_max, q_min), each (num_tasks,).

        `example_q` is the batch mean (or max) of Q(s*, a*) per task; `min_reward` the (unscaled) minimum
        reward per task, median-filtered only when the reward is learned (DAC) since fixed labels (SQIL)
        are exact.
        """
        q_max = self.q_max_filter.update(example_q)
        if learned_reward:
            min_reward = self.min_reward_filter.update(min_reward)
        q_min = self.reward_scale * min_reward / (1.0 - self.gamma)
        return q_max, q_min

    def state_dict(self) -> dict:
        """Both filters' states, for a checkpoint."""
        return {"q_max": self.q_max_filter.state_dict(), "min_reward": self.min_reward_filter.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        """Restores what `state_dict` returned."""
        self.q_max_filter.load_state_dict(state["q_max"])
        self.min_reward_filter.load_state_dict(state["min_reward"])
