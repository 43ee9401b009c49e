"""Where a pipeline run with N workers spends its time: shared by the benches that compare 1 and 2
workers (`executors`, `force_match`, `multiview`). Not a bench itself (`all.sh` skips `_*.py`).

A bench-only stage, `bench-stamp`, records in each episode's metadata the wall-clock time and the
worker's pid when the episode reached it; a pipeline wrapped in two of them (`stamped`) tells, per
source episode, when a worker started and finished it. `breakdown` turns those stamps into the
start-up (run start to the first episode started: spawning, imports, the stages' set-up), the
processing span (first start to last end), the write after it, and what keeps a 2-worker span above
half the 1-worker one: workers starting apart (`start_spread`), work falling unevenly on them
(`busy_imbalance`: the busiest worker's busy time minus the mean) and each episode taking longer
(`episode`: mean seconds per source episode). The local executor's spawned workers re-import the
bench's main module, which imports this one, so they know the stage too.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from shiftkit.datasets.episode import Episode
from shiftkit.datasets.features import Features
from shiftkit.pipelines.stage import Stage, register_stage

START, END = "bench_start", "bench_end"


@dataclasses.dataclass
class StampConfig:
    key: str = START
    """Episode metadata key that receives [wall-clock time, worker pid] when the episode reaches this stage."""


@register_stage
class Stamp(Stage):
    """Record when, and in which process, an episode reaches this point of the pipeline (bench-only)."""

    name = "bench-stamp"
    version = 1
    Config = StampConfig

    def transform_features(self, features: Features) -> Features:
        return features

    def process(self, episode: Episode, rng: np.random.Generator) -> Iterable[Episode]:
        yield Episode(episode.frames, {**episode.meta, self.config.key: [time.time(), os.getpid()]})


def stamped(stages: list) -> list:
    """`stages` (StageSpecs) between a start and an end stamp."""
    from shiftkit.pipelines.config import StageSpec

    return [
        StageSpec(name="bench-stamp", params={"key": START}),
        *stages,
        StageSpec(name="bench-stamp", params={"key": END}),
    ]


def breakdown(start: np.ndarray, end: np.ndarray, pid: np.ndarray, t0: float, total: float) -> dict[str, float]:
    """The run's time split (see the module doc) from per-source-episode start / end times and pids."""
    busy = [float((end - start)[pid == p].sum()) for p in np.unique(pid)]
    first = [float(start[pid == p].min()) for p in np.unique(pid)]
    return {
        "total": total,
        "startup": float(start.min()) - t0,
        "span": float(end.max() - start.min()),
        "write": t0 + total - float(end.max()),
        "workers_used": len(busy),
        "start_spread": max(first) - min(first),
        "busy_imbalance": max(busy) - float(np.mean(busy)),
        "episode": float(np.mean(end - start)),
    }


def timed_run(config, workers: int) -> dict[str, float]:
    """Run a pipeline built with `stamped` stages in this process (local executor) and return its
    `breakdown`.

    A stage that makes several episodes of one (multiview's views) gives them the same start stamp:
    they count as one source episode, finished when its last output passed the end stamp."""
    from shiftkit.datasets.episode import META_COLUMN
    from shiftkit.datasets.reader import open_lerobot_dataset
    from shiftkit.pipelines.runner import run_pipeline

    t0 = time.time()
    dest = run_pipeline(config, workers=workers, progress=False)
    total = time.time() - t0
    source_episodes: dict[tuple[float, int], float] = {}
    for meta in open_lerobot_dataset(Path(dest)).episodes[META_COLUMN]:
        m = json.loads(meta)
        key = (m[START][0], m[START][1])
        source_episodes[key] = max(source_episodes.get(key, 0.0), m[END][0])
    keys = list(source_episodes)
    start = np.array([k[0] for k in keys])
    pid = np.array([k[1] for k in keys])
    end = np.array([source_episodes[k] for k in keys])
    return breakdown(start, end, pid, t0, total)


def describe(label: str, t: dict[str, float], episodes: int) -> str:
    """One line of a run's time split, for the bench's output ("LABEL: ...")."""
    return (
        f"{label}: {t['total']:6.2f} s = start-up {t['startup']:5.2f} + span {t['span']:6.2f} "
        f"+ write {t['write']:5.2f} ({episodes / t['span']:.3f} episodes/s in the span; workers started "
        f"{t['start_spread']:.2f} s apart, busiest {t['busy_imbalance']:.2f} s over the mean, "
        f"{t['episode']:.2f} s per episode)"
    )
