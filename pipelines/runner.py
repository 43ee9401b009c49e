"""Run a pipeline: transform episodes in parallel, then write one LeRobot dataset atomically.

Workers run the stages on groups of source episodes (grouped by the file they live in) and store
each finished source episode's outputs as a *part* in a work directory beside the destination.
A part appears atomically (written under a temporary name, then renamed), so after a crash or a
SIGKILL re-running the same command skips every finished episode. When all parts exist, they are
written in source order into a temporary LeRobot dataset that is renamed into place, and the work
directory is removed: the destination holds a complete dataset or nothing.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import logging
import os
import pickle
import shutil
import threading
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from shiftkit.pipelines.config import PipelineConfig
from shiftkit.pipelines.episode import Episode
from shiftkit.pipelines.errors import ShiftkitError
from shiftkit.pipelines.features import check_episode
from shiftkit.pipelines.lerobot_io import require_utf8_path
from shiftkit.pipelines.planner import Plan, plan_pipeline
from shiftkit.pipelines.stage import select_outputs
from shiftkit.pipelines.staging import DestinationLock, remove_dead_staging, sibling

MAX_EPISODES_PER_UNIT = 16


@dataclass(frozen=True)
class WorkUnit:
    """Episodes of one source that a worker processes together (they share a data file)."""

    source: int
    episodes: tuple[int, ...]


def _atomic_pickle(path: Path, obj: Any) -> None:
    tmp = path.with_name(path.name + f".tmp-{os.getpid()}")
    with open(tmp, "wb") as f:
        pickle.dump(obj, f, protocol=pickle.HIGHEST_PROTOCOL)
    os.rename(tmp, path)


class PartStore:
    """Finished per-source-episode outputs in `<dest>/../.<name>.shiftkit-work/parts`.

    One file per source episode holds its output episodes, with their images' PNG bytes, and their
    position-independent statistics, computed by the worker so the writer does not have to. Parts
    are private to one run of one pipeline (the work directory is keyed by `run_key`), so they are
    plain pickles.
    A second, small file per source episode in `metas/` holds just the output metas and the
    stages' event counts for that episode (`Stage.report`; kept even when it has no outputs).
    """

    FORMAT = 2  # of the files; part of `run_key`, so a work dir in another format is not resumed

    def __init__(self, work_dir: Path) -> None:
        self.dir = work_dir / "parts"

    def path(self, source: int, episode: int) -> Path:
        return self.dir / f"s{source:03d}_e{episode:07d}.pkl"

    def done(self, source: int, episode: int) -> bool:
        return self.path(source, episode).is_file()

    def write(
        self, source: int, episode: int, outputs: list[Episode], features: dict, report: list[dict[str, int]]
    ) -> None:
        from shiftkit.pipelines.lerobot_io import encode_images, episode_stats

        records = [(encode_images(ep, features).frames, ep.meta, episode_stats(ep, features)) for ep in outputs]
        for folder in (self.dir, self.meta_path(source, episode).parent):
            folder.mkdir(parents=True, exist_ok=True)
        # The metas alone first: a dataset-level `select` reads them without loading frames, and the
        # part file (whose presence marks the episode done) only appears once both are complete.
        _atomic_pickle(self.meta_path(source, episode), {"metas": [ep.meta for ep in outputs], "report": report})
        _atomic_pickle(self.path(source, episode), records)

    def meta_path(self, source: int, episode: int) -> Path:
        return self.dir.parent / "metas" / self.path(source, episode).name

    def _small(self, source: int, episode: int) -> dict[str, Any]:
        with open(self.meta_path(source, episode), "rb") as f:
            return pickle.load(f)

    def metas(self, source: int, episode: int) -> list[dict[str, Any]]:
        """The metas of one source episode's outputs, without their frames."""
        return self._small(source, episode)["metas"]

    def report(self, source: int, episode: int) -> list[dict[str, int]]:
        """Per stage, the events it counted while processing this source episode."""
        return self._small(source, episode)["report"]

    def read(self, source: int, episode: int) -> Iterator[tuple[Episode, dict]]:
        with open(self.path(source, episode), "rb") as f:
            records = pickle.load(f)
        for frames, meta, stats in records:
            yield Episode(frames, meta), stats


def work_dir_for(destination: Path) -> Path:
    return sibling(destination, "shiftkit-work")


def source_fingerprint(root: Path) -> str:
    """What a source's files are now: every file's relative path, size and modification time, and
    the bytes of its small JSON metadata. A source re-recorded or edited at the same path gets a
    new fingerprint, so its old parts are never mixed with new episodes (a copy without preserved
    times is merely redone)."""
    h = hashlib.sha256()
    for folder, dirs, files in os.walk(root):
        dirs.sort()
        for name in sorted(files):
            path = Path(folder, name)
            st = path.stat()
            h.update(f"{path.relative_to(root)}\0{st.st_size}\0{st.st_mtime_ns}\0".encode("utf-8", "surrogateescape"))
            if name.endswith(".json"):
                h.update(path.read_bytes())
    return h.hexdigest()[:16]


def _files_of(source: Any) -> str | None:
    root = getattr(source, "root", None)
    return source_fingerprint(Path(root)) if root is not None and Path(root).is_dir() else None


def run_key(plan: Plan) -> str:
    """Identifies the job: same config, same source contents, same stage versions -> resumable parts."""
    from shiftkit.pipelines.provenance import versions

    doc = {
        "pipeline": asdict(plan.config),
        "sources": [{**s.describe(), "files": _files_of(s)} for s in plan.sources],
        "stages": [s.describe() for s in plan.stages],
        "source_stages": [[s.describe() for s in own] for own in plan.source_stages],
        "versions": versions(),
        "parts_format": PartStore.FORMAT,
    }
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode()).hexdigest()[:16]


def episode_rng(seed: int, source: int, episode: int, stage: int) -> np.random.Generator:
    """Independent of worker count and order: a function of (seed, source, episode, stage)."""
    return np.random.default_rng([seed, source, episode, stage])


def transform_episode(plan: Plan, source: int, episode: Episode) -> tuple[list[Episode], list[dict[str, int]]]:
    """Run the source's own stages, then the common ones, on one source episode and check the
    outputs against the predicted schema. Returns the outputs and, per stage of that chain, the
    events it counted (`Stage.report`) on the way."""
    index = int(episode.meta["source_episode_index"])
    current = [episode]
    report = []
    # Stage j of the chain draws from the same stream as stage j of that chain run alone.
    for j, stage in enumerate(plan.chain(source)):
        rng = episode_rng(plan.config.seed, source, index, j)
        current = [out for ep in current for out in stage.process(ep, rng)]
        report.append(stage.take_report())
    where = f"source {source} episode {index}"
    for out in current:
        check_episode(out, plan.features, plan.fps, where)
        out.meta.setdefault("source_episode_index", index)
        if len(plan.sources) > 1:
            out.meta["source_index"] = source
    return current, report


@dataclass
class RunReport:
    """What a run counted, read from the parts (so episodes done by other workers or before a
    resume count exactly once): per stage, the totals of its events (`Stage.report`), and per
    source the episodes it contributed to the output."""

    stages: list[dict[str, int]]
    """Per common stage, its event totals over every source episode."""
    source_stages: list[list[dict[str, int]]]
    """Per source, per stage of its own, its event totals over that source's episodes."""
    source_episodes: list[int]
    """Per source, how many output episodes came from it (after any dataset-level selection)."""


def run_report(plan: Plan, parts: PartStore) -> RunReport:
    """The run's counts (`RunReport`) from its finished parts."""
    totals: list[dict[str, int]] = [{} for _ in plan.stages]
    own_totals: list[list[dict[str, int]]] = [[{} for _ in own] for own in plan.source_stages]
    owners, metas = [], []
    for s, source in enumerate(plan.sources):
        for i in range(source.num_episodes):
            for total, counts in zip([*own_totals[s], *totals], parts.report(s, i), strict=True):
                for event, n in counts.items():
                    total[event] = total.get(event, 0) + n
            for meta in parts.metas(s, i):
                owners.append(s)
                metas.append(meta)
    keep = select_outputs(plan.stages, lambda: metas)
    kept = [0] * len(plan.sources)
    for k, s in enumerate(owners):
        kept[s] += keep is None or keep[k]
    return RunReport(
        [dict(sorted(t.items())) for t in totals],
        [[dict(sorted(t.items())) for t in own] for own in own_totals],
        kept,
    )


def exit_with_parent(main_pid: int | None, period: float = 1.0) -> None:
    """In a worker process started by `main_pid`, end the worker when that process dies (even by
    SIGKILL, which gives it no chance to stop its pool): a daemon thread watches the parent pid.
    Nothing happens in the main process itself or in a worker someone else started (Ray)."""
    parent = os.getppid()
    if main_pid is None or os.getpid() == main_pid or parent != main_pid or _WORKER.get("watchdog"):
        return

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(period)
        os._exit(1)

    threading.Thread(target=watch, name="shiftkit-parent-watchdog", daemon=True).start()
    _WORKER["watchdog"] = True


# One plan per worker process: sources opened and stages set up once (docs/executors.md).
_WORKER: dict[str, Any] = {}


def init_worker(config: PipelineConfig, main_pid: int | None = None) -> Plan:
    exit_with_parent(main_pid)
    plan = plan_pipeline(config, check_destination=False)
    for stage in [*(s for own in plan.source_stages for s in own), *plan.stages]:
        stage.setup()
    _WORKER["plan"] = plan
    _WORKER["parts"] = PartStore(work_dir_for(plan.destination))
    return plan


def process_unit(unit: WorkUnit) -> int:
    """Transform the unit's unfinished episodes into parts; returns how many episodes it did."""
    plan: Plan = _WORKER["plan"]
    parts: PartStore = _WORKER["parts"]
    todo = [i for i in unit.episodes if not parts.done(unit.source, i)]
    for episode in plan.sources[unit.source].iter_episodes(todo):
        index = int(episode.meta["source_episode_index"])
        outputs, report = transform_episode(plan, unit.source, episode)
        parts.write(unit.source, index, outputs, plan.features, report)
    return len(todo)


def plan_units(plan: Plan) -> list[WorkUnit]:
    units = []
    for s, source in enumerate(plan.sources):
        for group in source.episode_groups():
            for k in range(0, len(group), MAX_EPISODES_PER_UNIT):
                units.append(WorkUnit(s, tuple(group[k : k + MAX_EPISODES_PER_UNIT])))
    return units


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
    from shiftkit.pipelines.executors import get_executor
    from shiftkit.pipelines.hub import validate_repo_id

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


def _run_locked(config: PipelineConfig, plan: Plan, engine: Any, work: Path, progress: bool) -> Path | None:
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
    with _progress(plan.num_source_episodes, done, "transform", progress) as bar:
        if not engine.run(plan, units, parts, bar):
            return None
    try:
        with _progress(plan.num_source_episodes, 0, "write", progress) as bar:
            path = engine.assemble(plan, parts, bar)
    except ShiftkitError:
        # Every part exists, so the data itself is the problem (e.g. every episode filtered out): the
        # same job fails the same way again and a changed one has another key. Nothing to resume.
        shutil.rmtree(work, ignore_errors=True)
        raise
    shutil.rmtree(work, ignore_errors=True)
    if config.destination.push:
        from shiftkit.pipelines import hub

        # After the atomic rename: a failed push leaves the local dataset for `shiftkit push`.
        result = hub.push_dataset(
            path, plan.repo_id, revision=config.destination.revision, private=config.destination.private
        )
        logging.getLogger("shiftkit").warning("pushed %s to %s", path, result.url)
    return path


def write_dataset(plan: Plan, parts: PartStore, executor_info: dict[str, Any], bar: Any) -> Path:
    from shiftkit.pipelines.lerobot_io import DatasetWriter, lerobot_roots
    from shiftkit.pipelines.provenance import build_provenance

    def outputs() -> Iterator[tuple[Episode, dict]]:
        for s, source in enumerate(plan.sources):
            for i in range(source.num_episodes):
                yield from parts.read(s, i)
                bar.update(1)

    # Dataset-level selection (e.g. N examples per task) sees the metas of all outputs first.
    keep = select_outputs(
        plan.stages,
        lambda: [
            m for s, source in enumerate(plan.sources) for i in range(source.num_episodes) for m in parts.metas(s, i)
        ],
    )
    writer = DatasetWriter(plan.repo_id, plan.destination, plan.fps, plan.features, robot_type=plan.robot_type)
    with writer:
        for k, (episode, stats) in enumerate(outputs()):
            if keep is None or keep[k]:
                writer.add_episode(episode, stats)
        provenance = build_provenance(
            plan, executor_info, writer.num_episodes, writer.num_frames, run_report(plan, parts)
        )
        writer.close(provenance=provenance, carry_from=lerobot_roots(plan.sources))
    return plan.destination


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
