"""Throughput of the `multiview` stage.

Measures, in one run, on the same recorded `mv-lift` episodes (fixed view, simulator state):
  * frames/s of the stage's `process` (IK + re-render RGB-D + re-expression + checks) against a
    bare loop over the same work: `mujoco.Renderer` (RGB and depth) on the same scene plus the same
    damped least-squares IK, nothing else (goal: stage / bare >= 0.8);
  * the whole pipeline (raw source -> multiview -> LeRobot dataset) with 2 workers against 1
    (goal: speed-up >= 1.6; it needs two free cores). Start-up is measured apart and not inside
    either run: the writer's imports (lerobot, torch; paid once by every `shiftkit run`, done
    before both runs) and the start of a 2-process pool with the stage set up (inside the 2-worker
    run, also reported without it).
The load average is reported with the figures (a shared machine makes them noisy). The last line
printed is the JSON result; the headline metric is the stage / bare ratio.
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


def _config(raw: Path, dest: Path, views: int):
    from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, StageSpec
    from shiftkit.pipelines.sources import SourceConfig

    return PipelineConfig(
        sources=[SourceConfig(path=str(raw))],
        destination=DestinationConfig(root=str(dest)),
        stages=[StageSpec(name="multiview", params={"num_views": views})],
    )


def pipeline(raw: Path, dest: Path, views: int, workers: int) -> float:
    from shiftkit.pipelines.runner import run_pipeline

    start = time.perf_counter()
    run_pipeline(_config(raw, dest, views), workers=workers, progress=False)
    return time.perf_counter() - start


def writer_imports() -> float:
    """Seconds to import what the writer needs (lerobot pulls in torch): once per `shiftkit run`."""
    start = time.perf_counter()
    import lerobot.datasets.lerobot_dataset  # noqa: F401

    return time.perf_counter() - start


def _ready(_: int) -> int:
    time.sleep(0.5)  # long enough that each of the pool's processes takes one
    return os.getpid()


def pool_startup(raw: Path, dest: Path, views: int, workers: int) -> float:
    """Seconds until a spawned pool like the local executor's has every worker set up (imports,
    plan, stage setup)."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from shiftkit.pipelines import runner

    start = time.perf_counter()
    ctx = multiprocessing.get_context("spawn")
    config = _config(raw, dest, views)
    with ProcessPoolExecutor(workers, mp_context=ctx, initializer=runner.init_worker, initargs=(config,)) as pool:
        pids = set(pool.map(_ready, range(workers)))
        seconds = time.perf_counter() - start - 0.5
    if len(pids) != workers:
        raise RuntimeError(f"{workers} tasks ran in {len(pids)} processes: the pool did not start them all")
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="16 episodes, 2 views (about a minute)")
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--views", type=int, default=3)
    args = parser.parse_args()
    episodes, views = (16, 2) if args.quick else (args.episodes, args.views)
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="bench-multiview-") as tmp:
        raw = record(Path(tmp) / "raw", episodes)
        bare_frames, bare_s = bare(raw, views)
        stage_frames, stage_s = stage(raw, views)
        imports = writer_imports()
        startup = pool_startup(raw, Path(tmp) / "s", views, 2)
        one = pipeline(raw, Path(tmp) / "w1", views, 1)
        two = pipeline(raw, Path(tmp) / "w2", views, 2)
    load_after = os.getloadavg()[0]
    bare_fps, stage_fps = bare_frames / bare_s, stage_frames / stage_s
    print(f"bare mujoco.Renderer + IK: {bare_fps:8.1f} frames/s ({bare_frames} frames)")
    print(f"multiview stage process:   {stage_fps:8.1f} frames/s ({stage_frames} frames)")
    print(f"start-up: writer imports {imports:.1f} s (once per run); 2-worker pool ready {startup:.1f} s")
    print(
        f"pipeline, 1 worker: {one:.1f} s; 2 workers: {two:.1f} s (speed-up {one / two:.2f}x; "
        f"{one / (two - startup):.2f}x without the pool start-up; {os.cpu_count()} CPUs, "
        f"load average {load_before:.1f} -> {load_after:.1f})"
    )
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
                "workers_speedup_without_pool_startup": round(one / (two - startup), 3),
                "pipeline_seconds": {"1": round(one, 2), "2": round(two, 2)},
                "startup_seconds": {"writer_imports": round(imports, 2), "pool_2_workers": round(startup, 2)},
                "episodes": episodes,
                "views": views,
                "frames": stage_frames,
                "cpus": os.cpu_count(),
                "load_average": [round(load_before, 2), round(load_after, 2)],
            }
        )
    )


if __name__ == "__main__":
    main()
