"""Small shared helpers for tests."""

from __future__ import annotations

import hashlib
from pathlib import Path


def tree_hashes(root: Path) -> dict[str, str]:
    """sha256 of every file below `root`, by relative path."""
    return {
        p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(Path(root).rglob("*"))
        if p.is_file()
    }


# A small ACT (CPU, offline: no pretrained backbone) that lerobot-train runs in seconds.
SMALL_ACT = (
    "--policy.type=act",
    "--policy.pretrained_backbone_weights=null",
    "--policy.chunk_size=4",
    "--policy.n_action_steps=4",
    "--policy.dim_model=64",
    "--policy.dim_feedforward=128",
)


def lerobot_train_two_steps(repo_id: str, root: Path, output_dir: Path, policy_args=SMALL_ACT) -> None:
    """Run lerobot's own trainer (`lerobot-train` beside this Python) for 2 steps on the dataset at
    `root` and check it got there."""
    import os
    import subprocess
    import sys

    exe = Path(sys.executable).with_name("lerobot-train")
    args = [
        *policy_args,
        f"--dataset.repo_id={repo_id}",
        f"--dataset.root={root}",
        "--dataset.video_backend=pyav",
        "--steps=2",
        "--batch_size=2",
        "--num_workers=0",
        "--policy.device=cpu",
        "--policy.push_to_hub=false",
        "--wandb.enable=false",
        "--save_checkpoint=false",
        "--eval_freq=0",
        "--log_freq=1",
        f"--output_dir={output_dir}",
    ]
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    out = subprocess.run([str(exe), *args], capture_output=True, text=True, env=env, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "step:2" in out.stdout + out.stderr


def write_raw_as_lerobot(raw_dir: Path, repo_id: str, root: Path) -> Path:
    """A raw-episode directory as a LeRobot dataset at `root` (a pipeline with no stages)."""
    from shiftkit.pipelines.config import DestinationConfig, PipelineConfig
    from shiftkit.pipelines.runner import run_pipeline
    from shiftkit.pipelines.sources import SourceConfig

    config = PipelineConfig(
        sources=[SourceConfig(path=str(Path(raw_dir).resolve()))],
        destination=DestinationConfig(root=str(Path(root).resolve()), repo_id=repo_id),
    )
    return run_pipeline(config, progress=False)
