"""The Ray executor on a two-node Ray cluster started on this machine (`ray start --head` and a
second `ray start --address` node, 1 CPU each): `shiftkit run --executor ray --ray-address` runs
tasks on both nodes (the provenance counts them) and writes the local executor's bytes.

The nodes are stopped by ending the process groups this test started, not with `ray stop`, which
would also stop every other Ray instance of this user on the machine."""

from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.test_cluster_slurm import _free_port, _wait
from tests.test_executors import assert_same_dataset, write_config

pytestmark = pytest.mark.cluster

# 40 episodes: three shards of at most 16, so both tasks (one per 1-CPU node) have work.
EPISODES = 40


def _ports() -> list[str]:
    names = ("node-manager-port", "object-manager-port", "metrics-export-port", "runtime-env-agent-port")
    names += ("dashboard-agent-listen-port", "dashboard-agent-grpc-port")
    return [f"--{n}={_free_port()}" for n in names]


class RayCluster:
    """A head and one more node, each `ray start --block` in a process group of its own."""

    def __init__(self, root: Path) -> None:
        self.root = root
        from ray.util import get_node_ip_address

        self.port = _free_port()
        # Ray's nodes listen on this machine's address (as on a real cluster), not on loopback.
        self.address = f"{get_node_ip_address()}:{self.port}"
        # Token authentication (Ray's default once a token exists) with a token of this cluster's
        # own: the nodes and every driver, shiftkit's included, read it from RAY_AUTH_TOKEN_PATH.
        token = root / "auth_token"
        token.write_text(secrets.token_hex(32))
        token.chmod(0o600)
        self.env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0", "RAY_AUTH_MODE": "token"}
        self.env["RAY_AUTH_TOKEN_PATH"] = str(token)
        for name in ("RAY_ADDRESS", "RAY_AUTH_TOKEN"):
            self.env.pop(name, None)
        self.procs: list[subprocess.Popen] = []
        # Short: Ray's socket paths inside it must fit AF_UNIX's 107 bytes (pytest's folders do not).
        self.temp = Path(tempfile.mkdtemp(prefix="skray-", dir="/tmp"))

    def _start(self, name: str, args: list[str], workers: int) -> None:
        log = open(self.root / f"{name}.log", "wb")  # noqa: SIM115  (kept open while the node runs)
        ray = str(Path(sys.executable).with_name("ray"))
        ports = [f"--min-worker-port={workers}", f"--max-worker-port={workers + 99}", *_ports()]
        cmd = [ray, "start", "--block", "--num-cpus=1", "--disable-usage-stats", *ports, *args]
        self.procs.append(
            subprocess.Popen(cmd, env=self.env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        )

    def nodes(self) -> int:
        """The cluster's live nodes, or 0 while it cannot be reached."""
        probe = "import ray; ray.init(address=%r, logging_level='ERROR'); print(len([n for n in ray.nodes() if n['Alive']]))"
        try:
            proc = subprocess.run(
                [sys.executable, "-c", probe % self.address], env=self.env, capture_output=True, text=True, timeout=60
            )
        except subprocess.TimeoutExpired:
            # A driver that connects while the head's GCS is still starting can wait out the
            # GCS reconnect timeout; that is "not ready yet", asked again by the caller.
            return 0
        return int(proc.stdout.strip().splitlines()[-1]) if proc.returncode == 0 and proc.stdout.strip() else 0

    def start(self) -> None:
        temp = self.temp  # Ray's session folder; shared by the nodes of one machine
        self._start(
            "head",
            ["--head", f"--port={self.port}", "--include-dashboard=false", f"--temp-dir={temp}",
             f"--ray-client-server-port={_free_port()}"],
            21000,
        )  # fmt: skip
        logs = (self.root / "head.log", self.root / "node.log")
        _wait("the Ray head", lambda: self.nodes() == 1, 300, logs, period=1)
        self._start("node", [f"--address={self.address}"], 21200)
        _wait("the second Ray node", lambda: self.nodes() == 2, 300, logs, period=1)

    def stop(self) -> None:
        for proc in reversed(self.procs):
            for sig, wait in ((signal.SIGTERM, 20), (signal.SIGKILL, 10)):
                try:
                    os.killpg(proc.pid, sig)
                except ProcessLookupError:
                    break
                try:
                    proc.wait(wait)
                except subprocess.TimeoutExpired:
                    continue
                # The node's daemons (raylet, GCS, workers) share the group: end any left.
                try:
                    os.killpg(proc.pid, sig)
                except ProcessLookupError:
                    break
        shutil.rmtree(self.temp, ignore_errors=True)


@pytest.fixture(scope="module")
def ray_cluster(tmp_path_factory) -> Iterator[RayCluster]:
    pytest.importorskip("ray")
    cluster = RayCluster(tmp_path_factory.mktemp("raycluster"))
    try:
        cluster.start()
        yield cluster
    finally:
        cluster.stop()


def test_ray_cluster_runs_tasks_on_both_nodes_and_writes_the_local_bytes(ray_cluster, tmp_path):
    from shiftkit.datasets.synthetic import write_synthetic_raw

    raw = write_synthetic_raw(tmp_path / "raw", episodes=EPISODES, length=6, seed=4, camera=(12, 16))
    configs = {name: write_config(tmp_path, raw, name) for name in ("local", "ray")}
    env = ray_cluster.env
    for args in (["run", str(configs["local"])], ["run", str(configs["ray"]), "--executor", "ray", "--workers", "2",
                                                    "--ray-address", ray_cluster.address]):  # fmt: skip
        proc = subprocess.run(
            [sys.executable, "-m", "shiftkit.app.cli", *args, "--no-progress"],
            env=env,
            capture_output=True,
            text=True,
            timeout=600,  # a quiet run takes ~30 s per command, ~100 s at load 15 on 2 cores
        )
        assert proc.returncode == 0, proc.stderr[-3000:]
    assert_same_dataset(tmp_path / "local", tmp_path / "ray")
    executor = json.loads((tmp_path / "ray" / "meta/shiftkit_provenance.json").read_text())["executor"]
    assert executor == {"name": "ray", "workers": 2, "address": ray_cluster.address, "nodes": 2}
