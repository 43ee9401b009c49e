"""Small shared helpers for tests."""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
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


# A small diffusion policy (a 2-level U-Net, 10 noise steps), as offline as SMALL_ACT; group norm,
# since batch norm fails on the 1x1 maps small test images leave after the ResNet trunk.
SMALL_DIFFUSION = (
    "--policy.type=diffusion",
    "--policy.pretrained_backbone_weights=null",
    "--policy.use_group_norm=true",
    "--policy.crop_shape=null",
    "--policy.down_dims=[32,64]",
    "--policy.horizon=8",
    "--policy.n_action_steps=4",
    "--policy.num_train_timesteps=10",
)


def lerobot_train_two_steps(repo_id: str, root: Path, output_dir: Path, policy_args=SMALL_ACT) -> None:
    """Run lerobot's own trainer (`lerobot-train` beside this Python) for 2 steps on the dataset at
    `root` and check it got there."""
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
        "--env_eval_freq=0",
        "--log_freq=1",
        f"--output_dir={output_dir}",
    ]
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    out = subprocess.run([str(exe), *args], capture_output=True, text=True, env=env, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "step:2" in out.stdout + out.stderr


def write_raw_as_lerobot(raw_dir: Path, repo_id: str, root: Path) -> Path:
    """A raw-episode directory as a LeRobot dataset at `root` (a pipeline with no stages)."""
    from shiftkit.datasets.sources import SourceConfig
    from shiftkit.pipelines.config import DestinationConfig, PipelineConfig
    from shiftkit.pipelines.runner import run_pipeline

    config = PipelineConfig(
        sources=[SourceConfig(path=str(Path(raw_dir).resolve()))],
        destination=DestinationConfig(root=str(Path(root).resolve()), repo_id=repo_id),
    )
    return run_pipeline(config, progress=False)


# ----------------------------------------------------------------------------- killing runs
def shiftkit_process(*args: str, cwd: Path) -> subprocess.Popen:
    """`shiftkit ARGS` in a child process with its own session (process group), so that killing it
    does not take the test down."""
    return subprocess.Popen(
        [sys.executable, "-m", "shiftkit.app.cli", *args],
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )


def child_pids(pid: int) -> set[int]:
    """The direct children of `pid` (read from /proc: cheap enough to poll every few ms)."""
    import psutil

    try:
        return {c.pid for c in psutil.Process(pid).children()}
    except psutil.NoSuchProcess:
        return set()


def alive(pid: int) -> bool:
    """Whether a process exists and is not a zombie."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    stat = Path(f"/proc/{pid}/stat")
    return not (stat.exists() and stat.read_text().split(")")[-1].split()[0] == "Z")


def survivors(pids: set[int], within: float = 15.0, poll: float = 0.2) -> list[int]:
    """The processes of `pids` still alive after waiting up to `within` seconds for them to end."""
    deadline = time.monotonic() + within
    while any(alive(p) for p in pids) and time.monotonic() < deadline:
        time.sleep(poll)
    return sorted(p for p in pids if alive(p))


def sigkill_when(proc: subprocess.Popen, ready: Callable[[], bool], group: bool = False) -> set[int] | None:
    """SIGKILL `proc` (its whole process group with `group`) as soon as `ready()` holds while it
    runs; returns the pids of the children seen until then, or None if it ended first."""
    workers: set[int] = set()
    while proc.poll() is None:
        workers |= child_pids(proc.pid)
        if ready():
            (os.killpg if group else os.kill)(proc.pid, signal.SIGKILL)
            proc.wait()
            return workers
        time.sleep(0.005)
    return None


def finished_parts(destination: Path) -> int:
    """Episodes a run on `destination` has transformed so far (its work directory's parts)."""
    from shiftkit.pipelines.work import PART_SUFFIX, work_dir_for

    parts = work_dir_for(Path(destination)) / "parts"
    return len(list(parts.glob(f"*.{PART_SUFFIX}"))) if parts.is_dir() else 0


def dataset_bytes(root: Path) -> dict[str, str]:
    """`tree_hashes` of a dataset without the files that name how it was run (provenance, card)."""
    return {k: v for k, v in tree_hashes(root).items() if k not in ("meta/shiftkit_provenance.json", "README.md")}
