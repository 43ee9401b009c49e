"""Batched multi-intention SAC: an actor, twin critic and temperature per task.

Every per-task network is a stack of per-task parameters (`BatchedLinear`: weight (members, in, out)),
so one batched matmul evaluates all tasks at once and one optimizer step updates all of them. Task t's
outputs depend only on slice t of each parameter (and, with LfGP's shared trunk, on the trunk), Adam
and weight decay act element-wise; as in the reference code, gradients are clipped to one norm over
all tasks' parameters of a role (policies, Q-functions, temperatures), so a large gradient of one task
scales the step of every task.

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
            out = torch.baddbmm(self.bias if out is None else out, x, rows)
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
    """SAC-X intentions: per task a tanh-squashed Gaussian policy, twin Q with target, learned alpha.

    Two architectures, as the reference code builds them:
    * separate (VPACE, thesis B.2.6: sharing "substantially hurt performance"): every task's policy and
      each of its twin Q-functions is its own MLP of `hidden` layers;
    * `shared_trunk` (LfGP, thesis A.6; utiasSTARS/lfgp's multitask SAC): one trunk of `hidden` ReLU
      layers on the observation feeds every task's heads, a policy head (hidden[-1] -> hidden[-1] ->
      2 x action) and two Q heads ((hidden[-1] + action) -> hidden[-1] -> 1) per task. The trunk is a
      Q parameter (the reference's `qs_parameters`): the critic loss trains it and the target network
      averages it; the policy step reads its features without training it.

    Callers turn observations into the heads' input with `encode` first: (B, obs) rows shared by all
    tasks or (T, B, obs) rows per task give (T, B, features), the trunk evaluated once per row.
    """

    def __init__(
        self,
        num_tasks: int,
        obs_dim: int,
        act_dim: int,
        hidden: Sequence[int] = (256, 256),
        initial_alpha: float = 1e-2,
        shared_trunk: bool = False,
    ):
        super().__init__()
        self.num_tasks, self.obs_dim, self.act_dim = num_tasks, obs_dim, act_dim
        if shared_trunk:
            layers: list[nn.Module] = []
            for width in hidden:
                layers += [nn.Linear(obs_dim, width), nn.ReLU()]
                obs_dim = width
            self.trunk: nn.Module | None = nn.Sequential(*layers)
            self.target_trunk: nn.Module | None = copy.deepcopy(self.trunk).requires_grad_(False)
            head = (hidden[-1],)
        else:
            self.trunk = self.target_trunk = None
            head = tuple(hidden)
        self.actor = batched_mlp(num_tasks, obs_dim, 2 * act_dim, head)
        # Both twins of every task in one stack: members [0, T) are Q1, [T, 2T) are Q2.
        self.critic = batched_mlp(2 * num_tasks, obs_dim + act_dim, 1, head)
        self.target_critic = copy.deepcopy(self.critic).requires_grad_(False)
        self.log_alpha = nn.Parameter(torch.full((num_tasks,), math.log(initial_alpha)))

    @property
    def alpha(self) -> torch.Tensor:
        """The entropy temperature per task (num_tasks,), exp(log_alpha)."""
        return self.log_alpha.exp()

    def actor_parameters(self) -> list[nn.Parameter]:
        """What the policy step trains: the policies (heads)."""
        return list(self.actor.parameters())

    def critic_parameters(self) -> list[nn.Parameter]:
        """What the critic step trains: the Q-functions (heads) and the shared trunk."""
        return list(self.critic.parameters()) + ([] if self.trunk is None else list(self.trunk.parameters()))

    def encode(self, obs: torch.Tensor, target: bool = False) -> torch.Tensor:
        """The heads' input (T, B, features) of (B, obs) shared or (T, B, obs) per-task rows: the
        (target) trunk's features, or the observation itself without a trunk."""
        trunk = self.target_trunk if target else self.trunk
        h = obs if trunk is None else trunk(obs)
        return h.expand(self.num_tasks, *h.shape) if h.dim() == 2 else h

    def _gaussian(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, pre_std = self.actor(h).chunk(2, dim=-1)
        return mean, F.softplus(pre_std) + LOG_STD_EPS

    def sample(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Reparameterized squashed sample and its log-probability from `encode`d rows: (T, B, A), (T, B)."""
        mean, std = self._gaussian(h)
        noise = torch.randn_like(mean)
        pre_tanh = mean + std * noise
        # Normal(mean, std).log_prob(pre_tanh) in closed form: (pre_tanh - mean) / std is the noise.
        log_prob = -(0.5 * noise.square() + std.log()).sum(-1) - 0.5 * math.log(2.0 * math.pi) * noise.shape[-1]
        # log|d tanh(u)/du| = 2 (log 2 - u - softplus(-2u)), the numerically stable form.
        log_prob = log_prob - (2.0 * (math.log(2.0) - pre_tanh - F.softplus(-2.0 * pre_tanh))).sum(-1)
        return torch.tanh(pre_tanh), log_prob

    def mean_action(self, h: torch.Tensor) -> torch.Tensor:
        """Deterministic action (tanh of the mean) of `encode`d rows, used for evaluation."""
        return torch.tanh(self._gaussian(h)[0])

    def q(self, h: torch.Tensor, act: torch.Tensor, target: bool = False) -> torch.Tensor:
        """Twin Q-values (2, T, B) of per-task `encode`d rows (T, B, ·) (with `target`, encoded by the
        target trunk) and actions (T, B, A)."""
        net = self.target_critic if target else self.critic
        x = net[0].forward_parts(torch.cat([h, h]), torch.cat([act, act]))  # both twins
        for layer in net[1:]:
            x = layer(x)
        return x.view(2, self.num_tasks, -1)

    def target_pairs(self) -> list[tuple[nn.Module, nn.Module]]:
        """(target, source) modules that Polyak averaging moves together."""
        pairs = [(self.target_critic, self.critic)]
        return pairs if self.trunk is None else [*pairs, (self.target_trunk, self.trunk)]


@torch.no_grad()
def polyak_update(pairs: Iterable[tuple[nn.Module, nn.Module]], tau: float) -> None:
    """target <- (1 - tau) target + tau source, for every (target, source) pair."""
    targets, sources = zip(*((list(t.parameters()), list(s.parameters())) for t, s in pairs), strict=True)
    torch._foreach_lerp_(sum(targets, []), sum(sources, []), tau)
