"""Cost of one VPACE update with 5 intentions vs 1 intention (same run, same machine).

All intentions are stacked into batched matmuls, so adding tasks costs much less than linearly where
an update is bound by per-operation latency (a GPU). Nothing is shared between tasks, so the arithmetic
itself grows linearly, and on a CPU, where it dominates, the ratio stays near 4 (docs/vpace.md).
Panda-sized problem: 59-dim observations, 4-dim actions, 256x256 networks, 128 replay + 128 example rows.
Prints one JSON line last: {"bench": "vpace_update", "metric": "update_time_ratio_5_vs_1", ...}.
"""

from __future__ import annotations

import argparse
import json
import time

import gymnasium as gym
import numpy as np
import torch

from shiftkit.policies.replay import ReplayBuffer
from shiftkit.policies.vpace import Agent, VPACEArgs

OBS_DIM, ACT_DIM = 59, 4


def time_updates(num_tasks: int, updates: int, warmup: int, reward_model: str, device: torch.device) -> float:
    """Seconds per update for an agent with `num_tasks` intentions."""
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    aux = [f"aux{i}" for i in range(num_tasks - 1)]
    args = VPACEArgs.for_variant("vpace", main_task="main", aux_tasks=aux, reward_model=reward_model)
    agent = Agent(args, OBS_DIM, gym.spaces.Box(-1.0, 1.0, (ACT_DIM,), np.float32), device)
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
    for i in range(warmup):
        agent.update(batches[i % 8][0], batches[i % 8][1], None)
    if device.type == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    for i in range(updates):
        agent.update(batches[i % 8][0], batches[i % 8][1], None)
    if device.type == "cuda":
        torch.cuda.synchronize()
    return (time.perf_counter() - start) / updates


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="few updates (well under a minute)")
    parser.add_argument("--updates", type=int, default=300, help="timed updates per configuration")
    parser.add_argument("--reward-model", default="sqil", choices=["sqil", "dac"])
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--device", default="auto")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    device = torch.device(
        "cuda"
        if args.device == "auto" and torch.cuda.is_available()
        else ("cpu" if args.device == "auto" else args.device)
    )
    updates, warmup = (40, 5) if args.quick else (args.updates, 20)
    # Interleave the two configurations so machine load drifts affect both alike; keep each one's best.
    one, five = [], []
    for _ in range(3):
        one.append(time_updates(1, updates, warmup, args.reward_model, device))
        five.append(time_updates(5, updates, warmup, args.reward_model, device))
    t1, t5 = min(one), min(five)
    print(f"1 intention: {t1 * 1e3:.2f} ms/update   5 intentions: {t5 * 1e3:.2f} ms/update")
    print(
        json.dumps(
            {
                "bench": "vpace_update",
                "metric": "update_time_ratio_5_vs_1",
                "value": round(t5 / t1, 3),
                "goal": 2.5,
                "higher_is_better": False,
                "ms_per_update_1": round(t1 * 1e3, 3),
                "ms_per_update_5": round(t5 * 1e3, 3),
                "naive_linear_ratio": 5.0,
                "reward_model": args.reward_model,
                "device": str(device),
                "threads": args.threads,
                "updates": updates,
            }
        )
    )


if __name__ == "__main__":
    main()
