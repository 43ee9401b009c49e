"""FIRE's BC learning between episodes (thesis Algorithm 2, lines 36-39): a few gradient steps on the
expert set after every episode, and a full warm-started retraining every `retrain_every` samples,
early-stopped on held-out expert frames that the per-episode steps never sample (so the hold-out
measures what the retraining adds, 5.3.4).
"""

from __future__ import annotations

import numpy as np
import torch

from shiftkit.policies.bc_policy import BCPolicy
from shiftkit.policies.data import epoch_batches
from shiftkit.policies.fire.config import FireArgs
from shiftkit.policies.frame_buffer import FrameBuffer
from shiftkit.policies.trainers.bc.training import update_members


def online_update(
    policy: BCPolicy, optimizers: list, expert: FrameBuffer, rows: np.ndarray, steps: int, args: FireArgs, rng, device
) -> float | None:
    """Algorithm 2 line 36: `steps` gradient steps of every member on batches drawn from the expert
    set's `rows` (those not held out)."""
    m, b = len(policy.members), args.bc.batch_size
    policy.train()
    losses = []
    for _ in range(steps):
        batch = expert.gather(rows[rng.integers(0, len(rows), m * b)], device)
        losses += update_members(policy, optimizers, batch, b, [True] * m, args.online_lr)
    policy.eval()
    return float(np.mean(losses)) if losses else None


def retrain(
    policy: BCPolicy, optimizers: list, expert: FrameBuffer, held_out: np.ndarray, args: FireArgs, seed: int, device
) -> dict:
    """Algorithm 2 line 39: BC on the expert set's training frames, warm-started; each member keeps
    its weights of lowest loss on the `held_out` frames and stops after `retrain_patience` epochs
    without improvement."""
    val, train_rows = np.flatnonzero(held_out), np.flatnonzero(~held_out)
    m = len(policy.members)
    b = min(args.bc.batch_size, len(train_rows))
    val_batch = expert.gather(val, device)

    @torch.no_grad()
    def val_losses() -> list[float]:
        obs, target = policy.normalizer(val_batch), policy.normalizer.action(val_batch["action"])
        return [((net(obs) - target) ** 2).mean().item() for net in policy.members]

    policy.eval()
    best = val_losses()
    start = list(best)
    best_weights = [{k: v.clone() for k, v in net.state_dict().items()} for net in policy.members]
    bad, active, epoch = [0] * m, [True] * m, 0
    for epoch in range(args.retrain_max_epochs):
        policy.train()
        batches = [epoch_batches(len(train_rows), b, seed, member, epoch) for member in range(m)]
        for i in range(len(batches[0])):
            rows = np.concatenate([train_rows[batches[member][i]] for member in range(m)])
            update_members(policy, optimizers, expert.gather(rows, device), b, active, args.retrain_lr)
        policy.eval()
        for member, loss in enumerate(val_losses()):
            if not active[member]:
                continue
            if loss < best[member]:
                best[member], bad[member] = loss, 0
                best_weights[member] = {k: v.clone() for k, v in policy.members[member].state_dict().items()}
            else:
                bad[member] += 1
                active[member] = bad[member] < args.retrain_patience
        if not any(active):
            break
    for net, weights in zip(policy.members, best_weights, strict=True):
        net.load_state_dict(weights)
    return {
        "retrain_epochs": epoch + 1,
        "retrain_val_loss": float(np.mean(best)),
        "retrain_frames": len(train_rows),
        "retrain_val_frames": len(val),
        "retrain_improved": bool(any(b < s for b, s in zip(best, start, strict=True))),
    }
