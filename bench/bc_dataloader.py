"""BC training throughput: batches read from a LeRobot dataset vs the same model fed from memory.

Both paths run the trainer's own update (`update_members` of `shiftkit.policies.trainers.bc.training`:
a 5-member ensemble, one batch of 64 per member and step) on the same dataset, in alternating rounds
of one run:
* `lerobot`: `FrameTable` + `Prefetcher` (what `shiftkit train bc` uses), reading the dataset files;
* `memory`: every frame preloaded as torch tensors, batches by tensor indexing (the upper bound).
For context it also times lerobot's own per-frame `LeRobotDataset` through a torch `DataLoader`.

The dataset is `--dataset` (a LeRobot dataset folder) or a synthetic one written with lerobot's
writer (59-dim observation split like Panda play: 18 robot + 41 object dims; 4-dim action).

    python bench/bc_dataloader.py [--quick] [--dataset DIR] [--steps N] [--threads 1]

Last line: {"bench": "bc_dataloader", "metric": "steps_per_s_ratio", "value": lerobot/memory, "goal": 0.8, ...}
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import _device  # bench/, beside this file

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402


def synthetic_dataset(root: Path, episodes: int, length: int, seed: int = 0) -> Path:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    rng = np.random.default_rng(seed)
    features = {
        "observation.state": {"dtype": "float32", "shape": (18,), "names": [f"robot_{i}" for i in range(18)]},
        "observation.environment_state": {
            "dtype": "float32",
            "shape": (41,),
            "names": [f"object_{i}" for i in range(41)],
        },
        "action": {"dtype": "float32", "shape": (4,), "names": ["dx", "dy", "dz", "grip"]},
    }
    ds = LeRobotDataset.create("bench/bc", fps=20, root=root, features=features, use_videos=False)
    mix = rng.normal(size=(59, 4)).astype(np.float32) / 8
    for _ in range(episodes):
        obs = np.cumsum(rng.normal(size=(length, 59)).astype(np.float32) * 0.1, axis=0)
        actions = np.tanh(obs @ mix)
        for t in range(length):
            ds.add_frame(
                {
                    "observation.state": obs[t, :18],
                    "observation.environment_state": obs[t, 18:],
                    "action": actions[t],
                    "task": "synthetic",
                }
            )
        ds.save_episode()
    ds.finalize()
    return root


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="small dataset and few steps (< 1 minute)")
    parser.add_argument("--dataset", help="LeRobot dataset folder (default: a synthetic one)")
    parser.add_argument("--steps", type=int, help="steps per path and round (default 300, quick 60)")
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds per path (default 3)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    tmp = tempfile.TemporaryDirectory(prefix="bench-bc-")
    os.environ.setdefault("HF_DATASETS_CACHE", str(Path(tmp.name) / "cache"))

    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from shiftkit.policies.bc_policy import BCPolicy, PolicySpec
    from shiftkit.policies.data import FrameTable, Prefetcher, epoch_batches
    from shiftkit.policies.trainers.bc.training import _merged_stats, update_members

    steps = args.steps or (60 if args.quick else 300)
    members, batch_size = 5, 64
    t0 = time.perf_counter()
    root = (
        Path(args.dataset)
        if args.dataset
        else synthetic_dataset(Path(tmp.name) / "ds", episodes=20 if args.quick else 100, length=100)
    )
    write_s = time.perf_counter() - t0
    ds = LeRobotDataset("bench/bc", root=root)
    inputs = [
        k
        for k, ft in ds.meta.features.items()
        if k.startswith("observation.") and ft["dtype"] not in ("image", "video")
    ]
    keys = [*inputs, "action"]
    spec = PolicySpec(
        features={k: {f: ds.meta.features[k].get(f) for f in ("dtype", "shape", "names")} for k in inputs},
        action={f: ds.meta.features["action"].get(f) for f in ("dtype", "shape", "names")},
        stats=_merged_stats([ds], keys),
        encoder="cnn",
        num_keypoints=32,
        hidden=[512, 512],
        ensemble_size=members,
    )
    policy = BCPolicy(spec, seed=0)
    optimizers = [torch.optim.AdamW(m.parameters(), lr=1e-3, weight_decay=0.0) for m in policy.members]
    active = [True] * members

    table = FrameTable([ds], keys)
    n = table.num_frames
    memory = {k: torch.from_numpy(v) for k, v in table.gather(np.arange(n)).items()}

    def rows(epoch0: int, count: int):
        per_epoch = max(1, n // batch_size)
        for s in range(count):
            epoch, i = divmod(epoch0 * per_epoch + s, per_epoch)
            yield np.concatenate([epoch_batches(n, batch_size, 0, m, epoch)[i] for m in range(members)])

    def from_lerobot(round_: int) -> float:
        start = time.perf_counter()
        with Prefetcher(table, rows(round_, steps)) as batches:
            for batch in batches:
                update_members(policy, optimizers, batch, batch_size, active, 1e-3)
        return time.perf_counter() - start

    def from_memory(round_: int) -> float:
        start = time.perf_counter()
        for idx in rows(round_, steps):
            index = torch.from_numpy(idx)
            update_members(policy, optimizers, {k: v[index] for k, v in memory.items()}, batch_size, active, 1e-3)
        return time.perf_counter() - start

    from_memory(0)  # warm-up (allocator, lazy init)
    times = {"lerobot": 0.0, "memory": 0.0}
    for r in range(args.rounds):
        order = (
            (("lerobot", from_lerobot), ("memory", from_memory))
            if r % 2 == 0
            else (("memory", from_memory), ("lerobot", from_lerobot))
        )
        for name, fn in order:
            times[name] += fn(r + 1)
    rate = {k: args.rounds * steps / v for k, v in times.items()}

    # context: lerobot's per-frame reader through a torch DataLoader (main process, same batch size)
    loader = torch.utils.data.DataLoader(
        ds,
        batch_size=members * batch_size,
        shuffle=True,
        num_workers=0,
        generator=torch.Generator().manual_seed(0),
        drop_last=True,
    )
    ctx_steps, start = 0, time.perf_counter()
    for item in loader:
        batch = {k: item[k].float() for k in keys}
        update_members(policy, optimizers, batch, batch_size, active, 1e-3)
        ctx_steps += 1
        if ctx_steps >= max(5, steps // 10):
            break
    getitem_rate = ctx_steps / (time.perf_counter() - start)

    print(
        f"frames {n}, {members} members x batch {batch_size}, {args.rounds} rounds x {steps} steps, "
        f"threads {args.threads}"
    )
    print(f"  FrameTable + Prefetcher : {rate['lerobot']:7.1f} steps/s")
    print(f"  in-memory tensors       : {rate['memory']:7.1f} steps/s")
    print(f"  LeRobotDataset+DataLoader: {getitem_rate:7.1f} steps/s (context, {ctx_steps} steps)")
    print(
        json.dumps(
            {
                "bench": "bc_dataloader",
                "metric": "steps_per_s_ratio",
                "value": round(rate["lerobot"] / rate["memory"], 3),
                "goal": 0.8,
                "higher_is_better": True,
                "lerobot_steps_per_s": round(rate["lerobot"], 2),
                "memory_steps_per_s": round(rate["memory"], 2),
                "lerobot_getitem_dataloader_steps_per_s": round(getitem_rate, 2),
                "frames": n,
                "steps": args.rounds * steps,
                "members": members,
                "batch_size": batch_size,
                "threads": args.threads,
                # both paths train on the CPU: the bench compares data paths, not devices
                "device": "cpu",
                "gpu": _device.gpu_info(),
                "dataset": str(args.dataset or "synthetic"),
                "dataset_write_s": round(write_s, 2),
                "quick": args.quick,
            }
        )
    )


if __name__ == "__main__":
    main()
