"""Run a pipeline: transform episodes in parallel, then write one LeRobot dataset atomically.

The plan is built once here. An executor (`executors`) transforms the work units (`work`) into
parts in a work directory beside the destination; after a crash or a SIGKILL re-running the same
command skips every finished episode. When all parts exist, `assembly.write_dataset` writes them in
source order into a temporary LeRobot dataset that is renamed into place, and the work directory is
removed: the destination holds a complete dataset or nothing. Every executor shares that one
assembly.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import shutil
import threading
from pathlib import Path
from typing import Any

from shiftkit.datasets.errors import ShiftkitError
from shiftkit.datasets.reader import require_utf8_path
from shiftkit.datasets.staging import DestinationLock, remove_dead_staging
from shiftkit.datasets.writer import preload_writer
from shiftkit.pipelines.assembly import write_dataset
from shiftkit.pipelines.config import PipelineConfig
from shiftkit.pipelines.executors import Executor, get_executor
from shiftkit.pipelines.planner import Plan, plan_pipeline
from shiftkit.pipelines.work import PartStore, plan_units, run_key, work_dir_for


def run_pipeline(
    config: PipelineConfig,
    workers: int = 1,
    executor: str = "local",
    executor_options: dict[str, Any] | None = None,
    progress: bool = True,
    restart: bool = False,
) -> Path | None:
    """Run the pipeline to completion (resuming earlier partial work unless `restart`) and return
    the dataset path, or None when the executor handed the work to a scheduler (slurm): re-running
    then assembles. One run at a time per destination (a lock beside the work directory)."""
    from shiftkit.datasets.hub import validate_repo_id

    engine = get_executor(executor, workers, **(executor_options or {}))
    if config.destination.repo_id is not None:
        validate_repo_id(config.destination.repo_id)
    plan = plan_pipeline(config)
    dest = plan.destination
    check_writable_name(dest)
    work = work_dir_for(dest)
    with DestinationLock(dest):
        if restart and work.exists():
            shutil.rmtree(work)
        try:
            return _run_locked(config, plan, engine, work, progress)
        except OSError as exc:
            if exc.errno == errno.ENOSPC:
                raise ShiftkitError(
                    f"no space left on the device of {work.parent}: the work directory {work} holds "
                    f"{_size_text(work)}; free space and re-run to resume, or re-run with --restart to discard it"
                ) from None
            raise


def check_writable_name(dest: Path) -> None:
    """LeRobot's parquet writer (pyarrow) takes UTF-8 paths only: refuse others before any work."""
    require_utf8_path(dest, "destination", "written to")


def _run_locked(config: PipelineConfig, plan: Plan, engine: Executor, work: Path, progress: bool) -> Path | None:
    dest = plan.destination
    key = run_key(plan)
    _prepare_work_dir(work, key, dest)
    parts = PartStore(work)
    units = plan_units(plan)
    done = sum(parts.done(u.source, i) for u in units for i in u.episodes)
    if done:
        logging.getLogger("shiftkit").warning(
            "resuming: %d of %d source episodes were already transformed", done, plan.num_source_episodes
        )
    # The writer's imports (lerobot, torch) take seconds; made while the executor transforms they
    # overlap the work instead of adding to it afterwards, when the workers would be idle. Not a
    # daemon: a run that fails meanwhile exits after the imports, since CPython (< 3.14) ends a daemon
    # thread at exit with pthread_exit, whose unwinding through torch's C++ frames aborts (exit 134).
    preload = threading.Thread(target=preload_writer, name="shiftkit-preload-writer")
    preload.start()
    with _progress(plan.num_source_episodes, done, "transform", progress) as bar:
        if not engine.run(plan, units, parts, bar):
            return None
    preload.join()
    try:
        with _progress(plan.num_source_episodes, 0, "write", progress) as bar:
            path = write_dataset(plan, parts, engine.describe(), bar)
    except ShiftkitError:
        # Every part exists, so the data itself is the problem (e.g. every episode filtered out): the
        # same job fails the same way again and a changed one has another key. Nothing to resume.
        shutil.rmtree(work, ignore_errors=True)
        raise
    shutil.rmtree(work, ignore_errors=True)
    if config.destination.push:
        from shiftkit.datasets import hub

        # After the atomic rename: a failed push leaves the local dataset for `shiftkit push`.
        result = hub.push_dataset(
            path, plan.repo_id, revision=config.destination.revision, private=config.destination.private
        )
        logging.getLogger("shiftkit").warning("pushed %s to %s", path, result.url)
    return path


def _prepare_work_dir(work: Path, key: str, dest: Path) -> None:
    # Leftovers of a writer killed mid-way are never a usable dataset: remove them.
    remove_dead_staging(dest)
    key_file = work / "run_key"
    if work.exists() and (not key_file.exists() or key_file.read_text() != key):
        shutil.rmtree(work)  # parts of a different pipeline/config cannot be reused
    work.mkdir(parents=True, exist_ok=True)
    key_file.write_text(key)
    for tmp in (work / "parts").glob("*.tmp-*"):
        tmp.unlink()


def _size_text(folder: Path) -> str:
    total = 0
    for dirpath, _, files in os.walk(folder):
        for name in files:
            with contextlib.suppress(OSError):  # removed meanwhile
                total += os.lstat(os.path.join(dirpath, name)).st_size
    return f"{total / 1e6:.1f} MB"


class _progress:
    def __init__(self, total: int, initial: int, desc: str, enabled: bool) -> None:
        from tqdm import tqdm

        self._bar = tqdm(total=total, initial=initial, desc=desc, unit="ep", disable=not enabled, leave=False)

    def __enter__(self) -> Any:
        return self._bar

    def __exit__(self, *exc: Any) -> None:
        self._bar.close()
