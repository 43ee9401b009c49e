"""The SLURM executor on a real (single-node) SLURM cluster started on this machine: munged,
slurmctld and slurmd with 2 CPUs, a job array submitted by `shiftkit run --executor slurm` through
real `sbatch`. The dataset equals the local executor's bytes, and a job cancelled mid-run
(`scancel`, while a third-party stage plugin holds it) is resubmitted by the next run and ends with
the same bytes.

`.ci/run` installs Debian's `slurm-wlm` and `munge`; without their binaries the test skips."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.test_executors import assert_same_dataset, write_config

pytestmark = pytest.mark.cluster

EPISODES = 24
DAEMONS = ("munged", "slurmctld", "slurmd", "sbatch", "squeue", "scancel", "sinfo", "scontrol")

# the executor tests' pipeline, with a stage that drops episodes
FILTER = """[[stages]]
name = "filter"
params = { keep_fraction = 0.6 }"""


def _binary(name: str) -> str | None:
    return shutil.which(name) or next(
        (str(p) for p in (Path("/usr/sbin") / name, Path("/usr/bin") / name) if p.is_file()), None
    )


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait(what: str, ready, timeout: float = 60.0, logs: tuple[Path, ...] = (), period: float = 0.25) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if ready():
            return
        time.sleep(period)
    tails = "\n".join(f"--- {p}\n{p.read_text()[-3000:]}" for p in logs if p.is_file())
    raise AssertionError(f"{what} not ready after {timeout:.0f} s\n{tails}")


class Slurm:
    """A one-node SLURM cluster in `root`: its own munge socket, ports, state and spool folders."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.conf = root / "slurm.conf"
        self.env = {**os.environ, "SLURM_CONF": str(self.conf)}
        self.pids: list[int] = []

    def start(self) -> None:
        r = self.root
        for d in ("state", "spool", "munge"):
            (r / d).mkdir(mode=0o700)
        key = r / "munge" / "munge.key"
        key.write_bytes(os.urandom(1024))
        key.chmod(0o600)
        sock = r / "munge" / "munge.sock"
        subprocess.run(
            [
                _binary("munged"),
                "--force",
                f"--socket={sock}",
                f"--key-file={key}",
                f"--pid-file={r / 'munge' / 'munged.pid'}",
                f"--log-file={r / 'munge' / 'munged.log'}",
                f"--seed-file={r / 'munge' / 'munged.seed'}",
            ],
            check=True,
            capture_output=True,
        )
        self.pids.append(int((r / "munge" / "munged.pid").read_text()))
        host = socket.gethostname().split(".")[0]
        self.conf.write_text(
            f"""ClusterName=shiftkit
SlurmctldHost={host}
SlurmctldPort={_free_port()}
SlurmdPort={_free_port()}
AuthType=auth/munge
AuthInfo=socket={sock}
CredType=cred/munge
SlurmUser=root
SlurmdUser=root
StateSaveLocation={r / "state"}
SlurmdSpoolDir={r / "spool"}
SlurmctldPidFile={r / "slurmctld.pid"}
SlurmdPidFile={r / "slurmd.pid"}
SlurmctldLogFile={r / "slurmctld.log"}
SlurmdLogFile={r / "slurmd.log"}
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
MpiDefault=none
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
SlurmdParameters=config_overrides
ReturnToService=2
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
SchedulerParameters=sched_interval=1
MinJobAge=2
NodeName={host} CPUs=2 RealMemory=8192 State=UNKNOWN
PartitionName=debug Nodes={host} Default=YES MaxTime=INFINITE State=UP
"""
        )
        for daemon in ("slurmctld", "slurmd"):
            subprocess.run([_binary(daemon), "-f", str(self.conf)], check=True, env=self.env, capture_output=True)
            _wait(f"{daemon} pid file", (r / f"{daemon}.pid").is_file, 30, self.logs)
            self.pids.append(int((r / f"{daemon}.pid").read_text()))
        _wait("an idle node", lambda: "idle" in self.cmd("sinfo", "--noheader", "-o", "%T").stdout, 60, self.logs)

    @property
    def logs(self) -> tuple[Path, ...]:
        return (self.root / "slurmctld.log", self.root / "slurmd.log", self.root / "munge" / "munged.log")

    def cmd(self, *args: str) -> subprocess.CompletedProcess:
        return subprocess.run(args, env=self.env, capture_output=True, text=True)

    def stop(self) -> None:
        self.cmd("scancel", "--full", "--user=root")
        for pid in reversed(self.pids):
            try:
                os.kill(pid, 15)
            except ProcessLookupError:
                continue
            for _ in range(100):
                try:
                    os.kill(pid, 0)
                except ProcessLookupError:
                    break
                time.sleep(0.05)


@pytest.fixture(scope="module")
def slurm(tmp_path_factory) -> Iterator[Slurm]:
    missing = [d for d in DAEMONS if _binary(d) is None]
    if missing:
        pytest.skip(f"SLURM binaries absent ({', '.join(missing)}); .ci/run installs slurm-wlm and munge")
    if os.geteuid() != 0:
        pytest.skip("starting slurmd needs root")
    cluster = Slurm(tmp_path_factory.mktemp("slurm"))
    try:
        cluster.start()
        yield cluster
    finally:
        cluster.stop()


@pytest.fixture(scope="module")
def raw(tmp_path_factory) -> Path:
    from shiftkit.datasets.synthetic import write_synthetic_raw

    root = tmp_path_factory.mktemp("raw")
    return write_synthetic_raw(
        root / "raw", episodes=EPISODES, length=12, seed=4, camera=(24, 32), tasks=("reach", "push")
    )


def _config(tmp_path: Path, raw: Path, name: str) -> Path:
    return write_config(tmp_path, raw, name, FILTER)


def shiftkit(env: dict[str, str], *args: str) -> subprocess.CompletedProcess:
    proc = subprocess.run(
        [sys.executable, "-m", "shiftkit.app.cli", *args], env=env, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def _job_id(dest: Path) -> str:
    from shiftkit.pipelines.work import work_dir_for

    return (work_dir_for(dest) / "datatrove" / "slurm" / "job_id").read_text().strip()


def _until_job_ends(slurm: Slurm, job: str, timeout: float = 240) -> None:
    def ended() -> bool:
        return not slurm.cmd("squeue", "--noheader", "--jobs", job, "--format=%T").stdout.strip()

    _wait(f"SLURM job {job}", ended, timeout, slurm.logs)


def _run_slurm(env: dict[str, str], config: Path, dest: Path) -> subprocess.CompletedProcess:
    return shiftkit(
        env, "run", str(config), "--executor", "slurm", "--workers", "2", "--partition", "debug",
        "--time", "00:10:00", "--mem-per-cpu", "1", "--no-progress",
    )  # fmt: skip


def test_slurm_job_array_writes_the_local_executors_bytes(slurm, raw, tmp_path):
    local = shiftkit(slurm.env, "run", str(_config(tmp_path, raw, "local")), "--no-progress")
    assert local.returncode == 0
    dest = tmp_path / "slurm"
    config = _config(tmp_path, raw, "slurm")
    submitted = _run_slurm(slurm.env, config, dest)
    assert "submitted SLURM job" in submitted.stderr and not dest.exists()
    job = _job_id(dest)
    _until_job_ends(slurm, job)
    _run_slurm(slurm.env, config, dest)
    assert_same_dataset(tmp_path / "local", dest)


# A third-party stage, installed the way a lab's own package is (a module and its `shiftkit.plugins`
# entry point on the path): it holds each process after its first episode until a file exists, so the
# test cancels a job that is certainly mid-run, however fast or loaded the machine is.
GATE_MODULE = '''"""`gate`: passes episodes unchanged; after `free` of them in a process it waits for `path`."""
import time
from dataclasses import dataclass
from pathlib import Path

from shiftkit.pipelines.stage import FrameStage, register_stage


@dataclass
class GateConfig:
    """Parameters of `gate`."""

    path: str = ""
    """The file whose existence opens the gate."""
    free: int = 1
    """Episodes a process transforms before the gate holds it."""


_transformed = 0


@register_stage
class Gate(FrameStage):
    name = "gate"
    version = 1
    Config = GateConfig

    def transform_features(self, features):
        return features

    def process(self, episode, rng):
        global _transformed
        _transformed += 1
        while _transformed > self.config.free and not Path(self.config.path).exists():
            time.sleep(0.05)
        yield episode
'''


def _install_gate_plugin(root: Path) -> Path:
    root.mkdir()
    (root / "shiftkit_gate.py").write_text(GATE_MODULE)
    info = root / "shiftkit_gate-0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: shiftkit-gate\nVersion: 0\n")
    (info / "entry_points.txt").write_text("[shiftkit.plugins]\ngate = shiftkit_gate\n")
    return root


def test_a_cancelled_slurm_job_resumes_to_the_same_bytes(slurm, raw, tmp_path):
    from shiftkit.pipelines.work import PART_SUFFIX, work_dir_for

    gate = tmp_path / "gate-open"
    env = {**slurm.env, "PYTHONPATH": str(_install_gate_plugin(tmp_path / "plugin"))}
    stages = f"""[[stages]]
name = "gate"
params = {{ path = "{gate}" }}

{FILTER}"""
    gate.touch()
    shiftkit(env, "run", str(write_config(tmp_path, raw, "local", stages)), "--no-progress")
    gate.unlink()
    dest = tmp_path / "slurm"
    config = write_config(tmp_path, raw, "slurm", stages)
    _run_slurm(env, config, dest)
    job = _job_id(dest)
    parts = work_dir_for(dest) / "parts"
    _wait("a first part", lambda: parts.is_dir() and any(parts.glob(f"*.{PART_SUFFIX}")), 240, slurm.logs)
    assert slurm.cmd("scancel", job).returncode == 0
    _until_job_ends(slurm, job)
    done = len(list(parts.glob(f"*.{PART_SUFFIX}")))
    assert 1 <= done <= 2 < EPISODES  # one episode per array task, then held at the gate
    gate.touch()
    resumed = _run_slurm(env, config, dest)
    assert "submitted again" in resumed.stderr, resumed.stderr
    new = _job_id(dest)
    assert new != job
    _until_job_ends(slurm, new)
    _run_slurm(env, config, dest)
    assert_same_dataset(tmp_path / "local", dest)
