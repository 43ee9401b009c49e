"""The settings of the cluster executors beyond `workers`, one dataclass each: the executors take
their defaults from here and `shiftkit run` generates its options from them, so each default lives
once (docs/executors.md)."""

from __future__ import annotations

from dataclasses import dataclass

from shiftkit.datasets.dataclass_config import option


@dataclass(frozen=True)
class RaySettings:
    """The settings of the `ray` executor beyond `workers` (`RayExecutor` takes its defaults from here)."""

    address: str | None = None
    """ray: address of the cluster to join; default: $RAY_ADDRESS, else start a local Ray instance."""
    mem_per_cpu_gb: float = 1.0
    """ray: GB of memory each task asks for."""


@dataclass(frozen=True)
class SlurmSettings:
    """The settings of the `slurm` executor beyond `workers` (`SlurmExecutor` takes its defaults from here)."""

    partition: str | None = None
    """slurm: partition of the job array (required for slurm)."""
    time: str = "04:00:00"
    """slurm: time limit per array task."""
    cpus_per_task: int = option(1, rule="positive_int")
    """slurm: CPUs per array task."""
    mem_per_cpu_gb: int = option(2, rule="positive_int")
    """slurm: GB of memory per CPU."""
    setup: str | None = None
    """slurm: shell command that prepares each task's environment, e.g. 'module load python; source
    ~/venv/bin/activate'; default: activate this Python environment."""
    submit: bool = True
    """slurm: submit the job with sbatch (`--no-submit`: only write it)."""
