"""Cost of one VPACE update of 5 intentions, batched vs one after another, and vs 1 intention.

All intentions are stacked into batched matmuls, so adding tasks costs much less than linearly where
an update is bound by per-operation latency (a GPU). Nothing is shared between tasks, so the arithmetic
itself grows linearly, and on a CPU, where it dominates, the ratio stays near 4 (docs/vpace.md).
The comparison that holds on any device: the batched 5-intention update vs the same 5 intentions as
5 single-intention agents (own networks and optimizers) updated one after another; goal
batched <= 0.6 of the loop. (The reference code batches its intentions too, as grouped 1x1
convolutions in one network per role; the loop is the naive alternative.) The 5-vs-1 ratio (goal 2.5)
is kept, flagged meaningful on a GPU only.
Panda-sized problem: 59-dim observations, 4-dim actions, 256x256 networks, 128 replay + 128 example rows.

Where the arithmetic bounds the ratio, the JSON says so: the update's matmul FLOPs (counted by
torch's FlopCounterMode), this machine's batched-matmul rate measured in the same run on the hidden
layer's shape, the resulting floor of the 5-intention update and `ratio_floor`, the batched/loop
ratio if the batched update ran at that rate with no other cost. CPU time is reported beside wall
time: with 1 thread it is what the update costs, and other jobs time-slicing the cores inflate it
less. `--profile` prints where the time goes (torch profiler), batched and loop. Both run in one
process, under the allocator settings of `shiftkit train vpace` on CPU (policies/cpu_memory.py).
Prints one JSON line last: {"bench": "vpace_update", "metric": "update_time_ratio_batched_vs_loop_5_intentions", ...}.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from collections.abc import Callable

import _device  # bench/, beside this file
import gymnasium as gym
import numpy as np
import torch

from shiftkit.datasets.errors import ConfigError
from shiftkit.policies.cpu_memory import keep_freed_memory
from shiftkit.policies.replay import ReplayBuffer
from shiftkit.policies.run_dir import torch_device
from shiftkit.policies.trainers.vpace.args import VPACEArgs
from shiftkit.policies.trainers.vpace.training import Agent

OBS_DIM, ACT_DIM = 59, 4
# operator-name prefixes of the profile's element-wise class (beside matmuls, ReLU and optimizers)
ELEMENTWISE = (
    "mul add sub div sum mean pow square sqrt exp log neg tanh softplus sigmoid clamp min max lerp_ fill_ linalg_"
)


def make_agent(num_tasks: int, reward_model: str, device: torch.device) -> Agent:
    aux = [f"aux{i}" for i in range(num_tasks - 1)]
    args = VPACEArgs.for_variant("vpace", main_task="main", aux_tasks=aux, reward_model=reward_model)
    if device.type == "cpu":
        keep_freed_memory()  # as training does
    return Agent(args, OBS_DIM, gym.spaces.Box(-1.0, 1.0, (ACT_DIM,), np.float32), device)


def make_step(num_tasks: int, reward_model: str, device: torch.device, loop: bool) -> Callable[[int], None]:
    """Update `i` of `num_tasks` intentions: one agent holding them all (batched), or with `loop`, one
    single-intention agent per task, updated one after another."""
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    agents = (
        [make_agent(1, reward_model, device) for _ in range(num_tasks)]
        if loop
        else [make_agent(num_tasks, reward_model, device)]
    )
    args = agents[0].args
    replay = ReplayBuffer(10_000, OBS_DIM, ACT_DIM)
    for _ in range(10_000):
        replay.add(rng.standard_normal(OBS_DIM), rng.uniform(-1, 1, ACT_DIM), rng.standard_normal(OBS_DIM), False)
    batches = [
        (
            replay.sample(rng, args.batch_size),
            rng.standard_normal((num_tasks, args.example_batch_size, OBS_DIM), np.float32),
        )
        for _ in range(8)
    ]

    def step(i: int) -> None:
        batch, examples = batches[i % 8]
        if loop:
            for task, single in enumerate(agents):
                single.update(batch, examples[task : task + 1], None)
        else:
            agents[0].update(batch, examples, None)

    return step


def time_updates(
    num_tasks: int, updates: int, warmup: int, reward_model: str, device: torch.device, loop: bool
) -> tuple[float, float]:
    """(wall, CPU) seconds per update (see `make_step`)."""
    step = make_step(num_tasks, reward_model, device, loop)
    for i in range(warmup):
        step(i)
    if device.type == "cuda":
        torch.cuda.synchronize()
    wall, cpu = time.perf_counter(), time.process_time()
    for i in range(updates):
        step(i)
    if device.type == "cuda":
        torch.cuda.synchronize()
    return (time.perf_counter() - wall) / updates, (time.process_time() - cpu) / updates


def update_flops(num_tasks: int, reward_model: str, device: torch.device) -> int:
    """Matmul FLOPs of one update (forward and backward), counted by torch."""
    from torch.utils.flop_counter import FlopCounterMode

    step = make_step(num_tasks, reward_model, device, loop=False)
    counter = FlopCounterMode(display=False)
    with counter:
        step(0)
    return counter.get_total_flops()


def matmul_rate(num_tasks: int, device: torch.device, repeats: int = 20) -> float:
    """FLOP/s of this machine's batched matmul on the update's largest layer: both twin critics of
    every task, buffer + example rows (256), 256x256 weights; the best of 5 timings (CPU time on a
    CPU, so other jobs sharing the cores do not lower it)."""
    hidden, rows, members = 256, 256, 2 * num_tasks
    x, w = torch.randn(members, rows, hidden, device=device), torch.randn(members, hidden, hidden, device=device)
    clock = time.perf_counter if device.type == "cuda" else time.process_time
    best = math.inf
    for _ in range(5):
        if device.type == "cuda":
            torch.cuda.synchronize()
        start = clock()
        for _ in range(repeats):
            torch.bmm(x, w)
        if device.type == "cuda":
            torch.cuda.synchronize()
        best = min(best, clock() - start)
    return 2 * members * rows * hidden * hidden * repeats / best


def print_profile(reward_model: str, device: torch.device, updates: int) -> None:
    """Self time per operator class (torch profiler) of `updates` updates, batched and loop."""
    from torch.profiler import profile

    classes = {
        "matmul (bmm, baddbmm)": ("aten::bmm", "aten::baddbmm", "aten::mm", "aten::addmm"),
        "relu forward/backward": ("aten::clamp_min", "aten::threshold_backward", "aten::relu"),
        "optimizers": ("aten::_fused_adam", "aten::_fused_adamw", "Optimizer."),
        "other element-wise": tuple(f"aten::{op}" for op in ELEMENTWISE.split()),
        "copies (copy_, cat, clone)": ("aten::copy_", "aten::cat", "aten::clone", "aten::_to_copy"),
    }
    for loop in (False, True):
        step = make_step(5, reward_model, device, loop)
        for i in range(3):
            step(i)
        with profile() as prof:
            for i in range(updates):
                step(i)
        events = [e for e in prof.key_averages() if e.self_cpu_time_total > 0]
        total = sum(e.self_cpu_time_total for e in events)
        shares = {name: 0.0 for name in [*classes, "other operators and Python"]}
        for e in events:
            name = next(
                (c for c, prefixes in classes.items() if e.key.startswith(prefixes)), "other operators and Python"
            )
            shares[name] += e.self_cpu_time_total
        calls = sum(e.count for e in events)
        print(
            f"{'loop' if loop else 'batched'}, 5 intentions: {total / updates / 1e3:.1f} ms/update profiled, "
            f"{calls / updates:.0f} operator calls/update"
        )
        for name, t in shares.items():
            print(f"  {name:28s} {t / updates / 1e3:6.1f} ms  {100 * t / total:5.1f} %")
        top = sorted(events, key=lambda e: -e.self_cpu_time_total)[:8]
        print("  top: " + ", ".join(f"{e.key} {e.self_cpu_time_total / updates / 1e3:.2f} ms" for e in top))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="few updates (well under a minute)")
    parser.add_argument("--updates", type=int, default=300, help="timed updates per configuration")
    parser.add_argument("--reward-model", default="sqil", choices=["sqil", "dac"])
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--profile", type=int, default=0, metavar="N", help="also profile N updates, batched and loop")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    try:
        device = torch_device(args.device)
    except ConfigError as exc:
        parser.error(str(exc))
    updates, warmup = (40, 5) if args.quick else (args.updates, 20)
    if args.profile:
        print_profile(args.reward_model, device, args.profile)
    # Interleave the configurations so machine load drifts affect them alike; keep each one's best.
    runs: dict[str, list[tuple[float, float]]] = {"1": [], "5": [], "loop": []}
    for _ in range(3):
        runs["1"].append(time_updates(1, updates, warmup, args.reward_model, device, loop=False))
        runs["5"].append(time_updates(5, updates, warmup, args.reward_model, device, loop=False))
        runs["loop"].append(time_updates(5, updates, warmup, args.reward_model, device, loop=True))
    t1, t5, t_loop = (min(wall for wall, _ in runs[k]) for k in ("1", "5", "loop"))
    c1, c5, c_loop = (min(cpu for _, cpu in runs[k]) for k in ("1", "5", "loop"))
    flops, rate = update_flops(5, args.reward_model, device), matmul_rate(5, device)
    floor = flops / rate
    cpu = device.type == "cpu"  # CPU time is what a CPU update costs; on a GPU it only measures the launches
    loop_cost = c_loop if cpu else t_loop
    print(f"1 intention: {t1 * 1e3:.2f} ms/update   5 intentions: {t5 * 1e3:.2f} ms/update (batched)")
    print(f"5 intentions one after another: {t_loop * 1e3:.2f} ms/update -> batched/loop {t5 / t_loop:.2f}")
    print(
        f"5 intentions: {flops / 1e9:.2f} GFLOP of matmuls per update; at this machine's batched matmul rate "
        f"({rate / 1e9:.0f} GFLOP/s) that alone takes {floor * 1e3:.1f} ms, "
        f"{floor / loop_cost:.2f} of the loop's {'CPU ' if cpu else ''}time"
    )
    print(
        json.dumps(
            {
                "bench": "vpace_update",
                "metric": "update_time_ratio_batched_vs_loop_5_intentions",
                "value": round(t5 / t_loop, 3),
                "goal": 0.6,
                "higher_is_better": False,
                "ms_per_update_1": round(t1 * 1e3, 3),
                "ms_per_update_5_batched": round(t5 * 1e3, 3),
                "ms_per_update_5_loop": round(t_loop * 1e3, 3),
                "cpu_ms_per_update_1_5_loop": [round(c * 1e3, 3) for c in (c1, c5, c_loop)] if cpu else None,
                "cpu_time_ratio_batched_vs_loop": round(c5 / c_loop, 3) if cpu else None,
                # The floor: the update's matmuls at this machine's batched matmul rate, nothing else,
                # over the loop's (CPU) time: the best batched/loop ratio batching could reach here.
                "gflop_per_update_5": round(flops / 1e9, 3),
                "matmul_gflops": round(rate / 1e9, 1),
                "ms_matmul_floor_5": round(floor * 1e3, 2),
                "ratio_floor": round(floor / loop_cost, 3),
                "ratio_5_vs_1": round(t5 / t1, 3),
                "ratio_5_vs_1_goal": 2.5,
                # Batching saves per-operation latency, not arithmetic (nothing is shared between
                # intentions): 5 vs 1 says something only where latency dominates (a GPU).
                "ratio_5_vs_1_meaningful": device.type == "cuda",
                "naive_linear_ratio": 5.0,
                "reward_model": args.reward_model,
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
