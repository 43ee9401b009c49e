"""`shiftkit run FILE`: run a pipeline (resumable, atomic).

The options are generated (`option_values.DataclassOptions`) from `RunArgs` and from the executors'
own settings (`executor_settings.RaySettings`, `executor_settings.SlurmSettings`), so an executor's defaults live
once, in its settings; only the executor options given reach it.
"""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass

from shiftkit.datasets.dataclass_config import field_help, option
from shiftkit.datasets.option_values import DataclassOptions

HELP = "run a pipeline config; re-running after an interruption resumes it"


@dataclass(frozen=True)
class RunArgs:
    """How `shiftkit run` runs a pipeline config and where it pushes the result."""

    config: str
    """Pipeline config (.toml, .yaml or .json)."""
    workers: int = option(1, rule="positive_int")
    """Worker processes."""
    executor: str = "local"
    """local (process pool), datatrove-local, ray or slurm (see docs/executors.md)."""
    progress: bool = True
    """Show a progress bar."""
    restart: bool = False
    """Discard the unfinished work of an earlier run instead of resuming it."""
    push: str | None = None
    """Push the result to the hub under this dataset ID."""
    push_revision: str | None = None
    """Hub branch for `push`; default: main."""
    private: bool = False
    """Create the hub repository as private."""


OPTIONS = DataclassOptions(
    RunArgs,
    skip=("config",),
    metavars={"push": "ORG/NAME", "push_revision": "BRANCH"},
)


def _executor_options() -> tuple[DataclassOptions, ...]:
    from shiftkit.pipelines.executor_settings import RaySettings, SlurmSettings

    # `--mem-per-cpu` is the slurm setting's (ray's own default is kept unless it is given)
    ray = DataclassOptions(RaySettings, skip=("mem_per_cpu_gb",), flags={"address": "ray-address"})
    slurm = DataclassOptions(
        SlurmSettings,
        flags={"mem_per_cpu_gb": "mem-per-cpu"},
    )
    return ray, slurm


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `run`."""
    parser.add_argument("config", help=field_help(RunArgs, "config"))
    OPTIONS.add_to(parser)
    ray, slurm = _executor_options()
    ray.add_to(parser)
    parser.add_argument("--address", dest="address", default=argparse.SUPPRESS, help="the same as --ray-address")
    slurm.add_to(parser)


def run(args: argparse.Namespace) -> int:
    """Run (or resume, or submit) the pipeline and print its provenance report; return the exit code."""
    from shiftkit import datasets
    from shiftkit.datasets.provenance import recorded_verdict_lines, report_lines
    from shiftkit.pipelines.config import load_pipeline_config
    from shiftkit.pipelines.runner import run_pipeline

    options = OPTIONS.build(args, config=args.config)
    config = load_pipeline_config(options.config)
    if options.push:
        from shiftkit.datasets.hub import validate_repo_id

        validate_repo_id(options.push)  # fail before any work, not after it
        config.destination = dataclasses.replace(
            config.destination,
            repo_id=options.push,
            push=True,
            revision=options.push_revision,
            private=options.private or config.destination.private,
        )
    executor_options = {k: v for settings in _executor_options() for k, v in settings.values(args).items()}
    path = run_pipeline(
        config,
        workers=options.workers,
        executor=options.executor,
        executor_options=executor_options,
        progress=options.progress,
        restart=options.restart,
    )
    if path is None:  # handed to a scheduler; the executor said what to submit
        print(f"{config.destination.root} not written yet: run this command again when the job has finished")
        return 0
    print(f"wrote {path}")
    # The summary's counts are the provenance's, read back from what was written.
    written = datasets.open(path.name, root=path)
    for line in [*report_lines(written.provenance), *recorded_verdict_lines(written.provenance)]:
        print(line)
    return 0
