"""What a simulated FIRE run writes of its episodes: one npz file per executed episode, read back as
the DAgger recording lerobot's strategy makes (`dagger_recording`), which offline FIRE
(`fire.aggregate`) turns into the aggregated dataset with the run's settings.
"""

from __future__ import annotations

import io
import json
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from shiftkit.datasets.episode import Episode
from shiftkit.policies.fire.aggregate import AggregateArgs
from shiftkit.policies.fire.config import FireArgs
from shiftkit.policies.fire.predictor import RULES


def save_npz(path: Path, arrays: dict[str, np.ndarray], meta: dict) -> None:
    """Write an episode's arrays and its metadata (JSON) atomically: a killed run leaves no partial file."""
    buf = io.BytesIO()
    np.savez(buf, __meta__=np.array(json.dumps(meta)), **arrays)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(buf.getvalue())
    os.replace(tmp, path)


def load_npz(path: Path) -> tuple[dict[str, np.ndarray], dict]:
    """An episode file's arrays and metadata (`save_npz`)."""
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files if k != "__meta__"}
        return arrays, json.loads(str(z["__meta__"]))


def recorded_episodes(episodes_dir: Path, fps: int, task: str) -> Iterator[Episode]:
    """The executed episodes as a DAgger recording holds them (every frame, in order)."""
    for path in sorted(episodes_dir.glob("episode_*.npz")):
        frames, _ = load_npz(path)
        n = len(frames["action"])
        frames["timestamp"] = (np.arange(n) / fps).astype(np.float32)
        frames["task"] = np.array([task] * n)
        yield Episode(frames)


def aggregate_args(args: FireArgs, rollouts: list[str], policy: str, out: Path) -> AggregateArgs:
    """The offline aggregation of a simulated run's recordings, with the run's settings."""
    return AggregateArgs(
        expert=args.dataset,
        root=args.root,
        rollouts=rollouts,
        out=str(out),
        repo_id=args.repo_id,
        policy=policy,
        predictor=args.predictor if args.predictor in RULES else "gda",
        seed=args.seed,
        d_hidden=list(args.d_hidden),
        d_lr=args.d_lr,
        grad_penalty=args.grad_penalty,
        beta=args.beta,
        gamma=args.gamma,
        fp_cooldown=args.fp_cooldown,
        device=args.device,
    )
