"""Executors run work units (groups of source episodes) and report progress; they know nothing
about what a stage does. `local` is a process pool on this machine (in-process for 1 worker)."""

from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any, Protocol

from shiftkit.pipelines.config import PipelineConfig
from shiftkit.pipelines.errors import ConfigError


class Executor(Protocol):
    def run(self, config: PipelineConfig, units: list[Any], bar: Any) -> None: ...


class LocalExecutor:
    def __init__(self, workers: int = 1) -> None:
        if workers < 1:
            raise ConfigError(f"--workers must be >= 1, got {workers}")
        self.workers = workers

    def run(self, config: PipelineConfig, units: list[Any], bar: Any) -> None:
        from shiftkit.pipelines import runner

        if not units:
            return
        if self.workers == 1:
            runner.init_worker(config)
            for unit in units:
                bar.update(runner.process_unit(unit))
            return
        # spawn, not fork: stages may hold threads (torch, EGL) that do not survive a fork.
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(self.workers, mp_context=ctx, initializer=runner.init_worker, initargs=(config,)) as pool:
            futures = [pool.submit(runner.process_unit, unit) for unit in units]
            try:
                for future in as_completed(futures):
                    bar.update(future.result())
            except BaseException:
                for f in futures:
                    f.cancel()
                raise


EXECUTORS = {"local": LocalExecutor}


def get_executor(name: str, workers: int = 1, **options: Any) -> Executor:
    if name not in EXECUTORS:
        raise ConfigError(f"unknown executor {name!r} (available: {', '.join(EXECUTORS)})")
    return EXECUTORS[name](workers=workers, **options)
