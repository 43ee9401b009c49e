"""Distributed executors on datatrove: local processes, a Ray cluster, or a SLURM job array.

The work units of a run are packed into *shards* (consecutive units, at most `shard_episodes`
source episodes each), a grouping that does not depend on the number of workers. Each datatrove
task (rank) takes every `world_size`-th unfinished shard; for each it transforms the episodes into
the run's part store (so a resumed run skips finished episodes) and writes the shard as a LeRobot
dataset with `DatasetWriter` (atomic; a finished shard is skipped entirely). A failing shard is
retried (`attempts` in all, with freshly set-up stages); one that keeps failing leaves a failure
record naming the episode and the reason, and the run stops with that message before anything is
written at the destination. Assembly merges the shard datasets in shard order with lerobot's
`aggregate_datasets` into a temporary directory beside the destination, corrects what depends on
an episode's position in the whole dataset (the statistics of `index`, `episode_index` and
`task_index`), adds provenance and card, and renames it into place.

Stages with a dataset-level `select` need every episode's metadata before any shard is written:
then a first datatrove pass only transforms, and a second one writes the selected episodes.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import shutil
import sys
import threading
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from datatrove.pipeline.base import PipelineStep

from shiftkit.pipelines import runner
from shiftkit.pipelines.errors import ConfigError, DatasetError
from shiftkit.pipelines.runner import PartStore, WorkUnit, plan_units
from shiftkit.pipelines.stage import Stage, register_stage, registered_stages, select_outputs, selecting_stages

SHARD_EPISODES = 16
ATTEMPTS = 3
_LOG = logging.getLogger("shiftkit")


@dataclass(frozen=True)
class Shard:
    """Work units whose outputs become one temporary LeRobot dataset."""

    index: int
    units: tuple[WorkUnit, ...]
    keep: tuple[tuple[bool, ...], ...] | None = None
    """Per source episode (in `episodes` order), which of its outputs a dataset-level `select`
    kept; None keeps all."""

    @property
    def episodes(self) -> list[tuple[int, int]]:
        return [(u.source, i) for u in self.units for i in u.episodes]

    def describe(self) -> str:
        eps = self.episodes
        return (
            f"shard {self.index} (source {eps[0][0]} episode {eps[0][1]} .. source {eps[-1][0]} episode {eps[-1][1]})"
        )


def plan_shards(units: list[WorkUnit], max_episodes: int) -> list[Shard]:
    """Pack consecutive units into shards of at most `max_episodes` episodes (a unit is never split)."""
    shards: list[Shard] = []
    current: list[WorkUnit] = []
    for unit in units:
        if current and sum(len(u.episodes) for u in current) + len(unit.episodes) > max_episodes:
            shards.append(Shard(len(shards), tuple(current)))
            current = []
        current.append(unit)
    if current:
        shards.append(Shard(len(shards), tuple(current)))
    return shards


class ShardStore:
    """Shard datasets, empty-shard markers and failure records in `<work dir>/shards`."""

    def __init__(self, work_dir: Path) -> None:
        self.dir = work_dir / "shards"

    def dataset(self, k: int) -> Path:
        return self.dir / f"{k:05d}"

    def _empty(self, k: int) -> Path:
        return self.dir / f"{k:05d}.empty"

    def _failure(self, k: int) -> Path:
        return self.dir / f"{k:05d}.failed.json"

    def done(self, k: int) -> bool:
        return self.dataset(k).is_dir() or self._empty(k).is_file()

    def mark_empty(self, k: int) -> None:
        self._empty(k).touch()

    def record_failure(self, k: int, where: str, reason: str, attempts: int) -> None:
        tmp = self._failure(k).with_suffix(f".tmp-{os.getpid()}")
        tmp.write_text(json.dumps({"where": where, "reason": reason, "attempts": attempts}))
        os.rename(tmp, self._failure(k))

    def clear_failure(self, k: int) -> None:
        self._failure(k).unlink(missing_ok=True)

    def failure(self, k: int) -> dict[str, Any] | None:
        path = self._failure(k)
        return json.loads(path.read_text()) if path.is_file() else None

    def clean(self) -> None:
        """Remove what killed writers and earlier failed attempts left (never a finished shard)."""
        self.dir.mkdir(parents=True, exist_ok=True)
        for stale in self.dir.glob(".*.partial-*"):
            shutil.rmtree(stale, ignore_errors=True)
        for stale in self.dir.glob("*.failed.json"):
            stale.unlink()


class ShardStep(PipelineStep):
    """The datatrove pipeline step: transforms (and writes) the shards of its rank."""

    name = "shiftkit shards"
    type = "🤖 - SHIFTKIT"

    def __init__(
        self, config: Any, shards: list[Shard], attempts: int, stage_classes: list[type[Stage]], write: bool
    ) -> None:
        super().__init__()
        self.config = config
        self.shards = shards
        self.attempts = attempts
        # The stage classes travel with the step, so stages registered outside shiftkit's own
        # packages (a plugin, a script's __main__) exist on Ray workers too.
        self.stage_classes = stage_classes
        self.write = write
        self.main_pid = os.getpid()  # workers of a local pool exit when this process dies

    def run(self, data: Any = None, rank: int = 0, world_size: int = 1) -> Any:
        runner.exit_with_parent(getattr(self, "main_pid", None))
        known = registered_stages()
        for cls in self.stage_classes:
            if cls.name not in known:
                register_stage(cls)
        work = runner.work_dir_for(Path(self.config.destination.root))
        parts, store = PartStore(work), ShardStore(work)
        plan = None
        failed = []
        for shard in self.shards[rank::world_size]:
            for attempt in range(1, self.attempts + 1):
                try:
                    if plan is None:  # set up once per rank, and again after a failure
                        plan = runner.init_worker(self.config)
                        if self.write:  # the shard writer's lerobot modules load torch: part of set-up
                            import lerobot.datasets.lerobot_dataset  # noqa: F401
                    for unit in shard.units:
                        self.stat_update("episodes", value=runner.process_unit(unit))
                    if self.write:
                        _write_shard(plan, shard, parts, store)
                    store.clear_failure(shard.index)
                    self.stat_update("shards")
                    break
                except Exception as exc:
                    plan = None
                    where = next(
                        (f"source {s} episode {i}" for s, i in shard.episodes if not parts.done(s, i)),
                        f"writing {shard.describe()}",
                    )
                    reason = f"{type(exc).__name__}: {exc}".splitlines()[0]
                    _LOG.warning(
                        "%s, attempt %d/%d failed at %s: %s", shard.describe(), attempt, self.attempts, where, reason
                    )
                    self.stat_update("failed_attempts")
                    if attempt == self.attempts:
                        store.record_failure(shard.index, where, reason, attempt)
                        failed.append(shard.index)
        if failed:
            raise DatasetError(f"shards {failed} failed {self.attempts} times (records in {store.dir})")
        return data


def _write_shard(plan: Any, shard: Shard, parts: PartStore, store: ShardStore) -> None:
    from shiftkit.pipelines.lerobot_io import DatasetWriter

    writer = DatasetWriter(
        plan.repo_id, store.dataset(shard.index), plan.fps, plan.features, robot_type=plan.robot_type
    )
    with writer:
        for e, (s, i) in enumerate(shard.episodes):
            for j, (episode, stats) in enumerate(parts.read(s, i)):
                if shard.keep is None or shard.keep[e][j]:
                    writer.add_episode(episode, stats)
        if writer.num_episodes == 0:  # every output was filtered out: nothing to merge
            writer.abort()
            store.mark_empty(shard.index)


class DatatroveExecutor:
    """Shared driver side: shard planning, datatrove passes, failure reports, assembly."""

    name: ClassVar[str]
    schedules: ClassVar[bool] = False  # True: the work is handed to a scheduler, not run here

    def __init__(self, workers: int = 1, shard_episodes: int = SHARD_EPISODES, attempts: int = ATTEMPTS) -> None:
        if workers < 1:
            raise ConfigError(f"--workers must be >= 1, got {workers}")
        if shard_episodes < 1 or attempts < 1:
            raise ConfigError(f"shard_episodes and attempts must be >= 1, got {shard_episodes}, {attempts}")
        self.workers = workers
        self.shard_episodes = shard_episodes
        self.attempts = attempts

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "workers": self.workers}

    def run(self, plan: Any, units: list[WorkUnit], parts: PartStore, bar: Any) -> bool:
        shards = plan_shards(units, self.shard_episodes)
        store = ShardStore(parts.dir.parent)
        if selecting_stages(plan.stages):
            if self.schedules:
                raise ConfigError(
                    f"executor {self.name!r} cannot run stages with a dataset-level select; "
                    "use local, datatrove-local or ray"
                )
            if not self._pass(plan, shards, parts, store, bar, write=False):
                return False
            shards = _with_selection(plan, shards, parts)
        return self._pass(plan, shards, parts, store, bar, write=True)

    def _pass(self, plan: Any, shards: list[Shard], parts: PartStore, store: ShardStore, bar: Any, write: bool) -> bool:
        if write:
            todo = [s for s in shards if not store.done(s.index)]
        else:
            todo = [s for s in shards if not all(parts.done(src, i) for src, i in s.episodes)]
        if not todo:
            return True
        step = ShardStep(plan.config, todo, self.attempts, [type(s) for s in plan.stages], write)
        tasks = min(self.workers, len(todo))
        logdir = parts.dir.parent / "datatrove" / self.name
        if self.schedules:
            return self._schedule(plan, step, tasks, logdir, store, todo)
        store.clean()
        with _PartsProgress(parts, bar):
            try:
                self._execute(step, tasks, logdir)
                error = None
            except Exception as exc:  # reported below through the shards' own records
                error = exc
        _check_shards(plan, todo, parts, store, write, logdir, error)
        return True

    def _execute(self, step: ShardStep, tasks: int, logdir: Path) -> None:
        raise NotImplementedError

    def _schedule(
        self, plan: Any, step: ShardStep, tasks: int, logdir: Path, store: ShardStore, todo: list[Shard]
    ) -> bool:
        raise NotImplementedError

    def assemble(self, plan: Any, parts: PartStore, bar: Any) -> Path:
        store = ShardStore(parts.dir.parent)
        shards = plan_shards(plan_units(plan), self.shard_episodes)
        roots = [store.dataset(s.index) for s in shards if store.dataset(s.index).is_dir()]
        if not roots:
            raise DatasetError(f"no episodes to write to {plan.destination} (every episode was filtered out)")
        path = merge_shards(plan, roots, self.describe(), runner.run_report(plan, parts))
        bar.update(plan.num_source_episodes)
        return path


def _with_selection(plan: Any, shards: list[Shard], parts: PartStore) -> list[Shard]:
    """The shards with the keep-flags of the stages' dataset-level `select` over all outputs."""
    owners: list[tuple[int, int]] = []

    def read_metas() -> list[dict[str, Any]]:
        metas = []
        for shard in shards:
            for s, i in shard.episodes:
                for meta in parts.metas(s, i):
                    owners.append((s, i))
                    metas.append(meta)
        return metas

    keep = select_outputs(plan.stages, read_metas)
    flags: dict[tuple[int, int], list[bool]] = {}
    for owner, flag in zip(owners, keep or [], strict=True):
        flags.setdefault(owner, []).append(flag)
    return [dataclasses.replace(s, keep=tuple(tuple(flags.get(e, ())) for e in s.episodes)) for s in shards]


def _check_shards(
    plan: Any,
    todo: list[Shard],
    parts: PartStore,
    store: ShardStore,
    write: bool,
    logdir: Path,
    error: Exception | None,
) -> None:
    """One-line error naming the failed episodes and why; the destination stays untouched."""
    failures = [(s, store.failure(s.index)) for s in todo]
    failures = [(s, f) for s, f in failures if f is not None]
    if failures:
        what = "; ".join(f"{f['where']}: {f['reason']}" for _, f in failures)
        raise DatasetError(
            f"{len(failures)} of {len(todo)} shards failed {failures[0][1]['attempts']} times, "
            f"nothing written to {plan.destination}: {what}"
        )
    missing = [s for s in todo if not (store.done(s.index) if write else all(parts.done(a, i) for a, i in s.episodes))]
    if missing:
        why = f"{type(error).__name__}: {error}".splitlines()[0] if error else "the executor stopped"
        raise DatasetError(
            f"{len(missing)} of {len(todo)} shards did not finish ({missing[0].describe()}, ...): "
            f"{why}; logs in {logdir}"
        )


class _PartsProgress:
    """Moves the progress bar as finished parts appear (workers may be other processes or machines)."""

    def __init__(self, parts: PartStore, bar: Any, period: float = 0.5) -> None:
        self.parts, self.bar, self.period = parts, bar, period
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._poll, daemon=True)

    def _poll(self) -> None:
        while not self._stop.wait(self.period):
            self._update()

    def _update(self) -> None:
        done = sum(1 for p in self.parts.dir.glob("*.pkl")) if self.parts.dir.is_dir() else 0
        if done > self.bar.n:
            self.bar.update(done - self.bar.n)

    def __enter__(self) -> _PartsProgress:
        self._thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._stop.set()
        self._thread.join()
        self._update()


@contextlib.contextmanager
def _datatrove_logs_to(logdir: Path) -> Iterator[None]:
    """The driver's datatrove log (loguru) goes to a file in the work dir; warnings stay on the terminal."""
    from datatrove.utils.logging import setup_default_logger
    from loguru import logger

    logdir.mkdir(parents=True, exist_ok=True)
    logger.remove()
    logger.add(sys.stderr, level="WARNING")
    logger.add(logdir / "driver.log", level="DEBUG")
    try:
        yield
    finally:
        setup_default_logger()


class DatatroveLocalExecutor(DatatroveExecutor):
    name = "datatrove-local"

    def _execute(self, step: ShardStep, tasks: int, logdir: Path) -> None:
        from datatrove.executor import LocalPipelineExecutor

        # forkserver (datatrove's default): workers fork from a clean server, not from a process
        # that may hold threads (torch, EGL).
        with _datatrove_logs_to(logdir):
            LocalPipelineExecutor(
                [step], tasks=tasks, workers=tasks, logging_dir=str(logdir), skip_completed=False
            ).run()


class RayExecutor(DatatroveExecutor):
    name = "ray"
    # What Ray workers need from the driver's environment (offline hub, caches, headless MuJoCo).
    FORWARDED_ENV = ("HF_HUB_OFFLINE", "HF_LEROBOT_HOME", "HF_HOME", "HF_DATASETS_CACHE", "MUJOCO_GL")

    def __init__(
        self, workers: int = 1, address: str | None = None, mem_per_cpu_gb: float = 1.0, **options: Any
    ) -> None:
        super().__init__(workers, **options)
        self.address = address
        self.mem_per_cpu_gb = mem_per_cpu_gb

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "address": self.address}

    def _execute(self, step: ShardStep, tasks: int, logdir: Path) -> None:
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # never phone home
        import ray
        from datatrove.executor import RayPipelineExecutor

        started = not ray.is_initialized()
        if started:  # join the cluster at `address`, or start a local instance
            env = {k: os.environ[k] for k in self.FORWARDED_ENV if k in os.environ}
            # A local instance's workers run at this process's priority, as the local executor's do
            # (Ray's default lowers them by 15 nice levels: on a shared machine they got scraps).
            system = None if self.address else {"worker_niceness": 0}
            ray.init(
                address=self.address,
                include_dashboard=False,
                logging_level=logging.WARNING,
                runtime_env={"env_vars": env},
                _system_config=system,
            )
        try:
            # datatrove resubmits tasks whose Ray worker died (up to 3 times); errors raised by
            # the step are retried per shard inside it.
            with _datatrove_logs_to(logdir):
                RayPipelineExecutor(
                    [step],
                    tasks=tasks,
                    workers=tasks,
                    logging_dir=str(logdir),
                    skip_completed=False,
                    cpus_per_task=1,
                    mem_per_cpu_gb=self.mem_per_cpu_gb,
                ).run()
        finally:
            if started:
                ray.shutdown()


class SlurmExecutor(DatatroveExecutor):
    """Writes the SLURM job (sbatch script + pickled datatrove executor + README) into the work
    dir and stops; re-running the same command after the job has finished assembles the dataset."""

    name = "slurm"
    schedules = True

    def __init__(
        self,
        workers: int = 1,
        partition: str | None = None,
        time: str = "04:00:00",
        mem_per_cpu_gb: int = 2,
        **options: Any,
    ) -> None:
        super().__init__(workers, **options)
        if not partition:
            raise ConfigError("executor 'slurm' needs --partition")
        self.partition, self.time, self.mem_per_cpu_gb = partition, time, mem_per_cpu_gb

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "partition": self.partition}

    def _schedule(
        self, plan: Any, step: ShardStep, tasks: int, logdir: Path, store: ShardStore, todo: list[Shard]
    ) -> bool:
        script = logdir / "launch_script.slurm"
        if script.is_file():
            failures = [f for f in (store.failure(s.index) for s in todo) if f is not None]
            if failures:
                what = "; ".join(f"{f['where']}: {f['reason']}" for f in failures)
                raise DatasetError(
                    f"{len(failures)} shards of the SLURM job failed, nothing written to "
                    f"{plan.destination}: {what} (fix it, then `sbatch {script}` again)"
                )
            _LOG.warning(
                "SLURM job %s: %d shards still to do; when it has finished, run this command again "
                "to assemble the dataset",
                script,
                len(todo),
            )
            return False
        write_slurm_job(self, plan, step, tasks, logdir)
        _LOG.warning(
            "SLURM job written; submit it with:\n  sbatch %s\nthen run this command again to assemble "
            "the dataset (see %s)",
            script,
            logdir / "README.md",
        )
        return False


def write_slurm_job(executor: SlurmExecutor, plan: Any, step: ShardStep, tasks: int, logdir: Path) -> Path:
    """What datatrove's `SlurmPipelineExecutor.launch_job` prepares, without calling sbatch."""
    import dill
    from datatrove.executor import SlurmPipelineExecutor

    ShardStore(logdir.parents[1]).clean()
    activate = Path(sys.prefix) / "bin" / "activate"
    slurm = SlurmPipelineExecutor(
        [step],
        tasks=tasks,
        time=executor.time,
        partition=executor.partition,
        cpus_per_task=1,
        mem_per_cpu_gb=executor.mem_per_cpu_gb,
        job_name=f"shiftkit-{plan.destination.name}",
        qos=None,
        venv_path=str(activate) if activate.is_file() else None,
        logging_dir=str(logdir),
        skip_completed=False,
    )
    ranks = slurm.get_incomplete_ranks()
    with slurm.logging_dir.open("executor.pik", "wb") as f:
        dill.dump(slurm, f, fmode=dill.CONTENTS_FMODE)
    slurm.save_executor_as_json()
    with slurm.logging_dir.open("ranks_to_run.json", "w") as f:
        json.dump(ranks, f)
    env = " ".join(f"{k}={os.environ[k]}" for k in RayExecutor.FORWARDED_ENV if k in os.environ)
    # One line: datatrove dedents the script body around it.
    command = f"{'export ' + env + '; ' if env else ''}srun -l -n 1 launch_pickled_pipeline {logdir / 'executor.pik'}"
    script = logdir / "launch_script.slurm"
    script.write_text(slurm.get_launch_file_contents(slurm.get_sbatch_args(len(ranks)), command))
    (logdir / "README.md").write_text(
        SLURM_README.format(
            script=script,
            tasks=len(ranks),
            shards=len(step.shards),
            dest=plan.destination,
            logs=logdir / "logs",
            slurm_logs=slurm.slurm_logs_folder,
            work=logdir.parents[1],
        )
    )
    return script


SLURM_README = """# SLURM job for {dest}

`{script}` is a job array of {tasks} tasks; together they transform and write {shards} shards
(temporary LeRobot datasets in `{work}/shards`). Each task runs
`launch_pickled_pipeline executor.pik` (datatrove) with the shiftkit environment activated.

1. Submit from a login node that shares this file system with the compute nodes:

       sbatch {script}

2. Follow it with `squeue`; task logs are in `{logs}`, SLURM's own output in `{slurm_logs}`.
3. When every task has finished, run the same `shiftkit run ... --executor slurm` command again:
   it merges the shards (lerobot's aggregation) and renames the dataset into place. If a shard
   failed, that command names the episode and the reason; fix it and submit the script again
   (finished shards are skipped).
"""


def merge_shards(plan: Any, roots: list[Path], executor_info: dict[str, Any], report: list[dict[str, int]]) -> Path:
    """Aggregate the shard datasets (in order) into the destination, atomically."""
    from shiftkit.pipelines import camera_meta
    from shiftkit.pipelines.lerobot_io import aggregate_shards, write_provenance
    from shiftkit.pipelines.provenance import build_provenance

    dest = plan.destination
    tmp = dest.parent / f".{dest.name}.partial-{uuid.uuid4().hex[:8]}"  # removed by a later run if killed
    try:
        num_episodes, num_frames = aggregate_shards(plan.repo_id, roots, tmp)
        provenance = build_provenance(plan, executor_info, num_episodes, num_frames, report)
        # lerobot's aggregation does not know meta/cameras.json: concatenate the shards' own.
        cameras = camera_meta.provenance_entry(camera_meta.concat_cameras_files(roots, tmp))
        write_provenance(tmp, {**provenance, "cameras": cameras} if cameras else provenance)
        if dest.exists():
            raise DatasetError(f"destination already exists: {dest}")
        os.rename(tmp, dest)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return dest


DATATROVE_EXECUTORS: dict[str, type[DatatroveExecutor]] = {
    "datatrove-local": DatatroveLocalExecutor,
    "ray": RayExecutor,
    "slurm": SlurmExecutor,
}
