"""FIRE's discriminator D(s, a) (thesis 5.3.1, docs/fire.md): the probability that a state-action pair
comes from the expert rather than the policy.

Inputs are the BC policy's features, normalised with the same dataset statistics (`bc_policy.Normalizer`);
cameras go through the BC image encoder (`networks.image_encoder`, CNN + spatial soft-argmax), the
keypoints join the numeric state and the action in a 2x256 tanh MLP (Kostrikov et al. 2019, as in
the thesis, 5.4.2). Training: binary cross-entropy, expert = 1 and policy = 0, plus the gradient
penalty of Gulrajani et al. (2017), `lambda * (||grad D(x_mix)|| - 1)^2` on random mixes of an
expert and a policy batch (lambda 10). D trains after each episode for as many steps as the episode
had, once the policy set holds `start_after` samples (10k in the thesis).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from shiftkit.policies.bc_policy import Normalizer, PolicySpec
from shiftkit.policies.frame_buffer import FrameBuffer
from shiftkit.policies.networks import image_encoder, mlp, orthogonal_init_


@dataclass
class DiscriminatorConfig:
    """Discriminator network and training settings (defaults: thesis 5.4.2)."""

    hidden: list[int] = field(default_factory=lambda: [256, 256])
    """Widths of the tanh MLP."""
    lr: float = 1e-3
    """Adam learning rate."""
    batch_size: int = 64
    """Expert frames and policy frames per gradient step (each)."""
    grad_penalty: float = 10.0
    """Weight of the gradient penalty."""
    start_after: int = 10000
    """Policy samples collected before D trains (and D-based predictions begin)."""


class DiscriminatorNet(nn.Module):
    """Logit of D(s, a) from normalised inputs (feature -> tensor, plus `action`)."""

    def __init__(self, spec: PolicySpec, hidden: list[int]) -> None:
        super().__init__()
        self.numeric_keys, self.image_keys = spec.numeric_keys(), spec.image_keys()
        self.encoders = nn.ModuleList()
        for key in self.image_keys:
            h, w, c = spec.features[key]["shape"]
            self.encoders.append(image_encoder(spec.encoder, c, h, w, spec.num_keypoints))
        in_dim = sum(int(np.prod(spec.features[k]["shape"])) for k in self.numeric_keys)
        in_dim += sum(enc.out_dim for enc in self.encoders) + int(np.prod(spec.action["shape"]))
        self.head = mlp(in_dim, 1, tuple(hidden), act=nn.Tanh)

    def forward(self, x: dict[str, torch.Tensor]) -> torch.Tensor:
        """The (B, 1) logit of D(s, a) for normalised inputs `x` (observation features and `action`)."""
        parts = [x[k].flatten(1) for k in self.numeric_keys]
        parts += [enc(x[k]) for enc, k in zip(self.encoders, self.image_keys, strict=True)]
        parts.append(x["action"].flatten(1))
        return self.head(torch.cat(parts, dim=-1)).squeeze(-1)


class Discriminator:
    """D(s, a) with its optimiser: `update` after each episode, `score` for failure prediction."""

    def __init__(
        self, spec: PolicySpec, config: DiscriminatorConfig, device: torch.device | str = "cpu", seed: int = 0
    ) -> None:
        self.config = config
        self.device = torch.device(device)
        self.normalizer = Normalizer(spec).to(self.device)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed * 7919 + 17)
            self.net = DiscriminatorNet(spec, config.hidden)
            orthogonal_init_(self.net)
        self.net.to(self.device)
        self.optimizer = torch.optim.Adam(self.net.parameters(), lr=config.lr)
        self.keys = [*spec.features, "action"]
        self.updates = 0

    def ready(self, policy_samples: int) -> bool:
        """Whether D trains (and is trusted) with this many policy samples collected."""
        return policy_samples >= self.config.start_after

    def _inputs(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        x = self.normalizer(batch)
        x["action"] = self.normalizer.action(batch["action"].float())
        return x

    def update(self, expert: FrameBuffer, policy: FrameBuffer, steps: int, rng: np.random.Generator) -> dict:
        """`steps` gradient steps on expert vs policy batches; returns mean loss and accuracy."""
        self.net.train()
        b, losses, accs = self.config.batch_size, [], []
        bce = nn.BCEWithLogitsLoss()
        for _ in range(steps):
            xe = self._inputs(expert.sample(b, rng, self.device))
            xp = self._inputs(policy.sample(b, rng, self.device))
            le, lp = self.net(xe), self.net(xp)
            loss = bce(le, torch.ones_like(le)) + bce(lp, torch.zeros_like(lp))
            # gradient penalty on random mixes of the two batches (one mixing weight per pair)
            alpha = torch.as_tensor(rng.random(b), dtype=torch.float32, device=self.device)
            mixed = {}
            for k in xe:
                a = alpha.view(-1, *([1] * (xe[k].dim() - 1)))
                mixed[k] = (a * xe[k] + (1 - a) * xp[k]).detach().requires_grad_(True)
            out = self.net(mixed)
            grads = torch.autograd.grad(out.sum(), list(mixed.values()), create_graph=True)
            norm = torch.cat([g.flatten(1) for g in grads], dim=1).norm(dim=1)
            loss = loss + self.config.grad_penalty * ((norm - 1.0) ** 2).mean()
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self.optimizer.step()
            losses.append(loss.item())
            accs.append(((le > 0).float().mean().item() + (lp <= 0).float().mean().item()) / 2)
        self.updates += steps
        self.net.eval()
        return {
            "d_loss": float(np.mean(losses)) if losses else None,
            "d_accuracy": float(np.mean(accs)) if accs else None,
        }

    @torch.no_grad()
    def score(self, frames: dict[str, np.ndarray | torch.Tensor]) -> np.ndarray:
        """D(s, a) in [0, 1] for a batch of frames (features + `action`)."""
        self.net.eval()
        batch = {k: torch.as_tensor(np.array(frames[k])).to(self.device) for k in self.keys}
        return torch.sigmoid(self.net(self._inputs(batch))).cpu().numpy().astype(np.float64)

    def state_dict(self) -> dict:
        """The network, its optimiser and the update count, for checkpoints."""
        return {"net": self.net.state_dict(), "optimizer": self.optimizer.state_dict(), "updates": self.updates}

    def load_state_dict(self, state: dict) -> None:
        """Restores what `state_dict` saved."""
        self.net.load_state_dict(state["net"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.updates = state["updates"]
