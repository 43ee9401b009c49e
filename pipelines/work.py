"""The unit of work of a pipeline run, shared by the runner and every executor.

A *work unit* is a group of one source's episodes (they share a data file) that one worker
transforms. A worker (`init_worker` in a process of its own, `set_up_worker` in the main process)
holds one plan, built once per process, and turns each unfinished episode of a unit into a *part*
in the run's `PartStore`, the work directory beside the destination. A part appears atomically
(written under a temporary name, then renamed), so a run killed at any point resumes at the first
episode without a part. `run_key` names the job the parts belong to.
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing
import os
import threading
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from shiftkit.datasets import data_tree, video
from shiftkit.datasets.episode import Episode
from shiftkit.datasets.features import check_episode
from shiftkit.datasets.staging import sibling
from shiftkit.pipelines.config import PipelineConfig
from shiftkit.pipelines.planner import Plan, plan_pipeline
from shiftkit.pipelines.stage import check_output

MAX_EPISODES_PER_UNIT = 16
PART_SUFFIX = "tree"
"""The file suffix of parts (`data_tree.save_tree`)."""


@dataclass(frozen=True)
class WorkUnit:
    """Episodes of one source that a worker processes together (they share a data file)."""

    source: int
    episodes: tuple[int, ...]


def _atomic_save(path: Path, obj: Any) -> None:
    tmp = path.with_name(path.name + f".tmp-{os.getpid()}")
    with open(tmp, "wb") as f:
        data_tree.save_tree(f, obj)
    os.rename(tmp, path)


class PartStore:
    """Finished per-source-episode outputs in `<dest>/../.<name>.shiftkit-work/parts`.

    One file per source episode holds its output episodes, with their images' PNG bytes, and their
    position-independent statistics, computed by the worker so the writer does not have to. Parts
    are data, not code: plain arrays and a JSON document in a tree file (`datasets/data_tree.py`),
    so a work folder someone copied or sent cannot run code on resume.
    A second, small file per source episode in `metas/` holds just the output metas and the
    stages' event counts for that episode (`Stage.report`; kept even when it has no outputs).
    """

    FORMAT = 5  # of the files; part of `run_key`, so a work dir in another format is not resumed

    def __init__(self, work_dir: Path) -> None:
        self.dir = work_dir / "parts"

    def path(self, source: int, episode: int) -> Path:
        """The part file of one source episode."""
        return self.dir / f"s{source:03d}_e{episode:07d}.{PART_SUFFIX}"

    def done(self, source: int, episode: int) -> bool:
        """Whether that source episode is finished (its part file exists)."""
        return self.path(source, episode).is_file()

    def write(
        self,
        source: int,
        episode: int,
        outputs: list[Episode],
        features: dict,
        fps: int,
        report: list[dict[str, int]],
        copied: frozenset[str] = frozenset(),
    ) -> None:
        """Store one source episode's outputs (images and videos encoded, with their statistics) and
        the stages' event counts, the metas first; the part file appears last, marking it done.
        `copied`: the video features the writer copies from their sources (`Plan.video_copies`)."""
        from shiftkit.datasets.images import encode_images
        from shiftkit.datasets.stats import episode_stats

        records = []
        for i, ep in enumerate(outputs):
            stats = episode_stats(ep, features)  # from the frames, before they are encoded
            videos = self._encode_videos(ep, features, fps, self.videos_dir(source, episode) / str(i), copied)
            records.append((encode_images(ep, features).with_frames(**videos).frames, ep.meta, stats))
        for folder in (self.dir, self.meta_path(source, episode).parent):
            folder.mkdir(parents=True, exist_ok=True)
        # The metas alone first: a dataset-level `select` reads them without loading frames, and the
        # part file (whose presence marks the episode done) only appears once both are complete.
        _atomic_save(self.meta_path(source, episode), {"metas": [ep.meta for ep in outputs], "report": report})
        _atomic_save(self.path(source, episode), records)

    def videos_dir(self, source: int, episode: int) -> Path:
        """The folder of that source episode's outputs' encoded video files."""
        return self.dir.parent / "videos" / self.path(source, episode).stem

    @staticmethod
    def _encode_videos(ep: Episode, features: dict, fps: int, folder: Path, copied: frozenset[str]) -> dict[str, Any]:
        """The episode's video cameras that the writer does not copy, each encoded into a file in
        `folder`: encoding runs in the workers, and the part holds the file's name instead of the
        pixels. A camera still encoded at its source (`VideoRef`) is transcoded from the decoder's
        pixels (`Plan.video_transcodes`)."""
        from shiftkit.datasets.video import encode_episode_video, transcode_episode
        from shiftkit.datasets.video_copy import VideoRef

        videos = {}
        for key, ft in features.items():
            frames = ep.frames.get(key)
            if ft["dtype"] != "video" or key in copied:
                continue
            if isinstance(frames, VideoRef):
                videos[key] = transcode_episode(
                    frames.path, frames.start, frames.timestamps, ft, fps, folder / f"{key}.mp4"
                )
            else:
                videos[key] = encode_episode_video(frames, ft, fps, folder / f"{key}.mp4")
        return videos

    def meta_path(self, source: int, episode: int) -> Path:
        """The small file with that source episode's metas and event counts."""
        return self.dir.parent / "metas" / self.path(source, episode).name

    def _small(self, source: int, episode: int) -> dict[str, Any]:
        return data_tree.load_tree(self.meta_path(source, episode))

    def metas(self, source: int, episode: int) -> list[dict[str, Any]]:
        """The metas of one source episode's outputs, without their frames."""
        return self._small(source, episode)["metas"]

    def report(self, source: int, episode: int) -> list[dict[str, int]]:
        """Per stage, the events it counted while processing this source episode."""
        return self._small(source, episode)["report"]

    def read(self, source: int, episode: int) -> Iterator[tuple[Episode, dict]]:
        """That source episode's output episodes, each with its statistics."""
        for frames, meta, stats in data_tree.load_tree(self.path(source, episode)):
            yield Episode(frames, meta), stats


def work_dir_for(destination: Path) -> Path:
    """The work directory of a run to `destination` (a hidden sibling folder)."""
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
    from shiftkit.datasets.provenance import versions

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
        # each output knows the source frame each of its frames stands for (Episode.follow); a frame
        # stage's keeps its input's (check_output)
        outputs = []
        for ep in current:
            for out in stage.process(ep, rng):
                check_output(stage, out.follow(ep, stage.name), ep)
                outputs.append(out)
        current = outputs
        report.append(stage.take_report())
    where = f"source {source} episode {index}"
    for out in current:
        check_episode(out, plan.features, plan.fps, where)
        out.meta.setdefault("source_episode_index", index)
        if len(plan.sources) > 1:
            out.meta["source_index"] = source
    return current, report


def exit_with_parent(main_pid: int | None, period: float = 1.0) -> None:
    """In a worker process started by `main_pid`, end the worker when that process dies (even by
    SIGKILL, which gives it no chance to stop its pool): a daemon thread watches the parent pid.
    Nothing happens in the main process itself or in a worker someone else started (Ray)."""
    parent = os.getppid()
    if main_pid is None or os.getpid() == main_pid or _WORKER.get("watchdog"):
        return
    if parent != main_pid:
        spawner = multiprocessing.parent_process()
        if spawner is not None and spawner.pid == main_pid:
            os._exit(1)  # spawned by `main_pid`, which died while this worker was starting
        return

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(period)
        os._exit(1)

    threading.Thread(target=watch, name="shiftkit-parent-watchdog", daemon=True).start()
    _WORKER["watchdog"] = True


# One plan per worker process: sources opened and stages set up once (docs/executors.md).
_WORKER: dict[str, Any] = {}


def init_worker(config: PipelineConfig, main_pid: int | None = None, answers: dict[str, Any] | None = None) -> Plan:
    """Set up a worker process (a pool's, a datatrove task's): its own plan, its stages set up.
    `answers`: its main process's `worker_answers`."""
    exit_with_parent(main_pid)
    video.take_answers(answers or {})
    return set_up_worker(plan_pipeline(config, worker=True))


def worker_answers(plan: Plan) -> dict[str, Any]:
    """What the workers of `plan` would otherwise ask lerobot, resolved in this process (which has
    it loaded): the codec of each camera they may encode (the output's encoded cameras, the sources'
    cameras read encoded: cut or transcoded). A worker given them imports neither lerobot nor torch
    unless a stage or depth video needs them (`video.codec_for`)."""
    for key, ft in plan.features.items():
        if ft["dtype"] == "video" and key not in plan.video_copies:
            video.codec_for(ft)
    for i, source in enumerate(plan.sources):
        for key in plan.video_refs(i):
            video.codec_for(source.features[key])
    return video.answers()


def set_up_worker(plan: Plan) -> Plan:
    """Make this process a worker of `plan` (the main process passes the plan it already built)."""
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
    refs = plan.video_refs(unit.source)  # cameras copied, not decoded (datasets/video_copy.py)
    episodes = plan.sources[unit.source].iter_episodes(todo, **({"video_refs": refs} if refs else {}))
    for episode in episodes:
        index = int(episode.meta["source_episode_index"])
        outputs, report = transform_episode(plan, unit.source, episode)
        parts.write(unit.source, index, outputs, plan.features, plan.fps, report, frozenset(plan.video_copies))
    return len(todo)


def plan_units(plan: Plan) -> list[WorkUnit]:
    """The run's work units, in source order: each source's episode groups, split at
    `MAX_EPISODES_PER_UNIT` episodes."""
    units = []
    for s, source in enumerate(plan.sources):
        for group in source.episode_groups():
            for k in range(0, len(group), MAX_EPISODES_PER_UNIT):
                units.append(WorkUnit(s, tuple(group[k : k + MAX_EPISODES_PER_UNIT])))
    return units
