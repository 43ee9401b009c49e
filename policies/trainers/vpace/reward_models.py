"""Reward models for learning from examples: SQIL labels, a DAC discriminator, and RCE's classifier TD.

* SQIL (Reddy et al. 2020, with the thesis' -1 label): buffer data is labelled -1, example data +1.
* DAC (Kostrikov et al. 2019): one multitask discriminator, as in the reference code (utiasSTARS/lfgp
  `ActionConditionedFullyConnectedDiscriminator`, thesis A.6 and B.2.6): two tanh layers shared by all
  tasks and one logit per task, trained with binary cross-entropy (buffer rows = 0 for every task,
  each task's expert rows = 1 for its own logit) plus a gradient penalty (weight 10) on interpolates;
  reward log D - log(1 - D), i.e. the task's logit. State-only for VPACE, state-action for LfGP.
* RCE (Eysenbach et al. 2021): no separate reward; the critic is a classifier of future success,
  trained with weighted cross-entropy TD targets (thesis B.1.3).

Shapes: replay rows are shared by all tasks, (B, ..., in_dim) -> rewards (T, B, ...); example rows
belong to one task each, (T, n, in_dim) -> task t's reward of its own rows, (T, n).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from shiftkit.policies.networks import mlp


class SQILReward:
    """Fixed labels: the reward of a buffer state is `policy_label`, of an example state `example_label`."""

    learned = False

    def __init__(self, num_tasks: int, policy_label: float = -1.0, example_label: float = 1.0):
        self.num_tasks, self.policy_label, self.example_label = num_tasks, policy_label, example_label

    def buffer_reward(self, x: torch.Tensor) -> torch.Tensor:
        """The policy label of every task for shared rows `x`, (B, ..., in_dim) -> (T, B, ...)."""
        return torch.full((self.num_tasks, *x.shape[:-1]), self.policy_label, device=x.device)

    def example_reward(self, x: torch.Tensor) -> torch.Tensor:
        """The example label for each task's own rows `x`, (T, n, in_dim) -> (T, n)."""
        return torch.full(x.shape[:-1], self.example_label, device=x.device)


class DACReward(nn.Module):
    """The multitask discriminator D_T(x) = sigmoid(logit(x)[T]); x is a state, or state + action for LfGP."""

    learned = True

    def __init__(
        self, num_tasks: int, in_dim: int, hidden: tuple[int, ...] = (256, 256), gradient_penalty: float = 10.0
    ):
        super().__init__()
        self.net = mlp(in_dim, num_tasks, hidden, act=nn.Tanh)
        self.gradient_penalty = gradient_penalty

    def logits(self, x: torch.Tensor) -> torch.Tensor:
        """Every task's logit of rows `x`, (..., in_dim) -> (T, ...)."""
        return self.net(x).movedim(-1, 0)

    def own_logits(self, x: torch.Tensor) -> torch.Tensor:
        """Task t's logit of its own rows x[t], (T, n, in_dim) -> (T, n)."""
        return self.logits(x).diagonal(dim1=0, dim2=1).T

    @torch.no_grad()
    def buffer_reward(self, x: torch.Tensor) -> torch.Tensor:
        """log D - log(1 - D) (a sigmoid's logit) of every task for shared rows, (B, ..., in_dim) -> (T, B, ...)."""
        return self.logits(x)

    @torch.no_grad()
    def example_reward(self, x: torch.Tensor) -> torch.Tensor:
        """Each task's reward of its own rows, (T, n, in_dim) -> (T, n)."""
        return self.own_logits(x)

    def loss(self, buffer_x: torch.Tensor, example_x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(loss, per-task cross-entropy (T,)) for shared buffer rows (B, in_dim) and each task's expert
        rows (T, n, in_dim), as the reference's `update_discriminator`: the two cross-entropies' mean
        over every task's logits, halved, plus the gradient penalty on interpolates of the buffer rows
        with each task's expert rows (a uniform weight per element), on the gradient of the sum of all
        tasks' logits."""
        zeros = torch.zeros_like
        buffer_logit, example_logit = self.logits(buffer_x), self.own_logits(example_x)
        bce = (
            F.binary_cross_entropy_with_logits(buffer_logit, zeros(buffer_logit), reduction="none").mean(-1)
            + F.binary_cross_entropy_with_logits(example_logit, zeros(example_logit) + 1.0, reduction="none").mean(-1)
        ) / 2
        n = min(buffer_x.shape[0], example_x.shape[1])
        mix = torch.rand(example_x.shape[0], n, buffer_x.shape[-1], device=buffer_x.device)
        interp = (mix * buffer_x[:n] + (1 - mix) * example_x[:, :n]).requires_grad_(True)
        (grad,) = torch.autograd.grad(self.logits(interp).sum(), interp, create_graph=True)
        penalty = (grad.norm(dim=-1) - 1.0).square().mean()
        return bce.mean() + self.gradient_penalty * penalty, bce.detach()


def rce_targets(next_prob: torch.Tensor, gamma: float, eps: float = 1e-4) -> tuple[torch.Tensor, torch.Tensor]:
    """RCE's TD target and weight for buffer rows from the target classifier's C(s', a') in (0, 1).

    With w = C / (1 - C): target gamma w / (1 + gamma w), weight 1 + gamma w. Example rows use target 1
    and weight 1 - gamma (see `rce_loss`).
    """
    c = next_prob.clamp(eps, 1.0 - eps)
    w = c / (1.0 - c)
    return gamma * w / (1.0 + gamma * w), 1.0 + gamma * w


def rce_loss(
    buffer_logit: torch.Tensor,
    example_logit: torch.Tensor,
    target: torch.Tensor,
    weight: torch.Tensor,
    example_weight: torch.Tensor,
    gamma: float,
) -> torch.Tensor:
    """Weighted binary cross-entropy of the critic's logits (2, T, ·), summed over buffer rows and each
    task's own example rows (`example_weight` (T, n): 1 for a task's rows, 0 for padding), (2, T)."""
    target, weight = target.expand_as(buffer_logit), weight.expand_as(buffer_logit)
    buffer_term = weight * F.binary_cross_entropy_with_logits(buffer_logit, target, reduction="none")
    example_term = (1.0 - gamma) * F.binary_cross_entropy_with_logits(
        example_logit, torch.ones_like(example_logit), reduction="none"
    )
    return buffer_term.sum(-1) + (example_weight * example_term).sum(-1)
