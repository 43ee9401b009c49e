"""Throughput of the `multiview` stage.

Measures, in one run, on the same recorded `mv-lift` episodes (fixed view, simulator state):
  * frames/s of the stage's `process` (IK + re-render RGB-D + re-expression + checks) against a
    bare loop over the same work: `mujoco.Renderer` (RGB and depth) on the same scene plus the same
    damped least-squares IK, nothing else (goal: stage / bare >= 0.8);
  * the stage's damped least-squares IK against mink's on the same targets (accuracy, ms/frame);
  * the whole pipeline (raw source -> multiview -> LeRobot dataset) with 2 workers against 1 (goal:
    speed-up >= 1.6 of the processing span; it needs two free cores), with each run's CPU seconds
    (its processes together). As in bench/executors.py, the pipeline is stamped (`bench/_timing.py`)
    so that start-up (the workers' spawn, imports and renderer set-up), the processing span and the
    write are reported apart, with what keeps the 2-worker span above half the 1-worker one; the
    whole run's speed-up is beside it. The writer's imports (lerobot, torch: a fresh `shiftkit run`
    pays them once, whatever its workers) are measured in a fresh process and done in this one
    before the runs, so neither run pays them.
The load average is reported with the figures (on a shared machine they are noisy). The last line
printed is the JSON result; the headline metric is the stage / bare ratio.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import _timing  # noqa: E402  (bench/, beside this file; registers the bench-stamp stage)
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402


def record(out: Path, episodes: int) -> Path:
    from shiftkit.app.collect import CollectConfig, collect

    path, _ = collect(
        CollectConfig(env="mv-lift", task="lift", episodes=episodes, out=str(out), env_kwargs={"view": "fixed"})
    )
    return path


def bare(raw: Path, views: int) -> Callable[[int], tuple[int, float]]:
    """The same IK + RGB-D rendering with plain mujoco calls: per episode, frames and seconds."""
    from shiftkit.datasets.sources.raw import open_raw_dataset
    from shiftkit.envs.base_pose import SAMPLER, BasePose
    from shiftkit.envs.cameras import disable_costly_flags, scene_option
    from shiftkit.envs.geometry import rotation_z
    from shiftkit.envs.multiview.physics import MultiviewPhysics, rebase_state

    dataset = open_raw_dataset(raw)
    physics = MultiviewPhysics("mv-lift-v1", "lift", ("block",))
    model, data = physics.model, physics.data
    # the dataset-renderer setting the stage uses too (collision geometry, no shadows/reflections)
    option = scene_option("fast")
    rgb = mujoco.Renderer(model, 48, 64)
    depth = mujoco.Renderer(model, 48, 64)
    depth.enable_depth_rendering()

    def episode(i: int) -> tuple[int, float]:
        ep = dataset.read_episode(i)
        old = BasePose.from_dict(ep.meta["cameras"]["base"]["base_pose"])
        state = ep.frames["observation.state"].astype(np.float64)
        rng = np.random.default_rng(i)
        frames, start = 0, time.perf_counter()
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
        return frames, time.perf_counter() - start

    return episode


def ik_targets(raw: Path, views: int, episodes: int):
    """Per (episode, view): the physics at the new base pose, the arm's start and the re-expressed
    TCP targets, as the stage computes them."""
    from shiftkit.datasets.sources.raw import open_raw_dataset
    from shiftkit.envs.base_pose import SAMPLER, BasePose
    from shiftkit.envs.geometry import quat_xyzw_to_matrix, rotation_z
    from shiftkit.envs.multiview.physics import MultiviewPhysics, rebase_state

    dataset = open_raw_dataset(raw)
    physics = MultiviewPhysics("mv-lift-v1", "lift", ("block",))
    for i in range(episodes):
        ep = dataset.read_episode(i)
        old = BasePose.from_dict(ep.meta["cameras"]["base"]["base_pose"])
        state = ep.frames["observation.state"].astype(np.float64)
        rng = np.random.default_rng(i)
        for _ in range(views):
            new = SAMPLER.sample(rng)
            physics.set_base_pose(new)
            rots = rotation_z(old.yaw - new.yaw) @ quat_xyzw_to_matrix(state[:, 3:7])
            tcp = new.to_base(old.to_world(state[:, :3]))
            qpos = [
                rebase_state(physics, q, v, old, new)[0]
                for q, v in zip(ep.frames["sim.qpos"], ep.frames["sim.qvel"], strict=True)
            ]
            yield physics, np.asarray(ep.frames["sim.qpos"][0][physics.arm_qpos], np.float64), tcp, rots, qpos


def ik_comparison(
    raw: Path, views: int, episodes: int, posture_cost: float = 1e-3, mink_iterations: tuple[int, int] = (10, 2)
) -> dict[str, dict[str, float]]:
    """The stage's damped least-squares IK (80 iterations on an episode's first frame, 20 after)
    against mink's (a QP over a frame task and a posture task, daqp solver; `mink_iterations`) on
    the same targets and warm starts: worst and median TCP position error (mm), worst rotation
    error (deg) and milliseconds per frame."""
    import mink

    from shiftkit.envs.multiview.physics import HOME_QPOS

    errors: dict[str, list[float]] = {"dls": [], "mink": []}
    rotation_errors: dict[str, list[float]] = {"dls": [], "mink": []}

    def keep(name: str, error: tuple[float, float]) -> None:
        errors[name].append(error[0])
        rotation_errors[name].append(error[1])

    seconds = {"dls": 0.0, "mink": 0.0}
    for physics, q0, tcp, rots, qpos in ik_targets(raw, views, episodes):
        config = mink.Configuration(physics.model)
        frame = mink.FrameTask("tcp", "site", position_cost=1.0, orientation_cost=1.0)
        posture = mink.PostureTask(physics.model, cost=posture_cost)
        limits = [mink.ConfigurationLimit(physics.model)]
        q_dls, q_mink = q0.copy(), q0.copy()
        for t in range(len(tcp)):
            iterations = 80 if t == 0 else 20
            physics.data.qpos[:] = qpos[t]
            start = time.perf_counter()
            q_dls = physics.solve_arm(tcp[t], rots[t], q_dls, iterations)
            seconds["dls"] += time.perf_counter() - start
            keep("dls", physics.tcp_error(q_dls, tcp[t], rots[t]))
            start = time.perf_counter()
            full = np.array(qpos[t], np.float64)
            full[physics.arm_qpos] = q_mink
            config.update(full)
            home = full.copy()
            home[physics.arm_qpos] = HOME_QPOS
            posture.set_target(home)
            frame.set_target(mink.SE3.from_rotation_and_translation(mink.SO3.from_matrix(rots[t]), tcp[t]))
            for _ in range(mink_iterations[t > 0]):
                velocity = mink.solve_ik(config, [frame, posture], 0.1, "daqp", damping=1e-4, limits=limits)
                config.integrate_inplace(velocity, 0.1)
            q_mink = config.q[physics.arm_qpos].copy()
            seconds["mink"] += time.perf_counter() - start
            keep("mink", physics.tcp_error(q_mink, tcp[t], rots[t]))
    frames = len(errors["dls"])
    return {
        name: {
            "worst_mm": round(1e3 * max(errors[name]), 4),
            "median_mm": round(1e3 * float(np.median(errors[name])), 4),
            "worst_rotation_deg": round(float(np.degrees(max(rotation_errors[name]))), 4),
            "ms_per_frame": round(1e3 * seconds[name] / frames, 3),
            "frames": frames,
        }
        for name in errors
    }


def stage(raw: Path, views: int) -> Callable[[int], tuple[int, float]]:
    """The stage's `process` on the same episodes: per episode, output frames and seconds."""
    from shiftkit.datasets.sources.raw import open_raw_dataset
    from shiftkit.pipelines.stage import StageContext
    from shiftkit.transforms.multiview import Multiview, MultiviewConfig

    dataset = open_raw_dataset(raw)
    s = Multiview(MultiviewConfig(num_views=views, depth=True), StageContext(fps=10))
    s.setup()
    s.process(dataset.read_episode(0), np.random.default_rng(0))  # env built outside the timing

    def episode(i: int) -> tuple[int, float]:
        ep = dataset.read_episode(i)
        start = time.perf_counter()
        frames = sum(len(out) for out in s.process(ep, np.random.default_rng(i)))
        return frames, time.perf_counter() - start

    return episode


def stage_vs_bare(raw: Path, views: int, episodes: int) -> tuple[tuple[int, float], tuple[int, float]]:
    """(frames, seconds) of the stage and of the bare loop, episode by episode in turn, so that a
    change in the machine's load affects both alike."""
    loops = (stage(raw, views), bare(raw, views))
    totals = [[0, 0.0], [0, 0.0]]
    for i in tqdm(range(episodes), desc="stage vs bare", leave=False):
        for total, loop in zip(totals, loops, strict=True):
            frames, seconds = loop(i)
            total[0] += frames
            total[1] += seconds
    return tuple(totals[0]), tuple(totals[1])


def _config(raw: Path, dest: Path, views: int):
    from shiftkit.datasets.sources import SourceConfig
    from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, StageSpec

    return PipelineConfig(
        sources=[SourceConfig(path=str(raw))],
        destination=DestinationConfig(root=str(dest)),
        stages=[StageSpec(name="multiview", params={"num_views": views})],
    )


def _cpu_seconds() -> float:
    usage = [resource.getrusage(who) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)]
    return sum(u.ru_utime + u.ru_stime for u in usage)


def pipeline(raw: Path, dest: Path, views: int, workers: int) -> dict[str, float]:
    """The stamped pipeline with N workers: its `_timing.breakdown` and the CPU seconds of its
    processes (this one and the pool's workers, counted once they have exited)."""
    config = _config(raw, dest, views)
    config.stages = _timing.stamped(config.stages)
    before = _cpu_seconds()
    times = _timing.timed_run(config, workers)
    return {**times, "cpu": _cpu_seconds() - before}


def writer_imports() -> float:
    """Seconds a fresh process takes to import what the writer needs (lerobot pulls in torch)."""
    code = (
        "import time; t = time.perf_counter(); import lerobot.datasets.lerobot_dataset; print(time.perf_counter() - t)"
    )
    return float(subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout)


def _init_and_wait(config, barrier) -> None:
    from shiftkit.pipelines import work

    work.init_worker(config)
    barrier.wait()  # returns once every worker of the pool is set up


def _pid(_: int) -> int:
    return os.getpid()


def pool_startup(raw: Path, dest: Path, views: int, workers: int) -> float:
    """Seconds until a spawned pool like the local executor's has every worker set up (interpreter,
    imports, plan, stage setup)."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    start = time.perf_counter()
    ctx = multiprocessing.get_context("spawn")
    args = (_config(raw, dest, views), ctx.Barrier(workers))
    with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_and_wait, initargs=args) as pool:
        list(pool.map(_pid, range(workers)))  # runs once every worker has passed the barrier
        return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument(
        "--quick", action="store_true", help="24 episodes x 3 views, the first 8 for stage vs bare (about a minute)"
    )
    parser.add_argument("--episodes", type=int, default=60, help="episodes of the pipeline runs")
    parser.add_argument("--stage-episodes", type=int, default=20, help="episodes of the stage vs bare loop")
    parser.add_argument("--views", type=int, default=3)
    args = parser.parse_args()
    episodes, stage_episodes, views = (24, 8, 3) if args.quick else (args.episodes, args.stage_episodes, args.views)
    stage_episodes = min(stage_episodes, episodes)
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="bench-multiview-") as tmp:
        raw = record(Path(tmp) / "raw", episodes)
        (stage_frames, stage_s), (bare_frames, bare_s) = stage_vs_bare(raw, views, stage_episodes)
        ik = ik_comparison(raw, views, episodes)
        imports = writer_imports()
        import lerobot.datasets.lerobot_dataset  # noqa: F401  (the writer's imports: in neither run)

        startup = pool_startup(raw, Path(tmp) / "s", views, 2)
        runs = {w: pipeline(raw, Path(tmp) / f"w{w}", views, w) for w in (1, 2)}
    load_after = os.getloadavg()[0]
    bare_fps, stage_fps = bare_frames / bare_s, stage_frames / stage_s
    print(f"bare mujoco.Renderer + IK: {bare_fps:8.1f} frames/s ({bare_frames} frames)")
    print(f"multiview stage process:   {stage_fps:8.1f} frames/s ({stage_frames} frames)")
    for name, row in ik.items():
        print(
            f"IK {name:4s}: worst {row['worst_mm']} mm (median {row['median_mm']}), worst rotation "
            f"{row['worst_rotation_deg']} deg, {row['ms_per_frame']} ms/frame over {row['frames']} frames"
        )
    print(f"start-up: writer imports {imports:.1f} s (once per fresh run); 2-worker pool ready {startup:.1f} s")
    for w, t in runs.items():
        print(f"{_timing.describe(f'{w} worker(s)', t, episodes)}, {t['cpu']:.1f} CPU s")
    speedup = runs[1]["span"] / runs[2]["span"]
    print(
        f"{episodes} episodes x {views} views: speed-up {speedup:.2f}x over the processing span, "
        f"{runs[1]['total'] / runs[2]['total']:.2f}x whole run "
        f"({os.cpu_count()} CPUs, load average {load_before:.1f} -> {load_after:.1f})"
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
                "workers_speedup_excluding_startup": round(speedup, 3),
                "workers_speedup_goal": 1.6,
                "workers_speedup_whole_run": round(runs[1]["total"] / runs[2]["total"], 3),
                "run_seconds": {str(w): {k: round(v, 2) for k, v in t.items()} for w, t in runs.items()},
                "ik": ik,
                "startup_seconds": {"writer_imports": round(imports, 2), "pool_2_workers": round(startup, 2)},
                "episodes": episodes,
                "stage_episodes": stage_episodes,
                "views": views,
                "stage_frames": stage_frames,
                "cpus": os.cpu_count(),
                "load_average": [round(load_before, 2), round(load_after, 2)],
            }
        )
    )


if __name__ == "__main__":
    main()
