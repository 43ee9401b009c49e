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

import itertools
import logging
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from shiftkit.datasets.dataclass_config import check_fields, option
from shiftkit.datasets.errors import ConfigError, ShiftkitError
from shiftkit.datasets.staging import remove_dead_staging

log = logging.getLogger(__name__)


@dataclass
class CollectConfig:
    """What to record and where."""

    env: str = "panda-play"
    """Environment name (`shiftkit.envs.ENV_TASKS`)."""
    task: str = "lift"
    """Task, e.g. lift, stack, insert; with `play`, the main task whose play sequence is recorded."""
    episodes: int = option(10, rule="positive_int")
    """Number of episodes."""
    seed: int = option(0, rule="non_negative_int")
    """Episode i is reset with seed `seed + i`."""
    out: str | None = None
    """Raw-episode output directory (must not exist)."""
    lerobot: str | None = None
    """Write a LeRobot dataset with this repo id instead (needs `root`)."""
    root: str | None = None
    """LeRobot dataset root directory (with `lerobot`)."""
    play: bool = False
    """Record play episodes: one reset, then the task's play sequence with segment labels."""
    control_hz: int | None = option(None, rule="positive_int")
    """Control frequency; default: the env's first supported rate (panda-play: 20, or 5)."""
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    """Extra keyword arguments for the env constructor (e.g. `view="multiview"`)."""
    expert: str = "scripted"
    """How episodes are recorded: "scripted" (the task's expert) or a family's other recorder
    (e.g. "kinesthetic"; panda-play "suboptimal": the scripted expert with a person's variance)."""
    cameras: tuple[str, ...] = ()
    """Cameras rendered every frame (e.g. "front"); empty = state only."""
    depth: bool = False
    """Also record depth images for each camera."""
    video: bool = False
    """Write camera features as lerobot videos (with `lerobot`); default: PNG images."""
    width: int = option(64, rule="positive_int")
    """Image width in pixels."""
    height: int = option(48, rule="positive_int")
    """Image height in pixels."""
    render_quality: Literal["fast", "full"] = "fast"
    """Geometry shown: "fast" (collision geometry) or "full" (visual meshes)."""
    extra_steps: int = option(0, rule="non_negative_int")
    """Frames kept after success first holds (reset-based episodes)."""
    only_successful: bool = False
    """Skip failed episodes (their seeds are still consumed)."""
    sequence: tuple[str, ...] = field(default_factory=tuple)
    """Play sequence override; default `PLAY_SEQUENCES[task]`."""

    def validate(self) -> None:
        """Check the options against the registered envs and tasks (`ConfigError` on a bad one) and fill in `control_hz`
        from the env family."""
        from shiftkit.envs import ENV_TASKS, env_family

        if self.env not in ENV_TASKS:
            raise ConfigError(f"unknown env {self.env!r}; known: {', '.join(ENV_TASKS)}")
        if self.task not in ENV_TASKS[self.env]:
            raise ConfigError(f"unknown task {self.task!r} for {self.env}; known: {', '.join(ENV_TASKS[self.env])}")
        family = env_family(self.env)
        check_fields(self)
        if self.lerobot is not None:
            from shiftkit.datasets.hub import validate_repo_id

            validate_repo_id(self.lerobot)
        if self.root is not None:
            from shiftkit.pipelines.runner import check_writable_name

            check_writable_name(Path(self.root))
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
        unknown = [t for t in self.sequence if t not in ENV_TASKS[self.env]]
        if unknown:
            raise ConfigError(f"unknown task {unknown[0]!r} in --sequence; known: {', '.join(ENV_TASKS[self.env])}")
        for cam in self.cameras:
            if cam not in family.cameras:
                raise ConfigError(f"unknown camera {cam!r}; known: {', '.join(family.cameras)}")
        if self.render_quality not in ("fast", "full"):
            raise ConfigError(f"render quality must be 'fast' or 'full', got {self.render_quality!r}")


@dataclass
class _Recording:
    """The episodes of one `collect`, recorded as they are consumed, in the raw format's terms
    (`RawDatasetWriter.add_episode`'s arguments); `counts` grows as they are."""

    config: CollectConfig
    names: dict[str, list[str]]
    info: dict[str, Any]
    robot: str
    counts: dict[str, Any] = field(default_factory=lambda: {"episodes": 0, "successes": 0, "skipped": 0, "seeds": []})

    def episodes(self, env: Any, family: Any, progress: bool) -> Iterator[dict[str, Any]]:
        from tqdm import tqdm

        config, counts = self.config, self.counts
        state_idx, env_idx = family.state_indices, family.environment_state_indices
        record = family.rollout if config.expert == "scripted" else family.experts[config.expert]
        sequence = tuple(config.sequence) or family.play_sequences.get(config.task, ())
        with tqdm(total=config.episodes, desc="collect", unit="ep", disable=not progress, leave=False) as bar:
            for i in range(config.episodes):
                if i:
                    bar.update(1)
                    bar.set_postfix(success=f"{(counts['successes']) / i:.0%}")
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
                yield {
                    "arrays": {
                        "timestamp": np.arange(t, dtype=np.float64) / config.control_hz,
                        "action": r.actions,
                        "state": r.observations[:, state_idx],
                        "environment_state": r.observations[:, env_idx],
                        "success": r.success,
                        "sim_qpos": r.qpos,
                        "sim_qvel": r.qvel,
                        **r.arrays,
                    },
                    "images": r.images or None,
                    "depth": r.depth or None,
                    "meta": {
                        "task": task,
                        "outcome": "success" if ok else "failure",
                        "seed": seed,
                        "sim_model": family.sim_model_id,
                        "segments": r.segments,
                        "control_hz": config.control_hz,
                        **r.meta,
                    },
                }
                counts["episodes"] += 1
                counts["successes"] += int(ok)
                counts["seeds"].append(seed)
            bar.update(1)


def _open_env(config: CollectConfig) -> tuple[Any, Any, _Recording]:
    from shiftkit.envs import env_family, make
    from shiftkit.envs.cameras import camera_intrinsics

    family = env_family(config.env)
    try:
        env = make(
            config.env,
            config.task,
            **config.env_kwargs,
            control_hz=config.control_hz,
            width=config.width,
            height=config.height,
            render_quality=config.render_quality,
        )
    except (TypeError, ValueError) as exc:  # a keyword the constructor does not take, or a bad value
        raise ConfigError(f"--env-kwarg for {config.env}: {exc}") from None
    names = {
        "state": [family.observation_names[i] for i in family.state_indices],
        "environment_state": [family.observation_names[i] for i in family.environment_state_indices],
        "action": list(env.action_names),  # an --env-kwarg may change the action (door-tactile sensor_mode)
    }
    info = {
        "observation_layout": family.observation_layout,
        "control_hz": config.control_hz,
        "cameras": {
            c: {"intrinsics": camera_intrinsics(env.physics.model, c, config.width, config.height)}
            for c in config.cameras
        },
    }
    return env, family, _Recording(config, names, info, family.robot)


def collect(config: CollectConfig, progress: bool = False) -> tuple[Path, dict[str, Any]]:
    """Record the episodes; returns the written directory and counts (`seeds`: those kept).
    `progress` shows a bar with the success rate so far."""
    if config.out is not None or config.root is not None:
        # Before validating: a dead recorder's leftovers go even when this run is then refused.
        remove_dead_staging(Path(config.out if config.out is not None else config.root))
    config.validate()
    target = Path(config.out if config.out is not None else config.root)
    env, family, recording = _open_env(config)
    try:
        episodes = recording.episodes(env, family, progress)
        if config.out is not None:
            _write_raw(recording, episodes, target)
        else:
            _write_lerobot(recording, episodes, target)
    finally:
        env.close()
    return target, recording.counts


def _write_raw(recording: _Recording, episodes: Iterator[dict[str, Any]], out_dir: Path) -> None:
    from shiftkit.datasets.sources.raw import RawDatasetWriter

    config = recording.config
    with RawDatasetWriter(
        out_dir,
        fps=config.control_hz,
        robot=recording.robot,
        env=config.env,
        names=recording.names,
        info=recording.info,
    ) as writer:
        for episode in episodes:
            writer.add_episode(**episode)
        _check_kept(recording)


def _write_lerobot(recording: _Recording, episodes: Iterator[dict[str, Any]], root: Path) -> None:
    """Straight into the dataset, each episode converted as the raw reader would read it back
    (so the dataset equals recording raw episodes and importing them), without writing them."""
    import json

    from shiftkit.datasets.features import plain_camera_features
    from shiftkit.datasets.jsonutil import dumps
    from shiftkit.datasets.sources.raw import raw_episode, raw_features, validate_arrays
    from shiftkit.datasets.writer import write_episodes

    config = recording.config

    def converted(i: int, episode: dict[str, Any]):
        arrays = {k: np.asarray(v) for k, v in episode["arrays"].items()}
        validate_arrays(arrays, f"episode {i}")
        meta = json.loads(dumps(episode["meta"]))  # what a JSON round trip through meta.json gives
        return raw_episode(
            arrays, episode["images"] or {}, episode["depth"] or {}, meta, i, recording.info["cameras"], f"episode {i}"
        )

    first = next(episodes, None)
    if first is None:
        _check_kept(recording)
    first_episode = converted(0, first)
    features = raw_features(first["arrays"], first["images"] or {}, first["depth"] or {}, recording.names, "collect")
    if config.video:
        features = plain_camera_features(features, "video")
    rest = (converted(i, e) for i, e in enumerate(episodes, start=1))
    write_episodes(
        config.lerobot,
        root,
        config.control_hz,
        features,
        itertools.chain([first_episode], rest),
        robot_type=recording.robot or None,
        # `seeds` fills as the episodes are written, before the provenance is made from it
        sources=[{"kind": "simulator", "env": config.env, "task": config.task, "seeds": recording.counts["seeds"]}],
        importer={"name": "collect", **{k: v for k, v in asdict(config).items() if k not in ("out", "root")}},
        seed=config.seed,
    )


def _check_kept(recording: _Recording) -> None:
    if recording.counts["episodes"] == 0:
        raise ShiftkitError("no episode was kept (all failed with --only-successful)")
