"""`success_examples`: reduce trajectories to per-task sets of success states (VPACE / LfGP examples).

Input: reset-based episodes (one task each) or play episodes whose `meta["segments"]` label task
segments, with the per-frame `next.success` flag that `shiftkit collect` records. Every state in
which a task is complete becomes a *candidate*: a one-frame output episode whose `task` is that
task, with a random selection key drawn from the episode's seeded rng. After all episodes are
transformed, `select` keeps the `n_per_task` candidates with the smallest keys per task, so the
choice is a seeded uniform sample over the whole dataset, independent of worker count.

Frame convention (LeRobot): frame t holds the observation before action t, and `next.success[t]`
says whether the state after action t succeeds, which is frame t + 1. The state after an episode's
last action is not recorded; the last frame stands in for it (see docs/success_examples.md).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, Literal, override

import numpy as np

from shiftkit.datasets.dataclass_config import check_fields, option
from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import ConfigError, DatasetError
from shiftkit.datasets.features import Features
from shiftkit.pipelines.stage import Reindex, ReindexStage, register_stage
from shiftkit.transforms import papers

log = logging.getLogger(__name__)

SUCCESS_KEY = "next.success"


@dataclass
class SuccessExamplesConfig:
    """Parameters of `success_examples`."""

    n_per_task: int | None = option(200, rule="positive_int")
    """Examples kept per task, a seeded uniform sample of all candidates in the dataset (thesis: 200 in
    simulation, 50 real); None keeps every candidate."""
    states: Literal["final", "success"] = "final"
    """Which states are candidates: "final" = the state s_T in which a reset-based episode or a play
    segment first succeeds (one per successful episode / segment); "success" = every recorded state
    whose success flag holds (several per episode)."""
    tasks: list[str] | None = None
    """Make examples only for these tasks (main and auxiliary); None: every task found."""

    def __post_init__(self) -> None:
        check_fields(self)


@register_stage
class SuccessExamples(ReindexStage):
    """Turns each success state into a one-frame candidate episode; `select` keeps a seeded `n_per_task` of them per task."""

    name = "success_examples"
    version = 2  # v2: an example keeps its camera metadata; language rows' times follow it
    citation = papers.VPACE
    example_params = {"n_per_task": 3, "states": "success"}
    Config = SuccessExamplesConfig

    @override
    def transform_features(self, features: Features) -> Features:
        ft = features.get(SUCCESS_KEY)
        if ft is None or ft["dtype"] != "bool" or tuple(ft["shape"]) != (1,):
            raise ConfigError(
                f"success_examples needs a per-frame bool {SUCCESS_KEY!r} feature (as `shiftkit collect` records)"
            )
        return features

    @override
    def reindex(self, episode: Episode, rng: np.random.Generator) -> Iterable[Reindex]:
        n = len(episode)
        success = np.asarray(episode.frames[SUCCESS_KEY]).reshape(n)
        frames: list[int] = []
        tasks: list[str] = []
        for task, start, end in _task_spans(episode):
            if self.config.tasks is not None and task not in self.config.tasks:
                continue
            picked = _candidate_frames(success, start, end, self.config.states)
            frames += picked
            tasks += [task] * len(picked)
        keys = rng.random(len(frames))  # drawn for every candidate: keys never depend on `tasks`
        # Where each example comes from; nested because a reader reusing this dataset as a source
        # renumbers the top-level `source_episode_index`. The cameras stay where the writer keeps
        # them (meta/cameras.json): they describe the example's images.
        source = {k: v for k, v in episode.meta.items() if k not in ("segments", "cameras")}
        cameras = {"cameras": episode.meta["cameras"]} if episode.meta.get("cameras") else {}
        for frame, task, key in zip(frames, tasks, keys, strict=True):
            meta = {"task": task, "selection_key": float(key), "source": {**source, "frame_index": int(frame)}}
            # one frame standing for itself (language rows' times move with it to 0)
            yield Reindex(
                np.array([frame]),
                np.zeros(1),
                frames={"task": np.array([task])},
                cover=(frame, frame + 1),
                meta={**meta, **cameras},
            )

    @override
    def carried_features(self, features: Features) -> dict[str, str]:
        # an example's task is its segment's, which the frame after the segment may not have
        return {k: v for k, v in super().carried_features(features).items() if k != "task"}

    @override
    def select(self, metas: list[dict[str, Any]]) -> list[bool] | None:
        n = self.config.n_per_task
        if n is None:
            return None
        by_task: dict[str, list[tuple[float, int]]] = {}
        for k, meta in enumerate(metas):
            if "selection_key" not in meta:
                raise DatasetError(f"success_examples: output episode {k} lost its 'selection_key' metadata")
            by_task.setdefault(meta["task"], []).append((meta["selection_key"], k))
        keep = [False] * len(metas)
        for task, candidates in by_task.items():
            if len(candidates) < n:
                log.warning(
                    "success_examples: task %r has only %d candidate(s) for %d examples", task, len(candidates), n
                )
            for _, k in sorted(candidates)[:n]:  # ties (practically impossible) fall back to output order
                keep[k] = True
        return keep


def _task_spans(episode: Episode) -> list[tuple[str, int, int]]:
    """(task, start, end) of each labelled play segment, or of the whole reset-based episode."""
    segments = episode.meta.get("segments") or []
    if segments:
        return [(str(s["task"]), int(s["start"]), int(s["end"])) for s in segments]
    return [(str(episode.frames["task"][-1]), 0, len(episode))]


def _candidate_frames(success: np.ndarray, start: int, end: int, states: str) -> list[int]:
    """Frames holding the success states of the span [start, end).

    The state after action t is frame t + 1; after the episode's last action the last frame stands in.
    """
    last = len(success) - 1
    if states == "final":
        return [min(end, last)] if end > start and success[end - 1] else []
    return sorted({min(t + 1, last) for t in range(start, end) if success[t]})
