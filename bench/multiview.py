"""Throughput of the `multiview` stage.

Measures, in one run, on the same recorded `mv-lift` episodes (fixed view, simulator state):
  * frames/s of the stage's `process` (IK + re-render RGB-D + re-expression + checks) against a
    bare loop over the same work: `mujoco.Renderer` (RGB and depth) on the same scene plus the same
    damped least-squares IK, nothing else (goal: stage / bare >= 0.8);
  * the whole pipeline (raw source -> multiview -> LeRobot dataset) with 2 workers against 1
    (goal: speed-up >= 1.6; it needs two free cores).
The last line printed is the JSON result; the headline metric is the stage / bare ratio.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402


def record(out: Path, episodes: int) -> Path:
    from shiftkit.pipelines.sources.simulator import CollectConfig, collect

    path, _ = collect(
        CollectConfig(env="mv-lift", task="lift", episodes=episodes, out=str(out), env_kwargs={"view": "fixed"})
    )
    return path


def bare(raw: Path, views: int) -> tuple[int, float]:
    """The same IK + RGB-D rendering with plain mujoco calls: frames and seconds."""
    from shiftkit.envs.base_pose import BasePose
    from shiftkit.envs.cameras import disable_costly_flags, scene_option
    from shiftkit.envs.multiview.physics import SAMPLER, MultiviewPhysics, rebase_state, rotation_z
    from shiftkit.pipelines.sources.raw import open_raw_dataset

    dataset = open_raw_dataset(raw)
    physics = MultiviewPhysics("mv-lift-v1", "lift", ("block",))
    model, data = physics.model, physics.data
    # the dataset-renderer setting the stage uses too (collision geometry, no shadows/reflections)
    option = scene_option("fast")
    rgb = mujoco.Renderer(model, 48, 64)
    depth = mujoco.Renderer(model, 48, 64)
    depth.enable_depth_rendering()
    frames, seconds = 0, 0.0
    for i in tqdm(range(dataset.num_episodes), desc="bare", leave=False):
        ep = dataset.read_episode(i)
        old = BasePose.from_dict(ep.meta["cameras"]["base"]["base_pose"])
        state = ep.frames["observation.state"].astype(np.float64)
        rng = np.random.default_rng(i)
        start = time.perf_counter()
        for _ in range(views):
            new = SAMPLER.sample(rng)
            physics.set_base_pose(new)
            rel = rotation_z(old.yaw - new.yaw)
            tcp = new.to_base(old.to_world(state[:, :3]))
            q_arm = ep.frames["sim.qpos"][0][physics.arm_qpos]
            for t in range(len(ep)):
                qpos, _ = rebase_state(physics, ep.frames["sim.qpos"][t], ep.frames["sim.qvel"][t], old, new)
                rot = np.zeros(9)
                quat = state[t, [6, 3, 4, 5]]
                mujoco.mju_quat2Mat(rot, quat)
                q_arm = physics.solve_arm(tcp[t], rel @ rot.reshape(3, 3), q_arm, 80 if t == 0 else 20)
                qpos[physics.arm_qpos] = q_arm
                data.qpos[:] = qpos
                mujoco.mj_kinematics(model, data)  # what rendering needs: body, geom and camera poses
                mujoco.mj_camlight(model, data)
                for renderer in (rgb, depth):
                    renderer.update_scene(data, camera="base", scene_option=option)
                    disable_costly_flags(renderer.scene)
                    renderer.render()
                frames += 1
        seconds += time.perf_counter() - start
    return frames, seconds


def stage(raw: Path, views: int) -> tuple[int, float]:
    """The stage's `process` on the same episodes: output frames and seconds."""
    from shiftkit.pipelines.sources.raw import open_raw_dataset
    from shiftkit.pipelines.stage import StageContext
    from shiftkit.transforms.multiview import Multiview, MultiviewConfig

    dataset = open_raw_dataset(raw)
    s = Multiview(MultiviewConfig(num_views=views, depth=True), StageContext(fps=10))
    s.setup()
    s.process(dataset.read_episode(0), np.random.default_rng(0))  # env built outside the timing
    frames, seconds = 0, 0.0
    for i in tqdm(range(dataset.num_episodes), desc="stage", leave=False):
        ep = dataset.read_episode(i)
        start = time.perf_counter()
        frames += sum(len(out) for out in s.process(ep, np.random.default_rng(i)))
        seconds += time.perf_counter() - start
    return frames, seconds


def pipeline(raw: Path, dest: Path, views: int, workers: int) -> float:
    from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, StageSpec
    from shiftkit.pipelines.runner import run_pipeline
    from shiftkit.pipelines.sources import SourceConfig

    config = PipelineConfig(
        sources=[SourceConfig(path=str(raw))],
        destination=DestinationConfig(root=str(dest)),
        stages=[StageSpec(name="multiview", params={"num_views": views})],
    )
    start = time.perf_counter()
    run_pipeline(config, workers=workers, progress=False)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="6 episodes, 2 views (about a minute)")
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--views", type=int, default=3)
    args = parser.parse_args()
    episodes, views = (6, 2) if args.quick else (args.episodes, args.views)
    with tempfile.TemporaryDirectory(prefix="bench-multiview-") as tmp:
        raw = record(Path(tmp) / "raw", episodes)
        bare_frames, bare_s = bare(raw, views)
        stage_frames, stage_s = stage(raw, views)
        one = pipeline(raw, Path(tmp) / "w1", views, 1)
        two = pipeline(raw, Path(tmp) / "w2", views, 2)
    bare_fps, stage_fps = bare_frames / bare_s, stage_frames / stage_s
    print(f"bare mujoco.Renderer + IK: {bare_fps:8.1f} frames/s ({bare_frames} frames)")
    print(f"multiview stage process:   {stage_fps:8.1f} frames/s ({stage_frames} frames)")
    print(f"pipeline, 1 worker: {one:.1f} s; 2 workers: {two:.1f} s (speed-up {one / two:.2f}x, {os.cpu_count()} CPUs)")
    print(
        json.dumps(
            {
                "bench": "multiview",
                "metric": "stage_vs_bare_frames_per_s",
                "value": round(stage_fps / bare_fps, 3),
                "goal": 0.8,
                "higher_is_better": True,
                "stage_frames_per_s": round(stage_fps, 1),
                "bare_frames_per_s": round(bare_fps, 1),
                "workers_speedup": round(one / two, 3),
                "workers_speedup_goal": 1.6,
                "pipeline_seconds": {"1": round(one, 2), "2": round(two, 2)},
                "episodes": episodes,
                "views": views,
                "frames": stage_frames,
                "cpus": os.cpu_count(),
            }
        )
    )


if __name__ == "__main__":
    main()
