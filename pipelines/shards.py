"""Shards: the datatrove executors' grouping of work units, and the datatrove step that runs them.

The work units of a run are packed into *shards* (consecutive units, at most `shard_episodes`
source episodes each), a grouping that does not depend on the number of workers. Each datatrove
task (rank) takes every `world_size`-th unfinished shard and transforms its episodes into the
run's part store, the same parts the local executor's workers write (so a resumed run skips
finished episodes, whichever executor made them). A failing shard is retried (`attempts` in all,
with freshly set-up stages); one that keeps failing leaves a failure record naming the episode and
the reason. Each task that transformed a shard records the node it ran on (the Ray node, else the
host), so the provenance can say how many machines did the work.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import socket
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, override

from datatrove.pipeline.base import PipelineStep

from shiftkit.datasets.errors import DatasetError
from shiftkit.pipelines import work
from shiftkit.pipelines.stage import STAGES, Stage, register_stage
from shiftkit.pipelines.work import PartStore, WorkUnit

_LOG = logging.getLogger("shiftkit")


@dataclass(frozen=True)
class Shard:
    """Consecutive work units that one task transforms (and retries) together."""

    index: int
    units: tuple[WorkUnit, ...]

    @property
    def episodes(self) -> list[tuple[int, int]]:
        """The shard's (source, episode) pairs, in order."""
        return [(u.source, i) for u in self.units for i in u.episodes]

    def done(self, parts: PartStore) -> bool:
        """Whether every episode of the shard has its part."""
        return all(parts.done(s, i) for s, i in self.episodes)

    def describe(self) -> str:
        """The shard in words, from its first to its last episode (for failure reports)."""
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


class FailureStore:
    """The failure records of shards that kept failing, in `<work dir>/failures`."""

    def __init__(self, work_dir: Path) -> None:
        self.dir = work_dir / "failures"

    def _path(self, k: int) -> Path:
        return self.dir / f"{k:05d}.json"

    def record(self, k: int, where: str, reason: str, attempts: int) -> None:
        """Record that shard `k` failed `attempts` times, at `where` for `reason` (atomically)."""
        self.dir.mkdir(parents=True, exist_ok=True)
        tmp = self._path(k).with_suffix(f".tmp-{os.getpid()}")
        tmp.write_text(json.dumps({"where": where, "reason": reason, "attempts": attempts}))
        os.rename(tmp, self._path(k))

    def clear(self, k: int) -> None:
        """Forget shard `k`'s failure (it succeeded)."""
        self._path(k).unlink(missing_ok=True)

    def get(self, k: int) -> dict[str, Any] | None:
        """Shard `k`'s failure record, or None."""
        path = self._path(k)
        return json.loads(path.read_text()) if path.is_file() else None

    def clean(self) -> None:
        """Forget the failures of earlier attempts: a new attempt starts."""
        shutil.rmtree(self.dir, ignore_errors=True)

    def message(self, shards: list[Shard]) -> str | None:
        """One line naming the failed episodes of `shards` and why, or None when none failed."""
        failures = [f for f in (self.get(s.index) for s in shards) if f is not None]
        if not failures:
            return None
        what = "; ".join(f"{f['where']}: {f['reason']}" for f in failures)
        return f"{len(failures)} of {len(shards)} shards failed {failures[0]['attempts']} times: {what}"


class ShardStep(PipelineStep):
    """The datatrove pipeline step: transforms the unfinished shards of its rank into parts."""

    name = "shiftkit shards"
    type = "🤖 - SHIFTKIT"

    def __init__(
        self, config: Any, shards: list[Shard], attempts: int, stage_classes: list[type[Stage]], answers: dict[str, Any]
    ) -> None:
        super().__init__()
        self.config = config
        self.answers = answers  # work.worker_answers: what the tasks need not import lerobot for
        self.shards = shards
        self.attempts = attempts
        # The stage classes travel with the step, so stages registered outside shiftkit's own
        # packages (a plugin, a script's __main__) exist on Ray workers too.
        self.stage_classes = stage_classes
        self.main_pid = os.getpid()  # workers of a local pool exit when this process dies

    @override
    def run(self, data: Any = None, rank: int = 0, world_size: int = 1) -> Any:
        work.exit_with_parent(getattr(self, "main_pid", None))
        for cls in self.stage_classes:
            if cls.name not in STAGES:
                register_stage(cls)
        work_dir = work.work_dir_for(Path(self.config.destination.root))
        parts, failures = PartStore(work_dir), FailureStore(work_dir)
        plan = None
        failed = []
        for shard in self.shards[rank::world_size]:
            if shard.done(parts):  # finished by an earlier, killed or cancelled, run of this task
                continue
            for attempt in range(1, self.attempts + 1):
                try:
                    if plan is None:  # set up once per rank, and again after a failure
                        plan = work.init_worker(self.config, answers=self.answers)
                    for unit in shard.units:
                        self.stat_update("episodes", value=work.process_unit(unit))
                    failures.clear(shard.index)
                    record_node(work_dir, rank)
                    self.stat_update("shards")
                    break
                except Exception as exc:
                    plan = None
                    where = next((f"source {s} episode {i}" for s, i in shard.episodes if not parts.done(s, i)), "?")
                    reason = f"{type(exc).__name__}: {exc}".splitlines()[0]
                    _LOG.warning(
                        "%s, attempt %d/%d failed at %s: %s", shard.describe(), attempt, self.attempts, where, reason
                    )
                    self.stat_update("failed_attempts")
                    if attempt == self.attempts:
                        failures.record(shard.index, where, reason, attempt)
                        failed.append(shard.index)
        if failed:
            raise DatasetError(f"shards {failed} failed {self.attempts} times (records in {failures.dir})")
        return data


# The Ray node id of a process that a Ray worker spawned (`datatrove_executor.spawn_rank_pools`).
RAY_NODE_VAR = "SHIFTKIT_RAY_NODE_ID"


def _node() -> str:
    """This worker's node: its Ray node id on a Ray cluster, else the host name."""
    if RAY_NODE_VAR in os.environ:
        return os.environ[RAY_NODE_VAR]
    ray = sys.modules.get("ray")  # a Ray worker has imported it; nothing else needs to
    if ray is not None and ray.is_initialized():
        return ray.get_runtime_context().get_node_id()
    return socket.gethostname()


def record_node(work_dir: Path, rank: int) -> None:
    """Note that task `rank` transformed a shard on this node (one small file per rank and node)."""
    folder = work_dir / "nodes"
    folder.mkdir(parents=True, exist_ok=True)
    node = _node()
    (folder / f"{rank:05d}-{hashlib.sha256(node.encode()).hexdigest()[:16]}").write_text(node)


def nodes_used(work_dir: Path) -> int:
    """How many distinct nodes transformed shards of this run (earlier, resumed attempts included)."""
    folder = work_dir / "nodes"
    return len({p.read_text() for p in folder.iterdir()}) if folder.is_dir() else 0
