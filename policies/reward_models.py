"""Reward models for learning from examples: SQIL labels, a DAC discriminator, and RCE's classifier TD.

* SQIL (Reddy et al. 2020, with the thesis' -1 label): buffer data is labelled -1, example data +1.
* DAC (Kostrikov et al. 2019): one discriminator per task (independent batched MLPs with tanh), trained
  with binary cross-entropy (examples = 1, buffer = 0) plus a gradient penalty (weight 10) on
  interpolates; reward log D - log(1 - D), i.e. the discriminator's logit. State-only for VPACE,
  state-action for LfGP.
* RCE (Eysenbach et al. 2021): no separate reward; the critic is a classifier of future success,
  trained with weighted cross-entropy TD targets (thesis B.1.3).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from shiftkit.policies.sac import batched_mlp


class SQILReward:
    """Fixed labels: the reward of a buffer state is `policy_label`, of an example state `example_label`."""

    learned = False

    def __init__(self, policy_label: float = -1.0, example_label: float = 1.0):
        self.policy_label, self.example_label = policy_label, example_label

    def buffer_reward(self, x: torch.Tensor) -> torch.Tensor:
        """The constant policy label for every input in `x`, (..., in_dim) -> (...)."""
        return torch.full(x.shape[:-1], self.policy_label, device=x.device)

    def example_reward(self, x: torch.Tensor) -> torch.Tensor:
        """The constant example label for every input in `x`, (..., in_dim) -> (...)."""
        return torch.full(x.shape[:-1], self.example_label, device=x.device)


class DACReward(nn.Module):
    """Per-task discriminators D_T(x) = sigmoid(logit_T(x)); x is a state, or state + action for LfGP."""

    learned = True

    def __init__(
        self, num_tasks: int, in_dim: int, hidden: tuple[int, ...] = (256, 256), gradient_penalty: float = 10.0
    ):
        super().__init__()
        self.net = batched_mlp(num_tasks, in_dim, 1, hidden, act=nn.Tanh)
        self.gradient_penalty = gradient_penalty

    def logit(self, x: torch.Tensor) -> torch.Tensor:
        """(T, ..., in_dim) -> (T, ...)."""
        return self.net(x.reshape(x.shape[0], -1, x.shape[-1])).reshape(x.shape[:-1])

    @torch.no_grad()
    def buffer_reward(self, x: torch.Tensor) -> torch.Tensor:
        """The discriminators' logits log D - log(1 - D), (T, ..., in_dim) -> (T, ...)."""
        return self.logit(x)  # log D - log(1 - D) of a sigmoid is its logit

    example_reward = buffer_reward

    def loss(self, buffer_x: torch.Tensor, example_x: torch.Tensor) -> torch.Tensor:
        """Cross-entropy + gradient penalty per task (T,); each task's term touches only its own net."""
        buffer_logit, example_logit = self.logit(buffer_x), self.logit(example_x)
        bce = F.binary_cross_entropy_with_logits(buffer_logit, torch.zeros_like(buffer_logit), reduction="none").mean(
            -1
        ) + F.binary_cross_entropy_with_logits(example_logit, torch.ones_like(example_logit), reduction="none").mean(-1)
        n = min(buffer_x.shape[1], example_x.shape[1])
        mix = torch.rand(buffer_x.shape[0], n, 1, device=buffer_x.device)
        interp = (mix * example_x[:, :n] + (1 - mix) * buffer_x[:, :n]).requires_grad_(True)
        (grad,) = torch.autograd.grad(self.logit(interp).sum(), interp, create_graph=True)
        penalty = (grad.norm(dim=-1) - 1.0).square().mean(-1)
        return bce + self.gradient_penalty * penalty


def rce_targets(next_prob: torch.Tensor, gamma: float, eps: float = 1e-4) -> tuple[torch.Tensor, torch.Tensor]:
    """RCE's TD target and weight for buffer rows from the target classifier's C(s', a') in (0, 1).

    With w = C / (1 - C): target gamma w / (1 + gamma w), weight 1 + gamma w. Example rows use target 1
    and weight 1 - gamma (see `rce_loss`).
    """
    c = next_prob.clamp(eps, 1.0 - eps)
    w = c / (1.0 - c)
    return gamma * w / (1.0 + gamma * w), 1.0 + gamma * w


def rce_loss(
    buffer_logit: torch.Tensor, example_logit: torch.Tensor, target: torch.Tensor, weight: torch.Tensor, gamma: float
) -> torch.Tensor:
    """Weighted binary cross-entropy of the critic's logits (2, T, ·), mean over buffer + example rows."""
    target, weight = target.expand_as(buffer_logit), weight.expand_as(buffer_logit)
    buffer_term = weight * F.binary_cross_entropy_with_logits(buffer_logit, target, reduction="none")
    example_term = (1.0 - gamma) * F.binary_cross_entropy_with_logits(
        example_logit, torch.ones_like(example_logit), reduction="none"
    )
    return torch.cat([buffer_term, example_term], dim=-1).mean(-1)
