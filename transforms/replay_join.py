"""`replay_join`: turn a robot's recording of a force-matched replay plan into the training dataset
(docs/real_robot.md).

A replay plan (`force_match` with `execute = "plan"`) sends, at control step t, a target sensor
pose and the STS mode. The recording a lab's logger keeps of it holds, per frame, that sent
`action` (x, y, z, qx, qy, qz, qw, sts_mode), the measured sensor pose `observation.ee_pose` and
whatever else the robot observes. The join replaces the sent action by the env's action, the
target's relative pose from the measured one, scaled and clipped as the env scales it, with the
mode label: what the in-simulator replay (`execute = "sim"`) records, so a `mode_label` stage and
the trainers take the joined dataset as they take that one.

`execute_replay_plan` is the simulated lab: the door-tactile arm executes a plan and records it
in the raw format, as a real arm's logger would.
"""

from __future__ import annotations

import copy
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, override

import numpy as np

from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import ConfigError, DatasetError
from shiftkit.datasets.features import Features
from shiftkit.envs.geometry import quat_xyzw_to_matrix
from shiftkit.pipelines.stage import FrameStage, register_stage
from shiftkit.transforms import papers
from shiftkit.transforms.force_matching import PLAN_ACTION_NAMES

POSE = "observation.ee_pose"


@dataclass
class ReplayJoinConfig:
    """Parameters of `replay_join`."""

    env: str = "door-tactile"
    """Environment whose action convention (relative pose in the sensor frame, its scale) the
    joined `action` follows."""


@register_stage
class ReplayJoin(FrameStage):
    """Replaces a recorded replay plan's sent action by the env's relative-pose action (from the measured pose) plus the mode label."""

    name = "replay_join"
    version = 1
    citation = papers.FORCE_MATCHING
    example_params = {"env": "door-tactile"}
    example_input = "door-replay"
    Config = ReplayJoinConfig

    @override
    def transform_features(self, features: Features) -> Features:
        from shiftkit.envs import env_family

        try:
            family = env_family(self.config.env)
        except ValueError as exc:
            raise ConfigError(f"replay_join: {exc}") from None
        action = features.get("action")
        if action is None or tuple(action["shape"]) != (len(PLAN_ACTION_NAMES),):
            raise ConfigError(
                f"replay_join: 'action' must be the replay plan's sent target ({', '.join(PLAN_ACTION_NAMES)}), "
                f"got shape {None if action is None else tuple(action['shape'])}"
            )
        if POSE not in features or tuple(features[POSE]["shape"]) != (7,):
            raise ConfigError(f"replay_join: needs the measured sensor pose {POSE!r} (x, y, z, qx, qy, qz, qw)")
        if list(family.action_names[-1:]) != ["sts_mode"]:
            raise ConfigError(f"replay_join: env {self.config.env!r} has no STS mode action")
        out = dict(features)
        names = list(family.action_names)
        out["action"] = {**copy.deepcopy(action), "dtype": "float32", "shape": (len(names),), "names": names}
        return out

    @override
    def process(self, episode: Episode, rng: np.random.Generator) -> Iterable[Episode]:
        from shiftkit.envs.door_tactile.experts import relative_action

        where = f"replay_join: episode {episode.meta.get('source_episode_index', '?')}"
        sent = np.asarray(episode.frames["action"], dtype=np.float64)
        pose = np.asarray(episode.frames[POSE], dtype=np.float64)
        for name, values in (("action", sent), (POSE, pose)):
            if not np.isfinite(values).all():
                raise DatasetError(f"{where}: {name!r} contains NaN/inf")
        rot, target_rot = quat_xyzw_to_matrix(pose[:, 3:7]), quat_xyzw_to_matrix(sent[:, 3:7])
        action = np.array(
            [
                np.append(relative_action(p[:3], r, s[:3], tr), s[7] > 0.5)
                for p, r, s, tr in zip(pose, rot, sent, target_rot, strict=True)
            ],
            dtype=np.float32,
        )
        yield episode.with_frames(action=action)


# ----------------------------------------------------------------------------- the simulated lab
def execute_replay_plan(plan: str | Path, out: str | Path) -> dict[str, int]:
    """The door-tactile arm executes every episode of a replay plan (LeRobot dataset): reset with
    the demonstration's seed, hold the plan's start pose for its warmup steps, then send action t
    at step t; its logger records the sent action, the measured pose, raw wrench, state, simulator
    state and the cameras the plan asks for, in the raw format. Returns episode and success counts."""
    from shiftkit.datasets.sources import SourceConfig, open_source
    from shiftkit.datasets.sources.raw import RawDatasetWriter
    from shiftkit.envs import env_family, make
    from shiftkit.envs.door_tactile.lab import CAMERA_PREFIX, replay_targets

    source = open_source(SourceConfig(path=str(plan)))
    names = list((source.features.get("action") or {}).get("names") or [])
    if names != list(PLAN_ACTION_NAMES):
        raise DatasetError(f"{plan}: not a replay plan ('action' must be {', '.join(PLAN_ACTION_NAMES)}, got {names})")
    counts = {"episodes": 0, "successes": 0}
    writer: RawDatasetWriter | None = None
    envs: dict[tuple, Any] = {}
    try:
        for group in source.episode_groups():
            for episode in source.iter_episodes(group):
                spec = episode.meta.get("replay_plan")
                if not isinstance(spec, dict) or "start_pose" not in spec:
                    raise DatasetError(f"{plan}: episode {group} has no 'replay_plan' metadata (start pose)")
                family = env_family(spec["env"])
                shape = spec.get("image_shape") or (48, 64)
                task = str(episode.meta.get("task") or episode.frames["task"][0])
                sent = np.asarray(episode.frames["action"], dtype=np.float64)
                key = (spec["env"], task, tuple(shape))
                if key not in envs:
                    envs[key] = make(spec["env"], task, height=shape[0], width=shape[1], max_episode_seconds=1e6)
                replay = replay_targets(
                    envs[key],
                    int(episode.meta["seed"]),
                    np.concatenate([[spec["start_pose"]], sent[:, :7]]),
                    sent[:, 7],
                    int(spec.get("warmup_steps", 0)),
                    tuple(spec.get("cameras", ())),
                    spec.get("sts_images", "none"),
                )
                f = replay.frames
                if writer is None:
                    writer = RawDatasetWriter(
                        out,
                        fps=source.fps,
                        robot=family.robot,
                        env=spec["env"],
                        names={
                            "action": list(PLAN_ACTION_NAMES),
                            "state": [family.observation_names[i] for i in family.state_indices],
                            "environment_state": [
                                family.observation_names[i] for i in family.environment_state_indices
                            ],
                        },
                        info={"replay_plan": str(plan)},
                    ).__enter__()
                n = len(f["target"])
                writer.add_episode(
                    arrays={
                        "timestamp": np.arange(n, dtype=np.float64) / source.fps,
                        "action": f["target"],
                        "ee_pose": f["observation.ee_pose"],
                        "wrench_raw": f["observation.wrench"],
                        "state": f["observation.state"].astype(np.float32),
                        "environment_state": f["observation.environment_state"].astype(np.float32),
                        "sim_qpos": f["sim.qpos"],
                        "sim_qvel": f["sim.qvel"],
                        "success": f["next.success"],
                    },
                    images={k[len(CAMERA_PREFIX) :]: v for k, v in f.items() if k.startswith(CAMERA_PREFIX)},
                    meta={
                        **{k: v for k, v in episode.meta.items() if k != "source_episode_index"},
                        "outcome": "success" if replay.success else "failure",
                        "replay_success": replay.success,
                        "first_contact_step": replay.first_contact_step,
                    },
                )
                counts["episodes"] += 1
                counts["successes"] += int(replay.success)
    except BaseException as exc:
        if writer is not None:
            writer.__exit__(type(exc), exc, exc.__traceback__)
        raise
    finally:
        for env in envs.values():
            env.close()
    if writer is None:
        raise DatasetError(f"{plan}: the plan has no episodes")
    writer.__exit__(None, None, None)
    return counts
