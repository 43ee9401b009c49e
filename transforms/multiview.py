"""`multiview`: re-render simulator-recorded episodes from new mobile-base poses (thesis ch. 3, docs/multiview.md).

Input: episodes of a multiview env (`mv-lift`, `mv-stack`, `mv-pick-insert`, `mv-door`, any view)
recorded with simulator state (`sim.qpos`, `sim.qvel`) and the per-episode camera metadata that
`shiftkit collect` writes (`meta["cameras"]["base"]["base_pose"]`). For each episode the stage
samples `num_views` base poses with the thesis' sampler (seeded from the episode's rng) and, per
pose:

1. moves the free objects so that they keep their world poses (`rebase_state`);
2. solves the arm joints frame by frame (MuJoCo-Jacobian damped least squares, warm-started from
   the previous frame) so that the tool follows the recorded *world* trajectory, position and
   orientation;
3. re-renders RGB (and depth) from the base camera at the new pose;
4. re-expresses `observation.state` (tool pose; fingers unchanged), `observation.environment_state`
   (object poses, from the rebased state) and the actions (velocities, rotated by the yaw change) in
   the new base frame, and writes the new base pose into `meta["cameras"]` (the camera-metadata
   contract; intrinsics and camera-in-base extrinsics do not change).

A view is dropped when IK misses the recorded tool pose (`max_ik_error`, `max_ik_rotation`) or an
object leaves the image; each drop is logged and counted in each output episode's
`meta["multiview"]`, and the stage reports (`Stage.report`) views kept, views dropped per reason
and source episodes left without any view, for the run summary and the provenance. `matched =
true` emits exactly one view per episode (the first of up to `num_views` sampled poses that
works), so a multiview dataset built from the same demonstrations has the same episodes and frames
as the fixed-view one (docs/multiview.md).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, Literal, override

import numpy as np

from shiftkit.datasets.depth import as_metres, clean_metres, depth_feature, depth_unit, is_depth
from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import ConfigError, DatasetError
from shiftkit.datasets.features import Features, image_feature

# the rig and geometry load without MuJoCo; the scene is imported by the methods that render it
from shiftkit.envs.base_pose import CAMERA_NAME, SAMPLER, BasePose
from shiftkit.envs.geometry import matrix_to_quat_xyzw, quat_xyzw_to_matrix, rotation_z
from shiftkit.pipelines.stage import FrameStage, register_stage
from shiftkit.transforms import papers

log = logging.getLogger(__name__)

REQUIRED = ("sim.qpos", "sim.qvel", "observation.state", "action")
IMAGE_KEY = f"observation.images.{CAMERA_NAME}"
DEPTH_KEY = f"observation.depth.{CAMERA_NAME}"
# TCP pose in the family's observation.state: position 0:3, xyzw quaternion 3:7, fingers after
STATE_POS, STATE_QUAT = slice(0, 3), slice(3, 7)


@dataclass
class MultiviewConfig:
    """Parameters of `multiview`."""

    num_views: int = 3
    """Base poses sampled per episode (with `matched`: poses tried until one works)."""
    yaw_range: tuple[float, float] = SAMPLER.yaw_range
    """Base yaw interval (rad) sampled uniformly; the envs' training range is (-0.6, 0.2)."""
    xy_noise: float = SAMPLER.xy_noise
    """Half-width of the uniform noise on base x, y (m)."""
    yaw_noise: float = SAMPLER.yaw_noise
    """Half-width of the uniform noise on base yaw (rad)."""
    distance: float = SAMPLER.distance
    """Camera-to-task-centre distance along the optical axis (m); the camera's height and tilt only
    reach the centre near the default (the sampler refuses others)."""
    matched: bool = False
    """One view per episode (equal-size fixed-view and multiview datasets from the same demos)."""
    keep_source: bool = False
    """Also emit the source episode unchanged (first), before its views."""
    depth: bool = True
    """Render depth (`observation.depth.base`) too, in metres as lerobot's native depth
    (`datasets.depth`; an input's own depth feature keeps its storage and unit)."""
    render_quality: Literal["fast", "full"] = "fast"
    """"fast" (collision geometry) or "full" (visual meshes)."""
    width: int = 64
    """Image width when the input has no base-camera images (else the input's)."""
    height: int = 48
    """Image height when the input has no base-camera images (else the input's)."""
    max_ik_error: float = 0.005
    """Largest tool position error (m) of the IK solution at any frame before the view is dropped."""
    max_ik_rotation: float = 0.05
    """Largest tool orientation error (rad) at any frame before the view is dropped."""
    ik_iterations: int = 20
    """IK iterations per frame (the first frame gets four times as many)."""

    def __post_init__(self) -> None:
        if self.num_views < 1:
            raise ValueError(f"num_views must be >= 1, got {self.num_views}")
        if self.max_ik_error <= 0 or self.max_ik_rotation <= 0 or self.ik_iterations < 1:
            raise ValueError("max_ik_error, max_ik_rotation and ik_iterations must be > 0")
        if self.width < 1 or self.height < 1:
            raise ValueError("width and height must be >= 1")
        self.yaw_range = tuple(self.yaw_range)
        self.sampler()  # the sampler checks range, noise and distance

    def sampler(self):
        """The base-pose sampler with this config's yaw range, noise and distance."""
        return dataclasses.replace(
            SAMPLER,
            yaw_range=self.yaw_range,
            xy_noise=self.xy_noise,
            yaw_noise=self.yaw_noise,
            distance=self.distance,
        )


def _project(points: np.ndarray, extrinsics: dict[str, Any], intrinsics: dict[str, float]) -> np.ndarray:
    """Pixel coordinates (u, v) and depth of base-frame points seen by a MuJoCo camera (x right, y up,
    looking along -z); depth <= 0 means behind the camera."""
    rot, pos = np.asarray(extrinsics["rotation"]), np.asarray(extrinsics["position"])
    cam = (np.asarray(points) - pos) @ rot
    depth = -cam[:, 2]
    safe = np.where(depth > 1e-6, depth, 1e-6)
    u = intrinsics["cx"] + intrinsics["fx"] * cam[:, 0] / safe
    v = intrinsics["cy"] - intrinsics["fy"] * cam[:, 1] / safe
    return np.stack([u, v, depth], axis=1)


def _place(physics, qpos: np.ndarray, qvel: np.ndarray) -> None:
    """Set a state for rendering: positions of bodies, geoms and cameras only (no dynamics)."""
    import mujoco

    physics.data.qpos[:] = qpos
    physics.data.qvel[:] = qvel
    mujoco.mj_kinematics(physics.model, physics.data)
    mujoco.mj_camlight(physics.model, physics.data)


@register_stage
class Multiview(FrameStage):
    """Re-renders each episode from `num_views` sampled mobile-base poses, the arm re-solved to follow the recorded world trajectory."""

    name = "multiview"
    version = 2  # 2: depth is native (H, W, 1) metres
    citation = papers.MULTIVIEW
    example_params = {"num_views": 2, "depth": True}
    example_input = "mv-lift"
    Config = MultiviewConfig

    @override
    def setup(self) -> None:
        self._envs: dict[str, Any] = {}
        self._sampler = self.config.sampler()

    @override
    def transform_features(self, features: Features) -> Features:
        missing = [k for k in REQUIRED if k not in features]
        if missing:
            raise ConfigError(
                f"multiview: input lacks {', '.join(missing)}; record with `shiftkit collect --env mv-...` "
                "(simulator state) and keep sim.qpos/sim.qvel through earlier stages"
            )
        out = dict(features)
        shape = tuple(features[IMAGE_KEY]["shape"]) if IMAGE_KEY in features else None
        h, w = (shape[0], shape[1]) if shape else (self.config.height, self.config.width)
        out[IMAGE_KEY] = image_feature((h, w, 3))
        source = features.get(DEPTH_KEY)
        if source is not None and is_depth(source):  # keep the input's storage (image / video) and unit
            out[DEPTH_KEY] = depth_feature(h, w, source["dtype"], depth_unit(source))
        elif source is not None or self.config.depth:  # re-rendered: older shiftkit depth becomes native
            out[DEPTH_KEY] = depth_feature(h, w)
        return out

    @override
    def carried_features(self, features: Features) -> dict[str, str]:
        # a view re-renders the cameras and re-expresses the state, action and objects in its base frame
        rewritten = {*REQUIRED, IMAGE_KEY, DEPTH_KEY, "observation.environment_state"}
        return {k: v for k, v in super().carried_features(features).items() if k not in rewritten}

    @staticmethod
    def _depth_frames(metres: list[np.ndarray]) -> np.ndarray:
        """Rendered depth as shiftkit holds depth: (T, H, W, 1) float32 metres."""
        return clean_metres(np.array(metres, dtype=np.float32))

    @staticmethod
    def _camera_meta(episode: Episode, entries: dict[str, Any]) -> dict[str, Any]:
        """The episode's cameras with `entries` set on the base camera (other entries kept; the
        grey-level range of older shiftkit depth dropped, since the re-rendered depth is metres)."""
        cameras = dict(episode.meta.get("cameras") or {})
        camera = {k: v for k, v in {**cameras.get(CAMERA_NAME, {}), **entries}.items() if k != "depth"}
        return {**cameras, CAMERA_NAME: camera}

    # ----------------------------------------------------------------- per episode
    def _env(self, sim_model: str, size: tuple[int, int]):
        from shiftkit.envs import make
        from shiftkit.envs.multiview.tasks import TASKS

        task = next((t for t in TASKS.values() if t.model_id == sim_model), None)
        if task is None:
            known = ", ".join(t.model_id for t in TASKS.values())
            raise DatasetError(f"multiview: episode recorded with sim model {sim_model!r}; needs one of {known}")
        key = f"{sim_model}:{size}"
        if key not in self._envs:
            self._envs[key] = make(
                task.env,
                task.name,
                view="fixed",
                width=size[1],
                height=size[0],
                render_quality=self.config.render_quality,
            )
        return self._envs[key]

    @override
    def process(self, episode: Episode, rng: np.random.Generator) -> Iterable[Episode]:
        if not hasattr(self, "_envs"):  # direct use without a runner
            self.setup()
        meta = episode.meta
        try:
            source_pose = BasePose.from_dict(meta["cameras"][CAMERA_NAME]["base_pose"])
        except (KeyError, TypeError) as exc:
            raise DatasetError(
                f"multiview: episode {meta.get('source_episode_index')} has no meta.cameras.{CAMERA_NAME}.base_pose "
                "(record it with `shiftkit collect --env mv-...`)"
            ) from exc
        image = episode.frames.get(IMAGE_KEY)
        size = tuple(image.shape[1:3]) if image is not None else (self.config.height, self.config.width)
        env = self._env(str(meta.get("sim_model")), size)
        if self.config.keep_source:
            yield self._source_copy(episode, env, size)
        dropped = {"ik": 0, "out_of_view": 0}
        made = []
        for _ in range(self.config.num_views):
            pose = self._sampler.sample(rng)
            result = self._render_view(episode, env, source_pose, pose)
            if isinstance(result, str):
                dropped[result] += 1
                log.warning(
                    "multiview: episode %s, base pose %s dropped (%s)",
                    meta.get("source_episode_index"),
                    pose.as_dict(),
                    "IK missed the recorded tool pose" if result == "ik" else "an object left the image",
                )
                continue
            made.append((pose, result))
            if self.config.matched:
                break
        self.report("views_kept", len(made))
        for reason, n in dropped.items():
            self.report(f"views_dropped_{reason}", n)
        self.report("episodes_without_views", int(not made))
        for k, (pose, frames) in enumerate(made):
            out_meta = dict(meta)
            out_meta["cameras"] = self._camera_meta(
                episode, {**env.camera_metadata()[CAMERA_NAME], "base_pose": pose.as_dict()}
            )
            out_meta["multiview"] = {
                "view": k,
                "source_base_pose": source_pose.as_dict(),
                "dropped_views": dict(dropped),
            }
            yield Episode({**episode.frames, **frames}, out_meta)

    def _source_copy(self, episode: Episode, env, size: tuple[int, int]) -> Episode:
        """The source episode with the camera features the output schema has (rendered if absent)."""
        frames = dict(episode.frames)
        if DEPTH_KEY in frames:  # older shiftkit depth becomes metres, as the views' depth is
            frames[DEPTH_KEY] = as_metres(frames[DEPTH_KEY], episode.meta.get("cameras"), CAMERA_NAME)
        if IMAGE_KEY not in frames or (self.config.depth and DEPTH_KEY not in frames):
            pose = BasePose.from_dict(episode.meta["cameras"][CAMERA_NAME]["base_pose"])
            env.set_base_pose(pose)
            rgb, depth = self._render(env, episode.frames["sim.qpos"], episode.frames["sim.qvel"])
            frames.setdefault(IMAGE_KEY, rgb)
            if self.config.depth:
                frames.setdefault(DEPTH_KEY, self._depth_frames(depth))
        meta = dict(episode.meta)
        meta["cameras"] = self._camera_meta(episode, {})
        meta["multiview"] = {"view": "source"}
        return Episode(frames, meta)

    def _render(self, env, qpos: np.ndarray, qvel: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        """RGB frames and depth maps in metres at the given states."""
        rgb, depth = [], []
        for q, v in zip(qpos, qvel, strict=True):
            _place(env.physics, q, v)
            rgb.append(env.render_rgb())
            if self.config.depth:
                depth.append(env.render_depth())
        return np.array(rgb, dtype=np.uint8), depth

    def _render_view(self, episode: Episode, env, old: BasePose, new: BasePose) -> dict[str, np.ndarray] | str:
        """The re-rendered, re-expressed frames at base pose `new`, or the reason it was dropped."""
        from shiftkit.envs.multiview.physics import rebase_state

        cfg = self.config
        f = episode.frames
        with_depth = cfg.depth or DEPTH_KEY in f  # an input's depth is re-rendered too
        state = np.asarray(f["observation.state"], dtype=np.float64)
        rel = rotation_z(old.yaw - new.yaw)  # old base axes in the new base frame
        tcp = new.to_base(old.to_world(state[:, STATE_POS]))
        rots = rel @ quat_xyzw_to_matrix(state[:, STATE_QUAT])
        physics = env.physics
        env.set_base_pose(new)
        qpos, qvel = [], []
        q_arm = np.asarray(f["sim.qpos"][0][physics.arm_qpos], dtype=np.float64)
        for t in range(len(episode)):
            q_new, v_new = rebase_state(physics, f["sim.qpos"][t], f["sim.qvel"][t], old, new)
            physics.data.qpos[:] = q_new
            iterations = cfg.ik_iterations * (4 if t == 0 else 1)
            q_arm = physics.solve_arm(tcp[t], rots[t], q_arm, iterations=iterations)
            pos_err, rot_err = physics.tcp_error(q_arm, tcp[t], rots[t])
            if pos_err > cfg.max_ik_error or rot_err > cfg.max_ik_rotation:
                return "ik"
            q_new[physics.arm_qpos] = q_arm
            v_new[physics.arm_dofs] = 0.0  # joint velocities of another arm posture are not recorded
            qpos.append(q_new)
            qvel.append(v_new)
        rgb, depth, env_state = [], [], []
        camera = env.camera_metadata()[CAMERA_NAME]
        h, w = camera["intrinsics"]["height"], camera["intrinsics"]["width"]
        for q, v in zip(qpos, qvel, strict=True):
            _place(physics, q, v)
            u, v_px, depth_m = _project(self._object_points(physics), camera["extrinsics"], camera["intrinsics"]).T
            if not np.all((depth_m > 0) & (u >= 0) & (u <= w - 1) & (v_px >= 0) & (v_px <= h - 1)):
                return "out_of_view"
            rgb.append(env.render_rgb())
            if with_depth:
                depth.append(env.render_depth())
            env_state.append(physics.object_state())
        new_state = state.copy()
        new_state[:, STATE_POS] = tcp
        new_state[:, STATE_QUAT] = matrix_to_quat_xyzw(rots)
        action = np.asarray(f["action"], dtype=np.float64).copy()
        action[:, 0:3] = action[:, 0:3] @ rel.T
        if action.shape[1] == 7:  # 6-DOF: the angular velocity turns with the base too
            action[:, 3:6] = action[:, 3:6] @ rel.T
        out = {
            "observation.state": new_state.astype(f["observation.state"].dtype),
            "action": action.astype(f["action"].dtype),
            "sim.qpos": np.array(qpos, dtype=f["sim.qpos"].dtype),
            "sim.qvel": np.array(qvel, dtype=f["sim.qvel"].dtype),
            IMAGE_KEY: np.array(rgb, dtype=np.uint8),
        }
        if "observation.environment_state" in f:
            out["observation.environment_state"] = np.array(env_state, dtype=f["observation.environment_state"].dtype)
        if with_depth:
            out[DEPTH_KEY] = self._depth_frames(depth)
        return out

    @staticmethod
    def _object_points(physics) -> np.ndarray:
        """Base-frame points that must stay in the image: the free objects, or the door handle."""
        points = [physics.object_pos(n) for n in physics.objects]
        if physics.door_qpos is not None:
            points.append(physics.handle_pos())
        return np.array(points)
