"""Distributed executors on datatrove: local processes, a Ray cluster, or a SLURM job array.

Each runs the run's unfinished shards (`shards`) as datatrove tasks and reports failed or
unfinished shards in one line before anything is written at the destination. The runner then
writes the dataset from the parts with the same ordered writer pass as for the local executor
(`assembly.write_dataset`), so every executor writes the same bytes for the same pipeline and seed
(apart from the provenance's `executor` fields).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any, ClassVar, override

from shiftkit.datasets.errors import ConfigError, DatasetError
from shiftkit.pipelines.executor_settings import RaySettings, SlurmSettings
from shiftkit.pipelines.planner import Plan
from shiftkit.pipelines.shards import RAY_NODE_VAR, FailureStore, Shard, ShardStep, nodes_used, plan_shards
from shiftkit.pipelines.work import PART_SUFFIX, PartStore, WorkUnit, worker_answers

SHARD_EPISODES = 16
ATTEMPTS = 3
_LOG = logging.getLogger("shiftkit")


class DatatroveExecutor:
    """Shared driver side: shard planning, the datatrove pass, failure reports."""

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
        self.nodes: int | None = None  # how many nodes did the work, once it is done

    def describe(self) -> dict[str, Any]:
        """The executor fields of the provenance (name, workers, nodes once known)."""
        return {"name": self.name, "workers": self.workers, **({"nodes": self.nodes} if self.nodes else {})}

    def run(self, plan: Plan, units: list[WorkUnit], parts: PartStore, bar: Any) -> bool:
        """Transform the unfinished shards with datatrove; False when they were handed to a scheduler."""
        done = self._run(plan, units, parts, bar)
        if done:
            self.nodes = nodes_used(parts.dir.parent)
        return done

    def _run(self, plan: Plan, units: list[WorkUnit], parts: PartStore, bar: Any) -> bool:
        todo = [s for s in plan_shards(units, self.shard_episodes) if not s.done(parts)]
        if not todo:
            return True
        step = ShardStep(plan.config, todo, self.attempts, [type(s) for s in plan.stages], worker_answers(plan))
        tasks = min(self.workers, len(todo))
        logdir = parts.dir.parent / "datatrove" / self.name
        failures = FailureStore(parts.dir.parent)
        if self.schedules:
            return self._schedule(plan, step, tasks, logdir, failures, todo, parts)
        failures.clean()
        with _PartsProgress(parts, bar):
            try:
                self._execute(step, tasks, logdir)
                error = None
            except Exception as exc:  # reported below through the shards' own records
                error = exc
        if message := failures.message(todo):
            raise DatasetError(f"{message}; nothing written to {plan.destination}")
        missing = [s for s in todo if not s.done(parts)]
        if missing:
            why = f"{type(error).__name__}: {error}".splitlines()[0] if error else "the executor stopped"
            raise DatasetError(
                f"{len(missing)} of {len(todo)} shards did not finish ({missing[0].describe()}, ...): "
                f"{why}; logs in {logdir}"
            )
        return True

    def _execute(self, step: ShardStep, tasks: int, logdir: Path) -> None:
        raise NotImplementedError

    def _schedule(
        self,
        plan: Plan,
        step: ShardStep,
        tasks: int,
        logdir: Path,
        failures: FailureStore,
        todo: list[Shard],
        parts: PartStore,
    ) -> bool:
        raise NotImplementedError


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
        done = sum(1 for p in self.parts.dir.glob(f"*.{PART_SUFFIX}")) if self.parts.dir.is_dir() else 0
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
    """`datatrove-local`: datatrove's local process pool on this machine."""

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
    """`ray`: datatrove tasks on a Ray cluster (`address` or $RAY_ADDRESS; default: a local instance)."""

    name = "ray"
    # What Ray workers need from the driver's environment (offline hub, caches, headless MuJoCo).
    FORWARDED_ENV = ("HF_HUB_OFFLINE", "HF_LEROBOT_HOME", "HF_HOME", "HF_DATASETS_CACHE", "MUJOCO_GL")

    def __init__(
        self,
        workers: int = 1,
        address: str | None = RaySettings.address,
        mem_per_cpu_gb: float = RaySettings.mem_per_cpu_gb,
        **options: Any,
    ) -> None:
        super().__init__(workers, **options)
        # RAY_ADDRESS is what `ray.init` reads itself; taken here so the provenance names the cluster.
        self.address = address or os.environ.get("RAY_ADDRESS") or None
        self.mem_per_cpu_gb = mem_per_cpu_gb

    @override
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
                runtime_env={"env_vars": env, "worker_process_setup_hook": spawn_rank_pools},
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


def spawn_rank_pools() -> None:
    """Ray worker set-up: datatrove's rank actor runs its ranks in a `multiprocess` pool, which by
    default forks the actor, a process with Ray's gRPC and event-loop threads; a fork child can
    inherit a lock another thread held and never get past it (Python 3.12 warns of exactly this).
    Spawned pool processes start clean, at ~1 s of imports per task; they are not Ray workers, so
    the node they run on travels to them in the environment (`shards.RAY_NODE_VAR`)."""
    import multiprocess
    import ray

    os.environ[RAY_NODE_VAR] = ray.get_runtime_context().get_node_id()
    multiprocess.set_start_method("spawn", force=True)


class SlurmExecutor(DatatroveExecutor):
    """Writes the SLURM job (sbatch script + pickled datatrove executor + README) into the work
    dir and submits it with `sbatch` (unless `submit` is false), then stops. Re-running the same
    command reports a job still queued or running, submits the job again when it ended with shards
    unfinished (cancelled, timed out, a node lost: finished episodes are kept), and writes the
    dataset once every shard is done."""

    name = "slurm"
    schedules = True

    def __init__(
        self,
        workers: int = 1,
        partition: str | None = SlurmSettings.partition,
        time: str = SlurmSettings.time,
        cpus_per_task: int = SlurmSettings.cpus_per_task,
        mem_per_cpu_gb: int = SlurmSettings.mem_per_cpu_gb,
        setup: str | None = SlurmSettings.setup,
        submit: bool = SlurmSettings.submit,
        **options: Any,
    ) -> None:
        super().__init__(workers, **options)
        if not partition:
            raise ConfigError("executor 'slurm' needs --partition")
        if cpus_per_task < 1 or mem_per_cpu_gb < 1:
            raise ConfigError(f"--cpus-per-task and --mem-per-cpu must be >= 1, got {cpus_per_task}, {mem_per_cpu_gb}")
        if submit and shutil.which("sbatch") is None:
            raise ConfigError(
                "executor 'slurm' submits its job with sbatch, which is not on PATH: run on a SLURM "
                "login node, or pass --no-submit to only write the job"
            )
        self.partition, self.time = partition, time
        self.cpus_per_task, self.mem_per_cpu_gb = cpus_per_task, mem_per_cpu_gb
        self.setup, self.submit = setup, submit

    @override
    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "partition": self.partition}

    def _schedule(
        self,
        plan: Plan,
        step: ShardStep,
        tasks: int,
        logdir: Path,
        failures: FailureStore,
        todo: list[Shard],
        parts: PartStore,
    ) -> bool:
        script = logdir / "launch_script.slurm"
        job_file = logdir / "job_id"
        if not script.is_file():
            failures.clean()
            write_slurm_job(self, plan, step, tasks, logdir)
            if not self.submit:
                _LOG.warning(
                    "SLURM job written; submit it with:\n  sbatch %s\nthen run this command again to write "
                    "the dataset (see %s)",
                    script,
                    logdir / "README.md",
                )
                return False
            job = submit_slurm_job(script, job_file)
            _LOG.warning(
                "submitted SLURM job %s (%d tasks, %d shards); run this command again when it has finished",
                job,
                tasks,
                len(todo),
            )
            return False
        job = job_file.read_text().strip() if job_file.is_file() else None
        if job is not None and slurm_job_active(job):
            _LOG.warning("SLURM job %s is still queued or running: %d shards to do", job, len(todo))
            return False
        if message := failures.message(todo):
            raise DatasetError(
                f"SLURM job: {message}; nothing written to {plan.destination} (fix it, then run this command again)"
            )
        if job is None:  # written with submit=False: the user submits
            _LOG.warning(
                "SLURM job %s: %d shards still to do; when it has finished, run this command again", script, len(todo)
            )
            return False
        # The job ended with shards left: cancelled, timed out, or a node lost. The same job again
        # skips the finished shards (and, within a shard, the finished episodes).
        kept = sum(parts.done(s, i) for shard in todo for s, i in shard.episodes)
        failures.clean()
        new = submit_slurm_job(script, job_file)
        _LOG.warning(
            "SLURM job %s ended with %d shards unfinished; submitted again as job %s (%d of their episodes are "
            "kept); run this command again when it has finished",
            job,
            len(todo),
            new,
            kept,
        )
        return False


def submit_slurm_job(script: Path, job_file: Path) -> str:
    """`sbatch script`; records and returns the job id."""
    proc = subprocess.run(["sbatch", "--parsable", str(script)], capture_output=True, text=True)
    if proc.returncode != 0:
        why = (proc.stderr.strip() or proc.stdout.strip() or f"exit code {proc.returncode}").splitlines()[-1]
        raise DatasetError(f"sbatch {script} failed: {why}")
    job = proc.stdout.strip().split(";")[0]
    job_file.write_text(job + "\n")
    return job


def slurm_job_active(job: str) -> bool:
    """Whether any task of job `job` is still pending or running (squeue lists it)."""
    proc = subprocess.run(["squeue", "--noheader", "--jobs", job, "--format=%T"], capture_output=True, text=True)
    return proc.returncode == 0 and bool(proc.stdout.strip())


def write_slurm_job(executor: SlurmExecutor, plan: Plan, step: ShardStep, tasks: int, logdir: Path) -> Path:
    """What datatrove's `SlurmPipelineExecutor.launch_job` prepares, without calling sbatch."""
    import dill
    from datatrove.executor import SlurmPipelineExecutor

    activate = Path(sys.prefix) / "bin" / "activate"
    slurm = SlurmPipelineExecutor(
        [step],
        tasks=tasks,
        time=executor.time,
        partition=executor.partition,
        cpus_per_task=executor.cpus_per_task,
        mem_per_cpu_gb=executor.mem_per_cpu_gb,
        job_name=f"shiftkit-{plan.destination.name}",
        qos=None,
        env_command=executor.setup,
        venv_path=str(activate) if activate.is_file() and not executor.setup else None,
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

`{script}` is a job array of {tasks} tasks; together they transform {shards} shards of source
episodes into parts (`{work}/parts`). Each task runs `launch_pickled_pipeline executor.pik`
(datatrove) with the shiftkit environment activated.

1. `shiftkit run ... --executor slurm` submits it with `sbatch` (with `--no-submit`, submit it
   yourself from a login node that shares this file system with the compute nodes:
   `sbatch {script}`).
2. Follow it with `squeue`; task logs are in `{logs}`, SLURM's own output in `{slurm_logs}`.
3. When the job has ended, run the same `shiftkit run ... --executor slurm` command again: it
   writes the dataset and renames it into place. If the job ended with shards unfinished
   (cancelled, timed out), that command submits it again (finished episodes are kept); if a shard
   failed, it names the episode and the reason: fix it and run the command again.
"""
