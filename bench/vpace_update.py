"""Cost of one update of VPACE (lift, 4 intentions) and LfGP (stack, 6 intentions, the reference's
shared-trunk network), fp32 and the faster settings tried, beside the reference code's FLOPs.

Configurations, as `shiftkit train` runs them (docs/vpace.md), with 59-dim observations, 4-dim actions
and 256-unit layers:
* `vpace`: main task lift with open, close and reach; SQIL labels, value penalization, separate networks
  per task; 128 replay rows and 128 example rows divided among the tasks (32 each).
* `lfgp`: main task stack with open, close, lift, reach and move-object; thesis Table A.2: batch 256 (25
  of them expert transitions at the first update), one trunk under per-task policy and Q heads, one
  multitask discriminator on (s, a) trained on the 256 replay rows against 256 expert rows per task
  with the gradient penalty.

Settings, timed in one process, interleaved, best of 3 rounds (CPU time with 1 thread, where other jobs
sharing the cores inflate it less; wall time on a GPU):
* `fp32`: the trainer as it runs;
* `bf16`: the update under `torch.autocast(dtype=torch.bfloat16)` (bf16 matmuls);
* `compile`: `Agent.update` under `torch.compile` (its first calls, the compilation, are timed apart);
  torch 2.11 cannot compile LfGP's (AOTAutograd has no double backward, which the discriminator's
  gradient penalty needs), so the JSON lists it under `failed`.
A setting is `chosen` only where it is faster than fp32 here; the trainer uses it only once a short
learning run with it matches fp32 within its confidence interval (docs/vpace.md).

FLOPs per update, counted by torch's FlopCounterMode (matmuls, forward and backward, the gradient
penalty's double backward included):
* `shiftkit`: one `Agent.update`;
* `reference`: the same update as the reference code computes it (utiasSTARS/lfgp
  `UpdateSACIntentions`, `UpdateDACIntentions`, its multitask networks), counted the same way on layers
  of the reference's shapes. Its heads are grouped 1x1 convolutions that run every task's head on
  every row, and its target-Q and policy passes repeat the batch once per task (`aug_data`), so those
  passes cost T x T heads per row; shiftkit runs each row through its own task's heads.
LfGP's update is also counted with a network per task instead of the trunk
(`shiftkit_separate_networks`). The JSON's metric is shiftkit's FLOPs over the reference's for LfGP
(goal <= 1: no extra arithmetic).
Prints one JSON line last: {"bench": "vpace_update", "metric": "flops_ratio_shiftkit_vs_reference_lfgp", ...}.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import os
import time
from collections.abc import Callable

import _device  # bench/, beside this file
import gymnasium as gym
import numpy as np
import torch
from torch import nn

from shiftkit.datasets.errors import ConfigError
from shiftkit.policies.cpu_memory import keep_freed_memory
from shiftkit.policies.replay import ReplayBuffer
from shiftkit.policies.run_dir import torch_device
from shiftkit.policies.sac import batched_mlp
from shiftkit.policies.trainers.vpace.args import VPACEArgs
from shiftkit.policies.trainers.vpace.example_buffer import ExampleBuffer, TaskExamples
from shiftkit.policies.trainers.vpace.training import Agent, sample_update

OBS_DIM, ACT_DIM = 59, 4
CONFIGS = {
    "vpace": dict(variant="vpace", main_task="lift", aux_tasks=["open", "close", "reach"]),
    "lfgp": dict(variant="lfgp", main_task="stack", aux_tasks=["open", "close", "lift", "reach", "move-object"]),
}
SETTINGS = ("fp32", "bf16", "compile")


def make_args(config: str, **overrides: object) -> VPACEArgs:
    spec = dict(CONFIGS[config])
    return VPACEArgs.for_variant(spec.pop("variant"), **spec, **overrides)


def make_step(config: str, setting: str, device: torch.device, **overrides: object) -> Callable[[int], None]:
    """Update `i` of a fresh agent of `config` (with `overrides`) on one of 8 pre-sampled batches, in `setting`."""
    args = make_args(config, **overrides)
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    if device.type == "cpu":
        keep_freed_memory()  # as training does
    agent = Agent(args, OBS_DIM, gym.spaces.Box(-1.0, 1.0, (ACT_DIM,), np.float32), device)
    replay = ReplayBuffer(10_000, OBS_DIM, ACT_DIM)
    for _ in range(10_000):
        replay.add(rng.standard_normal(OBS_DIM), rng.uniform(-1, 1, ACT_DIM), rng.standard_normal(OBS_DIM), False)

    def task_set() -> TaskExamples:
        obs = rng.standard_normal((500, OBS_DIM)).astype(np.float32)
        act = rng.uniform(-1, 1, (500, ACT_DIM)).astype(np.float32) if args.full_trajectories else None
        return TaskExamples(obs, act, np.roll(obs, -1, 0), np.arange(500) % 50 == 49)

    examples = ExampleBuffer({t: task_set() for t in args.tasks}, args.tasks, args.aug_factor)
    batches = [sample_update(args, args.buffer_warmup, replay, examples, rng) for _ in range(8)]
    update = torch.compile(agent.update) if setting == "compile" else agent.update

    def step(i: int) -> None:
        if setting == "bf16":
            with torch.autocast(device.type, dtype=torch.bfloat16):
                update(*batches[i % 8])
        else:
            update(*batches[i % 8])

    return step


def time_updates(config: str, setting: str, updates: int, warmup: int, device: torch.device) -> tuple[float, float]:
    """(seconds per update, seconds of the `warmup` first updates): CPU time on a CPU, wall time on a GPU."""
    step = make_step(config, setting, device)
    clock = time.perf_counter if device.type == "cuda" else time.process_time
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    start = clock()
    for i in range(warmup):
        step(i)
    sync()
    first = clock() - start
    start, done = clock(), 0
    while done < updates:
        step(warmup + done)
        done += 1
        if done == 3 and clock() - start > 1.0:  # a setting ten times slower than fp32 needs no long run
            break
    sync()
    return (clock() - start) / done, first


class _Global:
    """FlopCounterMode's stand-in module tracker that files every count under "Global": its real one
    hooks every module's backward, which `autograd.grad` on a leaf input (the gradient penalty) refuses."""

    parents = ("Global",)

    def __enter__(self) -> _Global:
        return self

    def __exit__(self, *exc: object) -> None:
        return None


def flop_counter():
    """torch's matmul FLOP counter (forward, backward and double backward), without module tracking."""
    from torch.utils.flop_counter import FlopCounterMode

    counter = FlopCounterMode(display=False)
    counter.mod_tracker = _Global()
    return counter


def shiftkit_flops(config: str, device: torch.device, **overrides: object) -> int:
    """Matmul FLOPs of one `Agent.update` (forward and backward), counted by torch."""
    step = make_step(config, "fp32", device, **overrides)
    with flop_counter() as counter:
        step(0)
    return counter.get_total_flops()


def reference_flops(config: str, device: torch.device) -> int:
    """Matmul FLOPs of the same update as the reference code computes it, counted by torch on stand-in
    layers of the reference's shapes (module docstring). Every pass below is one of the reference's,
    with its rows: B the batch, T the tasks; `all_heads(x, net)` is a grouped 1x1 convolution, every
    member of `net` on every row of x."""
    args, a, h = make_args(config), ACT_DIM, 256
    T, B = len(args.tasks), args.batch_size + (0 if args.full_trajectories else args.example_batch_size)
    rand = lambda *shape: torch.randn(*shape, device=device)  # noqa: E731

    def all_heads(x: torch.Tensor, net: nn.Module) -> torch.Tensor:
        members = net[0].weight.shape[0]
        return net(x.expand(members, *x.shape))

    with flop_counter() as counter:
        if not args.shared_trunk:  # VPACE: `shared_layers: false`, every task's own policy and twin Q
            policy = batched_mlp(T, OBS_DIM, 2 * a, (h, h)).to(device)
            critic = batched_mlp(2 * T, OBS_DIM + a, 1, (h, h)).to(device)
            target = copy.deepcopy(critic).requires_grad_(False)
            expert, buffer = args.example_batch_size, args.batch_size
            with torch.no_grad():
                all_heads(rand(expert, OBS_DIM), policy)  # the expert rows' actions, every policy
                all_heads(rand(B, OBS_DIM), policy)  # next actions
                all_heads(rand(T * B, OBS_DIM + a), target)  # target Q of the batch repeated per task
            all_heads(rand(B, OBS_DIM + a), critic).sum().backward()  # the Q loss
            x = rand(buffer, OBS_DIM)
            acts = all_heads(x, policy)[..., :a].tanh().reshape(T * buffer, a)
            obs_act = torch.cat([x.repeat(T, 1), acts], -1)
            all_heads(obs_act, critic).sum().backward()  # the policy loss, the repeated rows through every Q
            with torch.no_grad():
                all_heads(x, policy)  # the temperature's log-probabilities
        else:  # LfGP: shared trunk, branched heads, one discriminator on (s, a)
            trunk = batched_mlp(1, OBS_DIM, h, (h,)).to(device)  # two ReLU layers (the last one's ReLU aside)
            policy = batched_mlp(T, h, 2 * a, (h,)).to(device)
            critic = batched_mlp(2 * T, h + a, 1, (h,)).to(device)
            target_trunk, target = copy.deepcopy(trunk), copy.deepcopy(critic)
            disc = batched_mlp(1, OBS_DIM + a, T, (h, h), act=nn.Tanh).to(device)
            features = lambda x, net=trunk: net(x.unsqueeze(0))[0].relu()  # noqa: E731
            # The discriminator: buffer rows and each task's expert rows (every logit, one gathered), the
            # gradient penalty on the mixtures.
            (disc(rand(1, B, OBS_DIM + a)).sum() + disc(rand(1, T * B, OBS_DIM + a)).sum()).backward()
            mix = rand(1, T * B, OBS_DIM + a).requires_grad_(True)
            (grad,) = torch.autograd.grad(disc(mix).sum(), mix, create_graph=True)
            grad.norm(dim=-1).sum().backward()
            with torch.no_grad():
                disc(rand(1, B, OBS_DIM + a))  # the batch's rewards
                acts = all_heads(features(rand(B, OBS_DIM)), policy)[..., :a].tanh().reshape(T * B, a)
                next_h = features(rand(T * B, OBS_DIM), target_trunk)  # the batch repeated per task
                all_heads(torch.cat([next_h, acts], -1), target)
            all_heads(torch.cat([features(rand(B, OBS_DIM)), rand(B, a)], -1), critic).sum().backward()
            x = rand(B, OBS_DIM)
            acts = all_heads(features(x), policy)[..., :a].tanh().reshape(T * B, a)
            all_heads(torch.cat([features(x.repeat(T, 1)), acts], -1), critic).sum().backward()
            with torch.no_grad():
                all_heads(features(x), policy)  # the temperature's log-probabilities
    return counter.get_total_flops()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="few updates, fp32 and bf16 only (under a minute)")
    parser.add_argument("--updates", type=int, default=50, help="timed updates per configuration and setting")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--device", default="auto")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    try:
        device = torch_device(args.device)
    except ConfigError as exc:
        parser.error(str(exc))
    updates, warmup, rounds = (5, 2, 1) if args.quick else (args.updates, 5, 3)
    settings = SETTINGS[:2] if args.quick else SETTINGS
    best: dict[str, dict[str, float]] = {c: {} for c in CONFIGS}
    first: dict[str, dict[str, float]] = {c: {} for c in CONFIGS}
    failed: dict[str, str] = {}
    for _ in range(rounds):  # interleaved, so load drifts affect every setting alike
        for config in CONFIGS:
            for setting in settings:
                if f"{config} {setting}" in failed:
                    continue
                try:
                    per_update, warm = time_updates(config, setting, updates, warmup, device)
                except Exception as exc:  # a setting this machine's torch cannot run is reported, not fatal
                    failed[f"{config} {setting}"] = f"{type(exc).__name__}: {str(exc).splitlines()[0][:200]}"
                    continue
                best[config][setting] = min(best[config].get(setting, math.inf), per_update)
                first[config][setting] = warm
    flops = {c: {"shiftkit": shiftkit_flops(c, device), "reference": reference_flops(c, device)} for c in CONFIGS}
    # LfGP with a network per task (no trunk), as shiftkit trained it before: what the trunk saves.
    flops["lfgp"]["shiftkit_separate_networks"] = shiftkit_flops("lfgp", device, shared_trunk=False)
    chosen = {c: min(times, key=times.get) for c, times in best.items()}
    for config in CONFIGS:
        times = ", ".join(f"{s} {t * 1e3:.1f} ms" for s, t in best[config].items())
        f = flops[config]
        print(
            f"{config}: {times}; {f['shiftkit'] / 1e9:.2f} GFLOP per update (reference code: "
            f"{f['reference'] / 1e9:.2f}); fastest: {chosen[config]}"
        )
    for setting, why in failed.items():
        print(f"{setting}: not measured ({why})")
    ratio = flops["lfgp"]["shiftkit"] / flops["lfgp"]["reference"]
    print(
        json.dumps(
            {
                "bench": "vpace_update",
                "metric": "flops_ratio_shiftkit_vs_reference_lfgp",
                "value": round(ratio, 3),
                "goal": 1.0,
                "higher_is_better": False,
                "ms_per_update": {c: {s: round(t * 1e3, 2) for s, t in b.items()} for c, b in best.items()},
                "first_updates_s": {c: {s: round(t, 2) for s, t in f.items()} for c, f in first.items()},
                "fastest": chosen,
                "failed": failed,
                "gflop_per_update": {c: {k: round(v / 1e9, 3) for k, v in f.items()} for c, f in flops.items()},
                "flops_ratio_shiftkit_vs_reference": {
                    c: round(f["shiftkit"] / f["reference"], 3) for c, f in flops.items()
                },
                "clock": "wall" if device.type == "cuda" else "cpu",
                "device": str(device),
                "gpu": _device.gpu_info(),
                "threads": args.threads,
                "updates": updates,
                "loadavg_1min": round(os.getloadavg()[0], 2),
            }
        )
    )


if __name__ == "__main__":
    main()
