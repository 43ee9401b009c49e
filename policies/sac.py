"""Batched multi-intention SAC: one independent actor, twin critic and temperature per task.

Every network is a stack of per-task parameters (`BatchedLinear`: weight (members, in, out)), so one
batched matmul evaluates all tasks at once and one optimizer step updates all of them. Nothing is
shared between tasks or between actor and critic: task t's outputs depend only on slice t of each
parameter, Adam and weight decay act element-wise, and gradient clipping is done per member, so the
batched update equals running one SAC per task.

Shapes: observations and actions are (num_tasks, batch, dim); Q-values are (2, num_tasks, batch) for
the twin critics; log-probabilities and rewards (num_tasks, batch).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Iterable, Sequence

import torch
import torch.nn.functional as F
from torch import nn

LOG_STD_EPS = 1e-7  # softplus(x) + eps keeps the policy std away from 0 (thesis A.6)


class BatchedLinear(nn.Module):
    """`members` independent linear layers applied to a (members, batch, in_dim) input."""

    def __init__(self, members: int, in_dim: int, out_dim: int):
        super().__init__()
        # Same distribution as torch.nn.Linear's default init, drawn independently per member.
        bound = 1.0 / math.sqrt(in_dim)
        self.weight = nn.Parameter(torch.empty(members, in_dim, out_dim).uniform_(-bound, bound))
        self.bias = nn.Parameter(torch.empty(members, 1, out_dim).uniform_(-bound, bound))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.baddbmm(self.bias, x, self.weight)


def batched_mlp(
    members: int, in_dim: int, out_dim: int, hidden: Sequence[int] = (256, 256), act: type[nn.Module] = nn.ReLU
) -> nn.Sequential:
    """`members` independent MLPs (hidden layers followed by `act`), evaluated together."""
    layers: list[nn.Module] = []
    for width in hidden:
        layers += [BatchedLinear(members, in_dim, width), act()]
        in_dim = width
    layers.append(BatchedLinear(members, in_dim, out_dim))
    return nn.Sequential(*layers)


class Intentions(nn.Module):
    """SAC-X intentions: per task a tanh-squashed Gaussian policy, twin Q with target, learned alpha."""

    def __init__(
        self,
        num_tasks: int,
        obs_dim: int,
        act_dim: int,
        hidden: Sequence[int] = (256, 256),
        initial_alpha: float = 1e-2,
    ):
        super().__init__()
        self.num_tasks, self.obs_dim, self.act_dim = num_tasks, obs_dim, act_dim
        self.actor = batched_mlp(num_tasks, obs_dim, 2 * act_dim, hidden)
        # Both twins of every task in one stack: members [0, T) are Q1, [T, 2T) are Q2.
        self.critic = batched_mlp(2 * num_tasks, obs_dim + act_dim, 1, hidden)
        self.target_critic = copy.deepcopy(self.critic).requires_grad_(False)
        self.log_alpha = nn.Parameter(torch.full((num_tasks,), math.log(initial_alpha)))

    @property
    def alpha(self) -> torch.Tensor:
        return self.log_alpha.exp()

    def _gaussian(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, pre_std = self.actor(obs).chunk(2, dim=-1)
        return mean, F.softplus(pre_std) + LOG_STD_EPS

    def sample(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Reparameterized squashed sample and its log-probability: (T, B, A), (T, B)."""
        mean, std = self._gaussian(obs)
        noise = torch.randn_like(mean)
        pre_tanh = mean + std * noise
        # Normal(mean, std).log_prob(pre_tanh) in closed form: (pre_tanh - mean) / std is the noise.
        log_prob = -(0.5 * noise.square() + std.log()).sum(-1) - 0.5 * math.log(2.0 * math.pi) * noise.shape[-1]
        # log|d tanh(u)/du| = 2 (log 2 - u - softplus(-2u)), the numerically stable form.
        log_prob = log_prob - (2.0 * (math.log(2.0) - pre_tanh - F.softplus(-2.0 * pre_tanh))).sum(-1)
        return torch.tanh(pre_tanh), log_prob

    def mean_action(self, obs: torch.Tensor) -> torch.Tensor:
        """Deterministic action (tanh of the mean), used for evaluation."""
        return torch.tanh(self._gaussian(obs)[0])

    def q(self, obs: torch.Tensor, act: torch.Tensor, target: bool = False) -> torch.Tensor:
        """Twin Q-values (2, T, B) of per-task (T, B, ·) observations and actions."""
        x = torch.cat([obs, act], dim=-1)
        net = self.target_critic if target else self.critic
        return net(torch.cat([x, x], dim=0)).view(2, self.num_tasks, -1)


def clip_grad_norm_per_member(params: Iterable[nn.Parameter], max_norm: float) -> torch.Tensor:
    """Clip gradients to `max_norm` separately for each member (leading dim) of stacked parameters.

    Returns the pre-clip norm per member. All parameters must share the same leading dim.
    """
    grads = [p.grad for p in params if p.grad is not None]
    sq = torch.stack([g.flatten(1).square().sum(1) for g in grads]).sum(0)
    norm = sq.sqrt()
    scale = (max_norm / (norm + 1e-6)).clamp(max=1.0)
    for g in grads:
        g.mul_(scale.view(-1, *([1] * (g.dim() - 1))))
    return norm


@torch.no_grad()
def polyak_update(target: nn.Module, source: nn.Module, tau: float) -> None:
    """target <- (1 - tau) target + tau source."""
    torch._foreach_lerp_(list(target.parameters()), list(source.parameters()), tau)
