"""`shiftkit collect`: record scripted-expert episodes from a simulated env into the raw-episode
format (with simulator state for re-rendering/replay), or straight into a LeRobot dataset.

Frame t holds the observation before action t; `success[t]` (LeRobot `next.success`) is the
env's held success after action t. Reset-based episodes end once success holds (plus
`extra_steps`) or at the time limit; the outcome goes into the episode metadata. Play episodes
(`play=True`) chain the experts of a task sequence after one reset and label each segment.
The env family's observation is split into `state` (robot) and `environment_state` (objects) as
its registry entry says (panda-play: reference dims 0:12 + 53:59 and 12:53; docs/panda_play.md).
"""

from __future__ import annotations

import logging
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from shiftkit.pipelines.errors import ConfigError, ShiftkitError

log = logging.getLogger(__name__)


@dataclass
class CollectConfig:
    """What to record and where."""

    env: str = "panda-play"
    """Environment name (`shiftkit.envs.ENV_TASKS`)."""
    task: str = "lift"
    """Task; with `play`, the main task whose play sequence is recorded."""
    episodes: int = 10
    """Number of episodes."""
    seed: int = 0
    """Episode i is reset with seed `seed + i`."""
    out: str | None = None
    """Raw-episode output directory (must not exist)."""
    lerobot: str | None = None
    """Write a LeRobot dataset with this repo id instead (needs `root`)."""
    root: str | None = None
    """LeRobot dataset root directory (with `lerobot`)."""
    play: bool = False
    """Record play episodes: one reset, then the task's play sequence with segment labels."""
    control_hz: int | None = None
    """Control frequency; default: the env's first supported rate (panda-play: 20, or 5)."""
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    """Extra keyword arguments for the env constructor (e.g. `view="multiview"`)."""
    expert: str = "scripted"
    """How episodes are recorded: "scripted" (the task's expert) or a family's other recorder
    (e.g. "kinesthetic")."""
    cameras: tuple[str, ...] = ()
    """Cameras rendered every frame (e.g. "front"); empty = state only."""
    depth: bool = False
    """Also record depth images for each camera."""
    video: bool = False
    """Write camera features as lerobot videos (with `lerobot`); default: PNG images."""
    width: int = 64
    """Image width in pixels."""
    height: int = 48
    """Image height in pixels."""
    render_quality: str = "fast"
    """"fast" (collision geometry) or "full" (visual meshes)."""
    extra_steps: int = 0
    """Frames kept after success first holds (reset-based episodes)."""
    only_successful: bool = False
    """Skip failed episodes (their seeds are still consumed)."""
    sequence: tuple[str, ...] = field(default_factory=tuple)
    """Play sequence override; default `PLAY_SEQUENCES[task]`."""

    def validate(self) -> None:
        from shiftkit.envs import ENV_TASKS, env_family

        if self.env not in ENV_TASKS:
            raise ConfigError(f"unknown env {self.env!r}; known: {', '.join(ENV_TASKS)}")
        if self.task not in ENV_TASKS[self.env]:
            raise ConfigError(f"unknown task {self.task!r} for {self.env}; known: {', '.join(ENV_TASKS[self.env])}")
        family = env_family(self.env)
        if self.episodes < 1:
            raise ConfigError(f"--episodes must be >= 1, got {self.episodes}")
        if self.control_hz is None:
            self.control_hz = family.control_rates[0]
        if self.control_hz not in family.control_rates:
            rates = " or ".join(map(str, family.control_rates))
            raise ConfigError(f"--control-hz must be {rates} for {self.env}, got {self.control_hz}")
        if self.expert != "scripted" and self.expert not in family.experts:
            known = ", ".join(["scripted", *family.experts])
            raise ConfigError(f"unknown expert {self.expert!r} for {self.env}; known: {known}")
        if self.play and self.expert != "scripted":
            raise ConfigError("--play records scripted experts only")
        if (self.out is None) == (self.lerobot is None):
            raise ConfigError("give exactly one of --out DIR (raw episodes) or --lerobot REPO_ID --root DIR")
        if self.lerobot is not None and self.root is None:
            raise ConfigError("--lerobot needs --root DIR")
        if self.video and self.lerobot is None:
            raise ConfigError("--video applies to LeRobot output (--lerobot REPO_ID --root DIR)")
        target = Path(self.out if self.out is not None else self.root)
        if target.exists():
            raise ConfigError(f"output directory already exists: {target}")
        if self.play and family.play_rollout is None:
            raise ConfigError(f"env {self.env} records no play episodes")
        if self.play and not self.sequence and self.task not in family.play_sequences:
            raise ConfigError(f"no play sequence for task {self.task!r}; known: {', '.join(family.play_sequences)}")
        for cam in self.cameras:
            if cam not in family.cameras:
                raise ConfigError(f"unknown camera {cam!r}; known: {', '.join(family.cameras)}")
        if self.render_quality not in ("fast", "full"):
            raise ConfigError(f"render quality must be 'fast' or 'full', got {self.render_quality!r}")


def _write_raw(config: CollectConfig, out_dir: Path) -> dict[str, int]:
    from shiftkit.envs import env_family, make
    from shiftkit.envs.cameras import camera_intrinsics
    from shiftkit.pipelines.sources.raw import RawDatasetWriter

    family = env_family(config.env)
    state_idx, env_idx = family.state_indices, family.environment_state_indices
    record = family.rollout if config.expert == "scripted" else family.experts[config.expert]
    env = make(
        config.env,
        config.task,
        **config.env_kwargs,
        control_hz=config.control_hz,
        width=config.width,
        height=config.height,
        render_quality=config.render_quality,
    )
    names = {
        "state": [family.observation_names[i] for i in state_idx],
        "environment_state": [family.observation_names[i] for i in env_idx],
        "action": list(family.action_names),
    }
    info = {
        "observation_layout": family.observation_layout,
        "control_hz": config.control_hz,
        "cameras": {
            c: {"intrinsics": camera_intrinsics(env.physics.model, c, config.width, config.height)}
            for c in config.cameras
        },
    }
    counts = {"episodes": 0, "successes": 0, "skipped": 0}
    sequence = tuple(config.sequence) or family.play_sequences.get(config.task, ())
    with RawDatasetWriter(
        out_dir, fps=config.control_hz, robot=family.robot, env=config.env, names=names, info=info
    ) as writer:
        for i in range(config.episodes):
            seed = config.seed + i
            if config.play:
                r = family.play_rollout(env, seed, sequence, cameras=config.cameras, depth=config.depth)
                ok = all(s["success"] for s in r.segments)
                task = f"play: {', '.join(sequence)}"
            else:
                r = record(env, seed, cameras=config.cameras, depth=config.depth, extra_steps=config.extra_steps)
                ok = r.succeeded
                task = config.task
            log.info("episode %d (seed %d): %s, %d frames", i, seed, "success" if ok else "failure", len(r.actions))
            if config.only_successful and not ok:
                counts["skipped"] += 1
                continue
            t = len(r.actions)
            writer.add_episode(
                arrays={
                    "timestamp": np.arange(t, dtype=np.float64) / config.control_hz,
                    "action": r.actions,
                    "state": r.observations[:, state_idx],
                    "environment_state": r.observations[:, env_idx],
                    "success": r.success,
                    "sim_qpos": r.qpos,
                    "sim_qvel": r.qvel,
                    **r.arrays,
                },
                images=r.images or None,
                depth=r.depth or None,
                meta={
                    "task": task,
                    "outcome": "success" if ok else "failure",
                    "seed": seed,
                    "sim_model": family.sim_model_id,
                    "segments": r.segments,
                    "control_hz": config.control_hz,
                    **r.meta,
                },
            )
            counts["episodes"] += 1
            counts["successes"] += int(ok)
    env.close()
    if counts["episodes"] == 0:
        raise ShiftkitError("no episode was kept (all failed with --only-successful)")
    return counts


def collect(config: CollectConfig) -> tuple[Path, dict[str, int]]:
    """Record the episodes; returns the written directory and counts."""
    config.validate()
    if config.out is not None:
        out = Path(config.out)
        return out, _write_raw(config, out)
    from shiftkit.pipelines.lerobot_io import write_raw_as_lerobot

    root = Path(config.root)
    tmp = Path(tempfile.mkdtemp(prefix=".collect-", dir=root.parent if root.parent.exists() else None))
    try:
        raw = tmp / "raw"
        counts = _write_raw(config, raw)
        return write_raw_as_lerobot(raw, config.lerobot, root, video=config.video), counts
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
