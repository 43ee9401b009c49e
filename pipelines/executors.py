"""Executors run the work units (`work`: groups of source episodes) of a pipeline into parts;
they know nothing about what a stage does, and none writes the dataset: the runner writes it from
the parts with the one ordered writer pass (`assembly.write_dataset`), so they all write the same
bytes.

`local` is a process pool on this machine (in-process for 1 worker); it is the default.
`datatrove-local`, `ray` and `slurm` run the same transforms on datatrove
(`shiftkit.pipelines.datatrove_executor`).
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any, Protocol

from shiftkit.datasets.errors import ConfigError
from shiftkit.envs.registry import Registry
from shiftkit.pipelines import work
from shiftkit.pipelines.planner import Plan
from shiftkit.pipelines.work import PartStore, WorkUnit


class Executor(Protocol):
    """What transforms a plan's work units into parts: this process, a process pool or datatrove (`EXECUTORS`)."""

    def describe(self) -> dict[str, Any]:
        """The executor fields of the provenance (name, workers, ...)."""

    def run(self, plan: Plan, units: list[WorkUnit], parts: PartStore, bar: Any) -> bool:
        """Transform every unit's unfinished episodes into `parts`. False when the work was handed
        to a scheduler and the dataset cannot be written yet."""


class LocalExecutor:
    """`local`: this process (one worker) or a pool of worker processes."""

    name = "local"

    def __init__(self, workers: int = 1) -> None:
        if workers < 1:
            raise ConfigError(f"--workers must be >= 1, got {workers}")
        self.workers = workers

    def describe(self) -> dict[str, Any]:
        """The executor fields of the provenance (name, workers)."""
        return {"name": self.name, "workers": self.workers}

    def run(self, plan: Plan, units: list[WorkUnit], parts: PartStore, bar: Any) -> bool:
        """Transform every unit's unfinished episodes into `parts`; always True (nothing is scheduled)."""
        units = [u for u in units if not all(parts.done(u.source, i) for i in u.episodes)]
        if not units:
            return True
        if self.workers == 1:  # in this process, on the plan the runner built
            work.set_up_worker(plan)
            for unit in units:
                bar.update(work.process_unit(unit))
            return True
        # spawn, not fork: stages may hold threads (torch, EGL) that do not survive a fork.
        ctx = multiprocessing.get_context("spawn")
        answers = work.worker_answers(plan)
        with ProcessPoolExecutor(
            self.workers, mp_context=ctx, initializer=work.init_worker, initargs=(plan.config, os.getpid(), answers)
        ) as pool:
            futures = [pool.submit(work.process_unit, unit) for unit in units]
            try:
                for future in as_completed(futures):
                    bar.update(future.result())
            except BaseException:
                for f in futures:
                    f.cancel()
                raise
        return True


def _datatrove(cls: str) -> Any:
    """A factory of the datatrove executor class `cls`, importing datatrove (and ray) only when used."""

    def make(workers: int = 1, **options: Any) -> Executor:
        from shiftkit.pipelines import datatrove_executor

        return getattr(datatrove_executor, cls)(workers=workers, **options)

    return make


# Executor factories by the name `shiftkit run --executor` takes.
EXECUTORS: Registry[Callable[..., Executor]] = Registry("executor", error=ConfigError)
EXECUTORS.register(LocalExecutor, "local")
EXECUTORS.register(_datatrove("DatatroveLocalExecutor"), "datatrove-local")
EXECUTORS.register(_datatrove("RayExecutor"), "ray")
EXECUTORS.register(_datatrove("SlurmExecutor"), "slurm")


def get_executor(name: str, workers: int = 1, **options: Any) -> Executor:
    """The executor registered as `name`; a ConfigError for an unknown name or an option it does not take."""
    make = EXECUTORS.get(name)
    try:
        return make(workers=workers, **options)
    except TypeError:  # an option this executor does not take, e.g. --address for local
        raise ConfigError(f"executor {name!r} does not take these options: {', '.join(options)}") from None
