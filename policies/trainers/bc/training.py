"""Behavioural cloning (thesis 3.6.3 and 4.4.2): MSE action regression by one network or by an
ensemble (`--ensemble N`; the policy and its networks: `bc_policy`).

Observations are the dataset's `observation.*` features: numeric ones are normalised with the
dataset's stats and concatenated; each camera goes through a CNN (or ResNet-18 trunk) ending in a
spatial soft-argmax, whose keypoints join the numeric state before the fully connected layers.
With several members, each sees its own shuffle of the data and its own orthogonal init; the
policy outputs the members' mean, and their spread is the ensemble doubt of FIRE (thesis 5.4).

Two regimes:
* `early-stop` (thesis ch. 3): Adam 1e-3, batch 64, a 20% hold-out of episodes, each member stops
  when its validation loss has not improved for 30 epochs (max 200) and keeps its best weights.
* `fixed` (thesis ch. 4): 20k steps, AdamW weight decay 0.1, lr 3e-4 halved halfway.

Normalisation cannot explode (`Normalization`): each dimension's std is floored at a share of its
own magnitude and the normalised inputs are clipped, so a state far outside the demonstrations (a
correction in FIRE, a bumped object whose velocity was ~0 in every demonstration) reaches the network
as a bounded input. The values are part of the policy spec, so checkpoint and model card record them.

The batch order is a function of (seed, member, step) and every checkpoint holds the full training
state, so a resumed run continues bit for bit where the killed one left off.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import torch
from tqdm import tqdm

from shiftkit.datasets.dataset import Dataset
from shiftkit.datasets.errors import ConfigError, DatasetError
from shiftkit.policies.bc_policy import BCPolicy, Normalization, PolicySpec
from shiftkit.policies.data import (
    FrameTable,
    Prefetcher,
    batches_per_epoch,
    epoch_batches,
    open_datasets,
    refuse_example_sets,
)
from shiftkit.policies.run_dir import RunDir, dataset_records, torch_device, versions
from shiftkit.policies.trainers.bc.args import BCArgs


def update_members(
    policy: BCPolicy,
    optimizers: list[torch.optim.Optimizer],
    batch: dict[str, torch.Tensor],
    batch_size: int,
    active: list[bool],
    lr: float,
) -> list[float | None]:
    """One gradient step of every active member on its own slice `[m*B, (m+1)*B)` of `batch`;
    returns each member's MSE (normalised units), None for inactive members."""
    obs, target = policy.normalizer(batch), policy.normalizer.action(batch["action"])
    losses: list[float | None] = []
    for m, (net, opt) in enumerate(zip(policy.members, optimizers, strict=True)):
        if not active[m]:
            losses.append(None)
            continue
        for group in opt.param_groups:
            group["lr"] = lr
        part = slice(m * batch_size, (m + 1) * batch_size)
        loss = ((net({k: v[part] for k, v in obs.items()}) - target[part]) ** 2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        losses.append(loss.item())
    return losses


def _select_inputs(features: dict[str, dict], inputs: list[str] | None) -> list[str]:
    if inputs is None:
        inputs = [k for k in features if k.startswith("observation.")]
    missing = [k for k in inputs if k not in features]
    if missing:
        raise ConfigError(f"input feature {missing[0]!r} is not in the dataset (has {', '.join(features)})")
    if not inputs:
        raise DatasetError("the dataset has no observation.* features to learn from")
    if "action" not in features:
        raise DatasetError("the dataset has no 'action' feature")
    return list(inputs)


def _merged_stats(datasets: list, keys: list[str]) -> dict[str, dict[str, list]]:
    from lerobot.datasets.compute_stats import aggregate_feature_stats

    out = {}
    for key in keys:
        per_ds = [ds.meta.stats.get(key) if ds.meta.stats else None for ds in datasets]
        if any(s is None or "mean" not in s or "std" not in s for s in per_ds):
            raise DatasetError(f"dataset stats (meta/stats.json) lack mean/std of {key!r}")
        merged = per_ds[0] if len(per_ds) == 1 else aggregate_feature_stats(per_ds)
        if not np.all(np.isfinite(merged["mean"])) or not np.all(np.isfinite(merged["std"])):
            raise DatasetError(f"dataset stats of {key!r} hold NaN or inf")
        out[key] = {"mean": np.asarray(merged["mean"]).tolist(), "std": np.asarray(merged["std"]).tolist()}
    return out


def check_root_id(dataset: Dataset, root: str | None) -> None:
    """`--dataset ID --root DIR`: the folder must hold that dataset (by the ID its provenance
    records), else the run would record an ID it did not train on. A dataset shiftkit did not make
    records none to compare with."""
    recorded = (dataset.provenance.get("output") or {}).get("repo_id")
    if root is not None and recorded is not None and recorded != dataset.repo_id:
        raise ConfigError(
            f"--dataset {dataset.repo_id} but {root} holds {recorded}: give --dataset {recorded} (or omit --root)"
        )


def train(args: BCArgs, progress: bool = False) -> dict:
    """Train (or resume) a BC policy (one network or an ensemble); returns the final metrics written to the model card.
    `progress` shows a bar with the training loss (its total is the step budget: early stopping
    may end sooner)."""
    args = args.resolved()
    # --- data: one frame table over all datasets, episodes split into train / held-out ---
    opened = open_datasets(args.datasets, args.root)
    check_root_id(opened[0][0], args.root)
    refuse_example_sets(opened, "BC")
    run = RunDir(args.output_dir, args.resume)
    device = torch_device(args.device)
    if args.threads is not None:
        torch.set_num_threads(args.threads)

    datasets = [ds for _, ds in opened]
    inputs = _select_inputs(datasets[0].meta.features, args.inputs)
    table = FrameTable(datasets, [*inputs, "action"])
    train_rows, val_rows = table.split_episodes(args.val_fraction, args.seed)
    features = {k: {f: datasets[0].meta.features[k].get(f) for f in ("dtype", "shape", "names")} for k in inputs}
    spec = PolicySpec(
        features=features,
        action={f: datasets[0].meta.features["action"].get(f) for f in ("dtype", "shape", "names")},
        stats=_merged_stats(datasets, [*inputs, "action"]),
        encoder=args.encoder,
        num_keypoints=args.num_keypoints,
        hidden=args.hidden,
        ensemble_size=args.ensemble_size,
        normalization=Normalization(std_floor=args.norm_std_floor, clip=args.norm_clip),
        output_activation=args.output_activation,
    )

    # The global generator is saved with every checkpoint (and restored on resume); torch starts it from a
    # random seed, so seed it: a checkpoint's bytes are then a function of the seed.
    torch.manual_seed(args.seed)
    # --- model and optimisers: one AdamW per member ---
    policy = BCPolicy(spec, args.encoder_weights, seed=args.seed).to(device)
    members = policy.members
    optimizers = [torch.optim.AdamW(m.parameters(), lr=args.lr, weight_decay=args.weight_decay) for m in members]
    per_epoch = batches_per_epoch(len(train_rows), args.batch_size)
    total_steps = args.steps if args.regime == "fixed" else min(args.steps or math.inf, args.max_epochs * per_epoch)
    M, B = args.ensemble_size, min(args.batch_size, len(train_rows))

    run.write_config(
        {
            "trainer": "bc",
            "args": dataclasses.asdict(args),
            "datasets": dataset_records([r for r, _ in opened]),
            "seed": args.seed,
            "versions": versions(),
            "inputs": inputs,
            "frames": {"train": len(train_rows), "val": len(val_rows), "episodes": len(table.episodes)},
            "normalization": {
                **dataclasses.asdict(spec.normalization),
                "floored_dims": policy.normalizer.floored_dims(spec),
            },
        }
    )

    # --- training state (everything a resumed run needs) ---
    step = 0
    active = [True] * M  # early-stop: members still training
    best_val = [math.inf] * M
    bad_epochs = [0] * M
    best_weights: list[dict | None] = [None] * M
    loss_sum, loss_count = torch.zeros(M), torch.zeros(M)  # per member since the last log line
    state = run.load_latest() if args.resume else None
    if state is not None:
        policy.load_state_dict(state["model"])
        for opt, s in zip(optimizers, state["optimizers"], strict=True):
            opt.load_state_dict(s)
        step, active, best_val, bad_epochs = state["step"], state["active"], state["best_val"], state["bad_epochs"]
        best_weights, loss_sum, loss_count = state["best_weights"], state["loss_sum"], state["loss_count"]
        torch.set_rng_state(state["torch_rng"])
        if state["final"]:
            return state["metrics"]

    def checkpoint(metrics: dict | None = None) -> None:
        run.save_checkpoint(
            step,
            {
                "trainer": "bc",
                "final": metrics is not None,
                "metrics": metrics,
                "policy_spec": dataclasses.asdict(spec),
                "model": policy.state_dict(),
                "optimizers": [o.state_dict() for o in optimizers],
                "active": active,
                "best_val": best_val,
                "bad_epochs": bad_epochs,
                "best_weights": best_weights,
                "loss_sum": loss_sum,
                "loss_count": loss_count,
                "torch_rng": torch.get_rng_state(),
            },
        )

    val_batches = [
        {k: torch.from_numpy(v).to(device) for k, v in table.gather(val_rows[i : i + 1024]).items()}
        for i in range(0, len(val_rows), 1024)
    ]

    def val_losses() -> list[float]:
        policy.eval()
        sums, n = torch.zeros(M), 0
        with torch.no_grad():
            for batch in val_batches:
                obs, target = policy.normalizer(batch), policy.normalizer.action(batch["action"])
                for m, net in enumerate(members):
                    sums[m] += ((net(obs) - target) ** 2).mean(dim=-1).sum().cpu()
                n += len(target)
        policy.train()
        return (sums / n).tolist()

    def step_rows(start: int):
        """Row indices of every remaining step: each member's batch, concatenated."""
        epoch_cache: tuple[int, list[list[np.ndarray]]] = (-1, [])
        for s in range(start, int(total_steps)):
            epoch, i = divmod(s, per_epoch)
            if epoch != epoch_cache[0]:
                epoch_cache = (epoch, [epoch_batches(len(train_rows), B, args.seed, m, epoch) for m in range(M)])
            yield np.concatenate([train_rows[epoch_cache[1][m][i]] for m in range(M)])

    # --- the loop: every step updates each still-active member on its own batch ---
    policy.train()
    started, start_step = time.perf_counter(), step
    bar = tqdm(total=int(total_steps), initial=step, desc="train bc", unit="step", disable=not progress, leave=False)
    with bar, Prefetcher(table, step_rows(step), pin=device.type == "cuda") as batches:
        for batch in batches:
            batch = {k: v.to(device, non_blocking=True) for k, v in batch.items()}
            lr = args.lr * (0.5 if args.regime == "fixed" and step >= total_steps // 2 else 1.0)
            losses = update_members(policy, optimizers, batch, B, active, lr)
            for m, loss in enumerate(losses):
                if loss is not None:
                    loss_sum[m] += loss
                    loss_count[m] += 1
            step += 1
            bar.update(1)

            if step % args.log_every == 0:
                trained = loss_count > 0
                member_loss = [
                    s / c if c else None for s, c in zip(loss_sum.tolist(), loss_count.tolist(), strict=True)
                ]
                run.log(
                    step,
                    "train",
                    loss=(loss_sum[trained] / loss_count[trained]).mean().item(),
                    member_loss=member_loss,
                    lr=lr,
                    steps_per_s=(step - start_step) / (time.perf_counter() - started),
                )
                bar.set_postfix(loss=f"{(loss_sum[trained] / loss_count[trained]).mean().item():.4g}")
                loss_sum, loss_count = torch.zeros(M), torch.zeros(M)
            if step % per_epoch == 0 and val_batches:
                losses = val_losses()
                for m in range(M):
                    if not active[m]:
                        continue
                    if losses[m] < best_val[m]:
                        best_val[m], bad_epochs[m] = losses[m], 0
                        best_weights[m] = {k: v.detach().clone() for k, v in members[m].state_dict().items()}
                    else:
                        bad_epochs[m] += 1
                        if args.regime == "early-stop" and bad_epochs[m] >= args.patience:
                            active[m] = False
                run.log(
                    step,
                    "val",
                    epoch=step // per_epoch,
                    loss=float(np.mean(losses)),
                    member_loss=losses,
                    active=sum(active),
                )
            if step >= total_steps or not any(active):
                break
            if step % args.checkpoint_every == 0:
                checkpoint()

    # --- finish: early stopping keeps each member's best weights ---
    if args.regime == "early-stop":
        for m, weights in enumerate(best_weights):
            if weights is not None:
                members[m].load_state_dict(weights)
    metrics = {"steps": step, "train_frames": len(train_rows), "val_frames": len(val_rows)}
    if val_batches:
        losses = val_losses()
        metrics.update(val_loss=float(np.mean(losses)), val_member_loss=losses)
        run.log(step, "final", loss=metrics["val_loss"], member_loss=losses)
    checkpoint(metrics)
    run.write_model_card(metrics)
    return metrics
