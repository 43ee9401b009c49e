"""Executor scaling: wall time of a CPU-heavy stage with 1 vs 2 workers, local and Ray executors.

The stage re-renders every frame of recorded Panda play episodes from their simulator state
(`sim.qpos`, written by `shiftkit collect --env panda-play`) with MuJoCo (visual meshes, 64x48),
adding a camera feature. It is registered here only, for the bench: the Ray executor ships it to
its workers with the step, the local executor's spawned workers re-import this file.

In one run: the same pipeline on the same episodes with the `local` executor (1 and 2 workers) and
the `ray` executor (1 and 2 workers, on a local Ray instance started once beforehand, as a cluster
would be). Goal: speed-up >= 1.6x with 2 workers, for each executor; the reported value is the
smaller of the two.

Start-up (spawning workers, importing, setting up the renderer) and the final dataset write do
not shrink with workers, and with few episodes they hide the scaling. The stage stamps each
episode with the wall-clock times it started and finished rendering it, so the bench reports,
apart from the wall time of the whole run, the processing span (first episode started to last
episode finished) and the start-up (run start to first episode started); the headline speed-up
is the processing span's, the whole-run one is reported beside it. What keeps a 2-worker span above
half the 1-worker one is broken down per run: workers starting apart, work falling unevenly on
them, and each episode rendering slower than with 1 worker (`episode_time_2_vs_1`: cores shared
with each other or with other jobs). The machine's load average is recorded, since other jobs share
its cores.

Bytes written per input byte: what each run leaves on disk (its work directory, measured just
before the runner removes it, plus the dataset) over the size of the source folder; re-writes of a
file in place are not counted. The JSON also says whether a CUDA device was present (the stage
renders on the CPU either way). The last line printed is the JSON result.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import tempfile
import time
from collections.abc import Iterable
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
# Mesa's llvmpipe rasterises with one thread per core by default, so a single renderer would
# already occupy both cores: one thread per renderer makes "workers" the unit of parallelism.
os.environ.setdefault("LP_NUM_THREADS", "1")

import _device  # noqa: E402  (bench/, beside this file)
import _timing  # noqa: E402
import numpy as np  # noqa: E402

from shiftkit.datasets.episode import META_COLUMN, Episode
from shiftkit.datasets.features import Features
from shiftkit.pipelines.stage import Stage, register_stage


@dataclasses.dataclass
class RerenderConfig:
    camera: str = "front"
    """Panda play camera to render."""
    quality: str = "full"
    """"full" (visual meshes, the costly mode) or "fast" (collision geometry)."""
    width: int = 64
    """Image width."""
    height: int = 48
    """Image height."""


@register_stage
class Rerender(Stage):
    """Re-render each frame from its recorded simulator state (bench-only stage)."""

    name = "bench-rerender"
    version = 1
    Config = RerenderConfig

    def setup(self) -> None:
        from shiftkit.envs.cameras import CameraRenderer
        from shiftkit.envs.panda_play.physics import PandaPlayPhysics

        self._physics = PandaPlayPhysics()
        self._renderer = CameraRenderer(self._physics.model, self.config.width, self.config.height, self.config.quality)

    def transform_features(self, features: Features) -> Features:
        image = {
            "dtype": "image",
            "shape": (self.config.height, self.config.width, 3),
            "names": ["height", "width", "channels"],
        }
        return {**features, f"observation.images.{self.config.camera}_rerendered": image}

    def process(self, episode: Episode, rng: np.random.Generator) -> Iterable[Episode]:
        t0 = time.time()
        qpos = episode.frames["sim.qpos"]
        zeros = np.zeros(self._physics.model.nv)
        images = []
        for q in qpos:
            self._physics.set_state(q.astype(np.float64), zeros)
            images.append(self._renderer.rgb(self._physics.data, self.config.camera).copy())
        key = f"observation.images.{self.config.camera}_rerendered"
        # Wall-clock stamps (bench-only): when this worker (pid) started and finished the episode.
        stamps = [t0, time.time(), os.getpid()]
        yield Episode({**episode.frames, key: np.stack(images)}, {**episode.meta, "bench_t": stamps})


def make_source(root: Path, episodes: int) -> Path:
    from shiftkit.app.collect import CollectConfig, collect

    path, _ = collect(CollectConfig(env="panda-play", task="lift", episodes=episodes, seed=0, out=str(root)))
    return path


def folder_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file() and not p.is_symlink())


_REMOVED: dict[str, int] = {}  # work directory -> bytes it held when the runner removed it
_rmtree = shutil.rmtree


def _measuring_rmtree(path: str | os.PathLike, *args: object, **kwargs: object) -> None:
    if str(path).endswith(".shiftkit-work") and Path(path).is_dir():
        _REMOVED[str(path)] = folder_bytes(Path(path))
    _rmtree(path, *args, **kwargs)


shutil.rmtree = _measuring_rmtree  # the runner removes its work directory with shutil.rmtree


def timed_run(source: Path, dest: Path, executor: str, workers: int, shard_episodes: int) -> dict[str, float]:
    """The run's time split (`_timing.breakdown`: start-up, processing span, where a span exceeds an
    even split of the work) and the bytes it wrote (`bytes_written`: work directory and dataset)."""
    from shiftkit.datasets.sources import SourceConfig
    from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, StageSpec
    from shiftkit.pipelines.runner import run_pipeline

    config = PipelineConfig(
        sources=[SourceConfig(path=str(source))],
        stages=[StageSpec(name="bench-rerender")],
        destination=DestinationConfig(root=str(dest)),
    )
    options = {} if executor == "local" else {"shard_episodes": shard_episodes}
    from shiftkit.datasets.reader import open_lerobot_dataset

    t0 = time.time()
    run_pipeline(config, workers=workers, executor=executor, executor_options=options, progress=False)
    total = time.time() - t0
    written = _REMOVED.pop(str(dest.parent / f".{dest.name}.shiftkit-work"), 0) + folder_bytes(dest)
    stamps = np.array([json.loads(m)["bench_t"] for m in open_lerobot_dataset(dest).episodes[META_COLUMN]])
    return {**_timing.breakdown(stamps[:, 0], stamps[:, 1], stamps[:, 2], t0, total), "bytes_written": written}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="6 episodes (about a minute on 2 idle cores)")
    parser.add_argument("--episodes", type=int, help="recorded lift episodes (default 24, quick 6)")
    args = parser.parse_args()
    episodes = args.episodes or (6 if args.quick else 24)

    with tempfile.TemporaryDirectory(prefix="shiftkit-bench-exec-") as tmp:
        tmp = Path(tmp)
        os.environ.setdefault("HF_LEROBOT_HOME", str(tmp / "home"))
        os.environ.setdefault("HF_DATASETS_CACHE", str(tmp / "datasets-cache"))
        source = make_source(tmp / "raw", episodes)
        from shiftkit.datasets.sources.raw import open_raw_dataset

        raw = open_raw_dataset(source)
        # The writer's lerobot modules (they load torch) are imported by whichever run writes first;
        # imported here, no timed run pays for them.
        import lerobot.datasets.lerobot_dataset  # noqa: F401

        frames = sum(int(e["length"]) for e in raw.index["episodes"])  # from the index, no episode reads
        input_bytes = folder_bytes(source)
        load_before = os.getloadavg()
        import ray

        ray.init(
            num_cpus=2,
            include_dashboard=False,
            logging_level="WARNING",
            # Workers at the bench's priority, like the local executor's and the Ray executor's own
            # local instance (Ray's default is 15 nice levels lower).
            _system_config={"worker_niceness": 0},
            runtime_env={
                "env_vars": {
                    k: os.environ[k]
                    for k in ("HF_HUB_OFFLINE", "HF_LEROBOT_HOME", "HF_DATASETS_CACHE", "MUJOCO_GL", "LP_NUM_THREADS")
                }
            },
        )
        runs: dict[str, dict[int, dict[str, float]]] = {}
        # One episode per unit (raw sources); shards of 1 episode balance 2 workers best.
        for name in ("local", "ray"):
            runs[name] = {w: timed_run(source, tmp / f"{name}-{w}", name, w, shard_episodes=1) for w in (1, 2)}
        ray.shutdown()
        load_after = os.getloadavg()

    def speedups(part: str) -> dict[str, float]:
        return {name: round(r[1][part] / r[2][part], 3) for name, r in runs.items()}

    for name, r in runs.items():
        for w, t in r.items():
            print(_timing.describe(f"{name:5s} {w} worker(s)", t, episodes))
    print(
        json.dumps(
            {
                "bench": "executors",
                "metric": "speedup_2_workers_excluding_startup_min_over_executors",
                "value": min(speedups("span").values()),
                "goal": 1.6,
                "higher_is_better": True,
                "speedup_excluding_startup": speedups("span"),
                "speedup_whole_run": speedups("total"),
                # > 1: each episode renders slower with 2 workers (cores shared with each other or other jobs).
                "episode_time_2_vs_1": {name: round(r[2]["episode"] / r[1]["episode"], 3) for name, r in runs.items()},
                # The dataset-writing cost: the 2-worker run of each executor.
                "bytes_written_per_input_byte": {
                    name: round(r[2]["bytes_written"] / input_bytes, 3) for name, r in runs.items()
                },
                "input_bytes": input_bytes,
                "seconds": {
                    name: {str(w): {k: round(v, 2) for k, v in t.items() if k != "bytes_written"} for w, t in r.items()}
                    for name, r in runs.items()
                },
                "stage": "bench-rerender (MuJoCo, visual meshes, 64x48)",
                "episodes": episodes,
                "frames": frames,
                "cpu_count": os.cpu_count(),
                "gpu": _device.gpu_info(),
                "lp_num_threads": os.environ["LP_NUM_THREADS"],
                "loadavg_1min_before_after": [round(load_before[0], 2), round(load_after[0], 2)],
                "quick": args.quick,
            }
        )
    )


if __name__ == "__main__":
    main()
