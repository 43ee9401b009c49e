"""`force_match`: replay kinesthetic demonstrations so that the replay presses as the person did
(thesis §4.3.6, docs/force_matching.md).

Kinesthetic teaching records the sensor poses x_raw,t and the unscaled tactile wrench F~_raw,t.
Under an impedance controller a replay of x_raw alone loses the contact force, since the force
comes from the error between the commanded and the reached pose. Force matching offsets each
replayed pose by the displacement that the calibration says produces the recorded reading,

    x_rep,t = A^-1 (F~_raw,t - b) + x_raw,t,

in the sensor frame (translation (ex, ey, ez), rotation erz about the pad normal as a rotation
vector), with F~ median-filtered over time first. With a zero offset (zero force against a
calibration without offset) it is exactly position replay.

`execute = "sim"` replays the targets in the door-tactile simulator and writes the replay;
`execute = "plan"` writes them as a replay plan for a real robot instead: per demonstration, one
episode whose `action` at control step t is the target pose sent at that step and the STS mode
(`PLAN_ACTION_NAMES`), and whose metadata (`replay_plan`) holds the start pose to hold first. The
robot's recording of it becomes the training dataset through the `replay_join` stage
(docs/real_robot.md).
"""

from __future__ import annotations

import copy
import hashlib
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, override

import numpy as np

from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import ConfigError, DatasetError
from shiftkit.datasets.features import Features, vector_feature
from shiftkit.envs.geometry import matrix_to_quat_xyzw, quat_xyzw_to_matrix, rotation_from_vector
from shiftkit.pipelines.stage import Stage, register_stage
from shiftkit.transforms import papers
from shiftkit.transforms.force_calibration import WRENCH_AXES, Calibration, load_calibration, sensor_id

PLAN_ACTION_NAMES = ("x", "y", "z", "qx", "qy", "qz", "qw", "sts_mode")


def median_filter(values: np.ndarray, kernel: int) -> np.ndarray:
    """Running median over the first axis (odd `kernel`, edges repeat the end values)."""
    if kernel <= 1:
        return np.asarray(values, dtype=np.float64).copy()
    half = kernel // 2
    padded = np.concatenate([np.repeat(values[:1], half, 0), values, np.repeat(values[-1:], half, 0)])
    windows = np.lib.stride_tricks.sliding_window_view(padded, kernel, axis=0)
    return np.median(windows, axis=-1)


def force_matched_poses(
    ee_pose: np.ndarray, wrench: np.ndarray, calibration: Calibration, median_kernel: int = 5
) -> np.ndarray:
    """x_rep for (T, 7) poses (position, quaternion xyzw; sensor frame = the pose's frame) and
    (T, 4) raw readings (Fx, Fy, Fz, tau_z): each pose moved by the calibrated displacement of its
    median-filtered reading, expressed in its own sensor frame."""
    ee_pose = np.asarray(ee_pose, dtype=np.float64)
    offset = calibration.displacement(median_filter(np.asarray(wrench, dtype=np.float64), median_kernel))
    rot = quat_xyzw_to_matrix(ee_pose[:, 3:7])
    pos = ee_pose[:, :3] + np.einsum("tij,tj->ti", rot, offset[:, :3])
    # q_raw * (rotation by erz about the sensor z), as a quaternion product: exact for erz = 0
    x, y, z, w = ee_pose[:, 3:7].T
    s, c = np.sin(offset[:, 3] / 2), np.cos(offset[:, 3] / 2)
    quat = np.stack([x * c + y * s, y * c - x * s, z * c + w * s, w * c - z * s], axis=1)
    return np.concatenate([pos, quat], axis=1)


# ----------------------------------------------------------------------------- replay in the simulator
REPLAY_SECONDS = 60.0  # time limit of a replay per unit of slowdown (the recording's own limit is shorter)


def final_pose(pose: np.ndarray, action: np.ndarray) -> np.ndarray:
    """The door-tactile pose reached by `action` (the relative pose change in the sensor frame,
    scaled as the env scales it) from `pose`: the recording's last action closes its pose sequence."""
    from shiftkit.envs.door_tactile.env import MAX_ROTATION, MAX_TRANSLATION

    rot = quat_xyzw_to_matrix(pose[3:7])
    pos = pose[:3] + rot @ (np.asarray(action[:3], np.float64) * MAX_TRANSLATION)
    turned = rot @ rotation_from_vector(np.asarray(action[3:6], np.float64) * MAX_ROTATION)
    return np.concatenate([pos, matrix_to_quat_xyzw(turned)])


def interpolate_poses(poses: np.ndarray, factor: int) -> np.ndarray:
    """`factor` - 1 poses between consecutive ones (positions linear, quaternions normalised linear:
    the steps are small); the last pose stays last."""
    if factor == 1:
        return poses
    a = (np.arange(factor) / factor)[None, :, None]
    inner = ((1 - a) * poses[:-1, None] + a * poses[1:, None]).reshape(-1, poses.shape[1])
    inner[:, 3:7] /= np.linalg.norm(inner[:, 3:7], axis=1, keepdims=True)
    return np.concatenate([inner, poses[-1:]])


@dataclass
class ForceMatchConfig:
    """Parameters of `force_match`."""

    calibration: str | None = None
    """Calibration file (`shiftkit calibrate`); needed for mode "force_matched"."""
    mode: Literal["force_matched", "position"] = "force_matched"
    """"force_matched": replay x_rep = A^-1 (F~_raw - b) + x_raw; "position": replay x_raw (the
    baseline that loses the contact force)."""
    env: str = "door-tactile"
    """Simulator environment the episodes were recorded in (its family replays them)."""
    median_kernel: int = 5
    """Frames of the running median over F~_raw before it is inverted (odd; 1 = none)."""
    axes: list[str] = field(default_factory=lambda: ["Fx", "Fy", "Fz"])
    """Wrench axes whose calibrated displacement offsets the replay (the others stay at x_raw)."""
    sts_images: bool = True
    """Record both STS images (visual and tactile) of every replayed frame, replacing the recorded
    active-mode image `observation.images.sts` (a `mode_label` stage then keeps one); False replays
    that active-mode image (the mode of the recording's labels)."""
    drop_failed: bool = False
    """Drop episodes whose replay does not succeed."""
    slowdown: int = 1
    """Control steps per recorded frame: the replay runs this many times slower than the
    demonstration (targets interpolated), so the output has that many times more frames. The
    impedance controller's damping resists fast motion that a person's freedrive does not."""
    hold_steps: int = 10
    """Steps the last target is held after the demonstration's end (a door may still be moving);
    they are part of the output."""
    damping_time: float = 0.0
    """Velocity feed-forward (s, force_matched only; not in the thesis): x_rep also moves by
    damping_time * v_raw, the pose error the replay controller's damping D needs at the recorded
    velocity (about D / K: 0.25 s replays the door-tactile demonstrations best, docs/force_matching.md).
    0 = the static model F = K e."""
    execute: Literal["sim", "plan"] = "sim"
    """"sim": replay in the simulator and write the replay; "plan": write the replay targets as a
    plan a real robot executes (`action` = target pose x, y, z, qx, qy, qz, qw in the recording's
    base frame + STS mode, one per control step; `replay_plan` metadata with the start pose), whose
    recording the `replay_join` stage turns into the training dataset."""

    def __post_init__(self) -> None:
        if self.slowdown < 1 or self.hold_steps < 0 or self.damping_time < 0:
            raise ValueError("need slowdown >= 1, hold_steps >= 0 and damping_time >= 0")
        if self.median_kernel < 1 or self.median_kernel % 2 == 0:
            raise ValueError(f"median_kernel must be odd and >= 1, got {self.median_kernel}")
        unknown = [a for a in self.axes if a not in WRENCH_AXES]
        if unknown:
            raise ValueError(f"unknown wrench axes {unknown}; known: {', '.join(WRENCH_AXES)}")
        if self.mode == "force_matched" and not self.calibration:
            raise ValueError('mode "force_matched" needs a calibration file')
        if self.execute == "plan" and self.drop_failed:
            raise ValueError('drop_failed needs execute = "sim" (a plan has not run yet)')


# what the replay produces for a recorded feature (cameras are handled apart)
REPLAYED = (
    "action",
    "observation.state",
    "observation.environment_state",
    "next.success",
    "sim.qpos",
    "sim.qvel",
    "observation.ee_pose",
    "observation.wrench",
    "contact_wrench",
)


@register_stage
class ForceMatch(Stage):
    """Replays kinesthetic episodes in the simulator with the force-matched (or plain position) offset and records the replay."""

    name = "force_match"
    version = 1
    citation = papers.FORCE_MATCHING
    # position mode replays the demonstration's contacts in the simulator without a calibration file
    example_params = {"mode": "position", "hold_steps": 2}
    example_input = "door-kinesthetic"
    Config = ForceMatchConfig

    def _family(self) -> Any:
        from shiftkit.envs import env_family

        try:
            return env_family(self.config.env)
        except ValueError as exc:
            raise ConfigError(f"force_match: {exc}") from None

    @override
    def transform_features(self, features: Features) -> Features:
        from shiftkit.envs.door_tactile.lab import CAMERA_PREFIX, STS_IMAGE, STS_TACTILE, STS_VISUAL

        family = self._family()
        for key in ("observation.ee_pose", "observation.wrench"):
            if key not in features:
                raise ConfigError(f"force_match: needs the kinesthetic recording's {key!r} feature")
        dims = features.get("action", {}).get("shape", (0,))[0]
        # the family's action, or without its mode dim (recorded in a fixed sensor mode)
        if dims not in (len(family.action_names), len(family.action_names) - 1):
            raise ConfigError(f"force_match: 'action' has {dims} dims, not {self.config.env}'s {family.action_names}")
        cameras = []
        for key in features:
            cam = key[len(CAMERA_PREFIX) :] if key.startswith(CAMERA_PREFIX) else None
            if cam is not None and cam != "sts" and cam in family.cameras:
                cameras.append(cam)
            elif key not in REPLAYED and key != STS_IMAGE:
                raise ConfigError(f"force_match: cannot replay feature {key!r}; drop it before this stage")
        self._cameras = tuple(cameras)
        self._sts = "none" if STS_IMAGE not in features else "both" if self.config.sts_images else "active"
        self._image_shape = next(
            (tuple(features[k]["shape"]) for k in (*(CAMERA_PREFIX + c for c in cameras), STS_IMAGE) if k in features),
            None,
        )
        if self.config.mode == "force_matched":
            load_calibration(self.config.calibration, sensor_id(family.sim_model_id))
        if self.config.execute == "plan":
            return {"action": vector_feature("float64", list(PLAN_ACTION_NAMES))}
        out = dict(features)
        if self._sts == "both":
            del out[STS_IMAGE]
            for key in (STS_VISUAL, STS_TACTILE):
                out[key] = copy.deepcopy(features[STS_IMAGE])
        return out

    @override
    def describe(self) -> dict[str, Any]:
        """The parameters and the calibration file's content digest: a calibration re-made at the
        same path is another job (an interrupted run's parts are not resumed with it) and the
        provenance records which calibration made the dataset."""
        out = super().describe()
        if self.config.mode == "force_matched":
            out["calibration_sha256"] = hashlib.sha256(Path(self.config.calibration).read_bytes()).hexdigest()[:16]
        return out

    @override
    def setup(self) -> None:
        self._envs: dict[str, Any] = {}
        family = self._family()
        self._calibration = (
            load_calibration(self.config.calibration, sensor_id(family.sim_model_id))
            if self.config.mode == "force_matched"
            else None
        )

    def _env(self, task: str, image_shape: tuple[int, ...] | None) -> Any:
        from shiftkit.envs import make

        if task not in self._envs:
            kwargs = {} if image_shape is None else {"height": image_shape[0], "width": image_shape[1]}
            # a demonstration may use the env's whole time limit; its replay lasts `slowdown` times longer
            kwargs["max_episode_seconds"] = REPLAY_SECONDS * self.config.slowdown + self.config.hold_steps
            self._envs[task] = make(self.config.env, task, **kwargs)
        return self._envs[task]

    def targets(self, episode: Episode) -> np.ndarray:
        """The replay's T + 1 target poses: x_raw (closed by the pose the last recorded action
        reached), or x_rep from the calibration (the last reading standing in for the closing pose's)."""
        poses = np.asarray(episode.frames["observation.ee_pose"], dtype=np.float64)
        poses = np.concatenate([poses, final_pose(poses[-1], np.asarray(episode.frames["action"][-1]))[None]])
        if self._calibration is None:
            return poses
        wrench = np.asarray(episode.frames["observation.wrench"], dtype=np.float64)
        keep = np.array([a in self.config.axes for a in WRENCH_AXES])
        # unmatched axes read as their offset b: zero displacement
        offsets = np.array([self._calibration.axes[a].offset for a in WRENCH_AXES])
        wrench = np.where(keep, np.concatenate([wrench, wrench[-1:]]), offsets)
        targets = force_matched_poses(poses, wrench, self._calibration, self.config.median_kernel)
        if self.config.damping_time > 0 and len(poses) > 1:
            velocity = np.gradient(poses[:, :3], axis=0) * self.context.fps
            targets[:, :3] += self.config.damping_time * velocity
        return targets

    @override
    def process(self, episode: Episode, rng: np.random.Generator) -> Iterable[Episode]:
        from shiftkit.envs.door_tactile.lab import STS_TACTILE, STS_VISUAL, replay_targets

        meta = episode.meta
        where = f"force_match: episode {meta.get('source_episode_index', '?')}"
        if meta.get("seed") is None:
            raise DatasetError(f"{where}: no simulator 'seed' in the episode metadata to replay from")
        family = self._family()
        if meta.get("sim_model") not in (None, family.sim_model_id):
            raise DatasetError(f"{where}: recorded in {meta.get('sim_model')!r}, not {family.sim_model_id!r}")
        task = str(meta.get("task") or episode.frames["task"][0])
        action = np.asarray(episode.frames["action"])
        # the operator's mode labels of the recording (the family's last action dim), else tactile
        modes = action[:, -1] if action.shape[1] == len(family.action_names) else np.ones(len(action))
        k = self.config.slowdown
        targets, modes = interpolate_poses(self.targets(episode), k), np.repeat(modes, k)
        warmup = int(meta.get("recording_start_step", 0))
        out_meta = {
            **meta,
            "replay_mode": self.config.mode,
            "replay_slowdown": k,
            # recorded frame indices become replay frame indices
            "recorded_first_contact_step": meta.get("first_contact_step"),
        }
        if meta.get("mode_switch_step") is not None:
            out_meta["mode_switch_step"] = int(meta["mode_switch_step"]) * k
        # replay frame t re-enacts recorded frame t // k: the frame it stands for
        stands_for = lambda n: episode.origin()[np.minimum(np.arange(n) // k, len(episode) - 1)]  # noqa: E731
        tasks = lambda n: np.asarray(episode.frames["task"])[np.minimum(np.arange(n) // k, len(episode) - 1)]  # noqa: E731
        if self.config.execute == "plan":
            plan = self._plan(targets, modes, warmup, tasks, out_meta)
            plan.source_frames = stands_for(len(plan))
            yield plan
            return
        replay = replay_targets(
            self._env(task, self._image_shape),
            int(meta["seed"]),
            targets,
            modes,
            warmup,
            self._cameras,
            self._sts,
            self.config.hold_steps,
        )
        drop = self.config.drop_failed and not replay.success
        self.report("replays_failed", int(not replay.success))
        self.report("episodes_dropped", int(drop))
        if drop:
            return
        n = len(replay.frames["action"])
        frames = {k: replay.frames[k].astype(episode.frames[k].dtype) for k in episode.frames if k in replay.frames}
        frames["action"] = frames["action"][:, : action.shape[1]]  # a fixed-mode recording has no mode dim
        if self._sts == "both":
            frames[STS_VISUAL], frames[STS_TACTILE] = replay.frames[STS_VISUAL], replay.frames[STS_TACTILE]
        frames["timestamp"] = np.arange(n, dtype=np.float64) / self.context.fps
        frames["task"] = tasks(n)
        out_meta.update(
            outcome="success" if replay.success else "failure",
            replay_success=replay.success,
            first_contact_step=replay.first_contact_step,  # the replay's own first contact
        )
        yield Episode(frames, out_meta, stands_for(n))

    @override
    def carried_features(self, features: Features) -> dict[str, str]:
        return {"task": "task"}  # a replay records every feature anew

    def _plan(self, targets: np.ndarray, modes: np.ndarray, warmup: int, tasks: Any, meta: dict) -> Episode:
        """The replay plan of one demonstration: action t = (target t + 1, mode t) for the T steps
        and the `hold_steps` after, the first target as the start pose to hold for `warmup` steps."""
        n = len(targets) - 1
        steps = np.arange(n + self.config.hold_steps)
        action = np.concatenate([targets[np.minimum(steps + 1, n)], modes[np.minimum(steps, n - 1), None]], axis=1)
        frames = {
            "action": action.astype(np.float64),
            "timestamp": steps.astype(np.float64) / self.context.fps,
            "task": tasks(len(steps)),
        }
        plan = {
            "env": self.config.env,
            "start_pose": [float(v) for v in targets[0]],
            "warmup_steps": warmup,
            # what the simulated robot records of it, as the in-simulator replay would
            "cameras": list(self._cameras),
            "sts_images": self._sts,
            "image_shape": list(self._image_shape) if self._image_shape else None,
        }
        meta = {k: v for k, v in meta.items() if k not in ("outcome", "first_contact_step")}
        return Episode(frames, {**meta, "replay_plan": plan})
