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
from typing import override

import torch
import torch.nn.functional as F
from torch import nn

LOG_STD_EPS = 1e-7  # softplus(x) + eps keeps the policy std away from 0 (thesis A.6)
NARROW_OUT = 32  # layers with fewer outputs than this compute their transposed product (BatchedLinear)


class NarrowProduct(torch.autograd.Function):
    """`x @ weight + bias` for a layer with few outputs (Q's 1, the policy's 2 x action dims), each
    product in the layout this CPU's GEMM runs fast. MKL's batched GEMM with few output columns, and
    backward the outer product with few inner dims, ran 3-20x slower than the transposed products (few
    output rows) and, for one output, a broadcast multiply. Backward is written in differentiable ops,
    so a gradient penalty can differentiate through it again (DAC)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        """x @ weight + bias per member, (M, B, in) -> (M, B, out), saving what `backward` needs."""
        ctx.save_for_backward(x, weight)
        # A fresh (batch, out) tensor, not a view: a following in-place activation must not rewrite
        # this function's output behind autograd (and it is small).
        return torch.baddbmm(bias.mT, weight.mT, x.mT).mT.clone(memory_format=torch.contiguous_format)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        """Gradients for x, weight and bias (None where not needed)."""
        x, weight = ctx.saved_tensors
        grad_x = grad_weight = grad_bias = None
        if ctx.needs_input_grad[0]:
            grad_x = grad * weight.mT if weight.shape[-1] == 1 else torch.bmm(grad, weight.mT)
        if ctx.needs_input_grad[1]:
            grad_weight = torch.bmm(grad.mT, x).mT
        if ctx.needs_input_grad[2]:
            grad_bias = grad.sum(1, keepdim=True)
        return grad_x, grad_weight, grad_bias


class BatchedLinear(nn.Module):
    """`members` independent linear layers applied to a (members, batch, in_dim) input."""

    def __init__(self, members: int, in_dim: int, out_dim: int):
        super().__init__()
        # Same distribution as torch.nn.Linear's default init, drawn independently per member.
        bound = 1.0 / math.sqrt(in_dim)
        self.weight = nn.Parameter(torch.empty(members, in_dim, out_dim).uniform_(-bound, bound))
        self.bias = nn.Parameter(torch.empty(members, 1, out_dim).uniform_(-bound, bound))

    @override
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.weight.shape[-1] < NARROW_OUT:
            return NarrowProduct.apply(x, self.weight, self.bias)
        return torch.baddbmm(self.bias, x, self.weight)

    def forward_parts(self, *parts: torch.Tensor) -> torch.Tensor:
        """`forward(torch.cat(parts, -1))` without the concatenation: each part meets its own rows of
        the weight, so backward computes input gradients only for the parts that need them (the
        policy step differentiates Q by the action, not by the 59 observation dims)."""
        out, start = None, 0
        for x in parts:
            rows = self.weight[:, start : start + x.shape[-1]]
            out = torch.baddbmm(self.bias, x, rows) if out is None else out.baddbmm_(x, rows)
            start += x.shape[-1]
        return out


def batched_mlp(
    members: int, in_dim: int, out_dim: int, hidden: Sequence[int] = (256, 256), act: type[nn.Module] = nn.ReLU
) -> nn.Sequential:
    """`members` independent MLPs (hidden layers followed by `act`), evaluated together."""
    layers: list[nn.Module] = []
    for width in hidden:
        # In place where the activation allows it: the matmul before it does not keep its output.
        layers += [BatchedLinear(members, in_dim, width), act(inplace=True) if act is nn.ReLU else act()]
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
        """The entropy temperature per task (num_tasks,), exp(log_alpha)."""
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
        net = self.target_critic if target else self.critic
        x = net[0].forward_parts(torch.cat([obs, obs]), torch.cat([act, act]))  # both twins
        for layer in net[1:]:
            x = layer(x)
        return x.view(2, self.num_tasks, -1)


def clip_grad_norm_per_member(params: Iterable[nn.Parameter], max_norm: float) -> torch.Tensor:
    """Clip gradients to `max_norm` separately for each member (leading dim) of stacked parameters.

    Returns the pre-clip norm per member. All parameters must share the same leading dim.
    """
    grads = [p.grad for p in params if p.grad is not None]
    norm = torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g.flatten(1), dim=1) for g in grads]), dim=0)
    scale = (max_norm / (norm + 1e-6)).clamp(max=1.0)
    for g in grads:
        g.mul_(scale.view(-1, *([1] * (g.dim() - 1))))
    return norm


@torch.no_grad()
def polyak_update(target: nn.Module, source: nn.Module, tau: float) -> None:
    """target <- (1 - tau) target + tau source."""
    torch._foreach_lerp_(list(target.parameters()), list(source.parameters()), tau)
