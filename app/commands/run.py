"""`shiftkit run FILE`: run a pipeline (resumable, atomic)."""

from __future__ import annotations

import argparse
import dataclasses

from shiftkit.pipelines.option_values import positive_int

HELP = "run a pipeline config; re-running after an interruption resumes it"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `run`."""
    parser.add_argument("config", help="pipeline config (.toml, .yaml or .json)")
    parser.add_argument("--workers", type=positive_int, default=1, help="worker processes (default 1)")
    parser.add_argument(
        "--executor",
        default="local",
        help="local (default, process pool), datatrove-local, ray or slurm (see docs/executors.md)",
    )
    parser.add_argument(
        "--ray-address",
        "--address",
        dest="address",
        help="ray: address of the cluster to join (default: $RAY_ADDRESS, else start a local Ray instance)",
    )
    parser.add_argument("--partition", help="slurm: partition of the job array (required for slurm)")
    parser.add_argument("--time", help="slurm: time limit per array task (default 04:00:00)")
    parser.add_argument("--cpus-per-task", type=int, help="slurm: CPUs per array task (default 1)")
    parser.add_argument("--mem-per-cpu", type=int, dest="mem_per_cpu_gb", help="slurm: GB per CPU (default 2)")
    parser.add_argument(
        "--setup",
        help="slurm: shell command that prepares each task's environment, e.g. 'module load python; "
        "source ~/venv/bin/activate' (default: activate this Python environment)",
    )
    parser.add_argument(
        "--no-submit", dest="submit", action="store_false", default=None, help="slurm: write the job, do not sbatch it"
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument(
        "--restart", action="store_true", help="discard the unfinished work of an earlier run instead of resuming it"
    )
    parser.add_argument("--push", metavar="ORG/NAME", help="push the result to the hub under this dataset ID")
    parser.add_argument("--push-revision", metavar="BRANCH", help="hub branch for --push (default main)")
    parser.add_argument("--private", action="store_true", help="create the hub repository as private")


def run(args: argparse.Namespace) -> int:
    """Run (or resume, or submit) the pipeline and print its provenance report; return the exit code."""
    from shiftkit.pipelines.config import load_pipeline_config
    from shiftkit.pipelines.jsonutil import read_json_file
    from shiftkit.pipelines.lerobot_io import PROVENANCE_PATH
    from shiftkit.pipelines.provenance import report_lines
    from shiftkit.pipelines.runner import run_pipeline

    config = load_pipeline_config(args.config)
    if args.push:
        from shiftkit.pipelines.hub import validate_repo_id

        validate_repo_id(args.push)  # fail before any work, not after it
        config.destination = dataclasses.replace(
            config.destination,
            repo_id=args.push,
            push=True,
            revision=args.push_revision,
            private=args.private or config.destination.private,
        )
    names = ("address", "partition", "time", "cpus_per_task", "mem_per_cpu_gb", "setup", "submit")
    options = {k: v for k in names if (v := getattr(args, k)) is not None}
    path = run_pipeline(
        config,
        workers=args.workers,
        executor=args.executor,
        executor_options=options,
        progress=not args.no_progress,
        restart=args.restart,
    )
    if path is None:  # handed to a scheduler; the executor said what to submit
        print(f"{config.destination.root} not written yet: run this command again when the job has finished")
        return 0
    print(f"wrote {path}")
    # The summary's counts are the provenance's, read back from what was written.
    for line in report_lines(read_json_file(path / PROVENANCE_PATH, "provenance")):
        print(line)
    return 0
