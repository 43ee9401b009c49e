"""Write the destination dataset from a run's parts: one ordered pass, the same for every executor.

Parts are read in source order and each output episode is written once into a temporary LeRobot
dataset (renamed into place by the writer), with the statistics that depend on an episode's place
computed as it goes. A dataset-level `select` (`Stage.select`) sees every output's meta first, and
the run's event counts (`RunReport`) are summed from the parts, so episodes done by other workers,
machines or before a resume count exactly once.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from shiftkit.datasets.episode import Episode
from shiftkit.datasets.provenance import make_provenance
from shiftkit.pipelines.config import config_record
from shiftkit.pipelines.planner import Plan
from shiftkit.pipelines.stage import select_outputs
from shiftkit.pipelines.work import PartStore


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


def _output_metas(plan: Plan, parts: PartStore) -> Iterator[tuple[int, dict[str, Any]]]:
    """(source, meta) of every output episode, in the order the writer meets them."""
    for s, source in enumerate(plan.sources):
        for i in range(source.num_episodes):
            for meta in parts.metas(s, i):
                yield s, meta


def selection(plan: Plan, parts: PartStore) -> list[bool] | None:
    """Which output episodes the dataset keeps (a dataset-level `select`, e.g. N examples per task,
    sees the metas of all outputs first); None when every one is kept."""
    return select_outputs(plan.stages, lambda: [meta for _, meta in _output_metas(plan, parts)])


def run_report(plan: Plan, parts: PartStore, keep: list[bool] | None) -> RunReport:
    """The run's counts (`RunReport`) from its finished parts, given the `selection`."""
    totals: list[dict[str, int]] = [{} for _ in plan.stages]
    own_totals: list[list[dict[str, int]]] = [[{} for _ in own] for own in plan.source_stages]
    for s, source in enumerate(plan.sources):
        for i in range(source.num_episodes):
            for total, counts in zip([*own_totals[s], *totals], parts.report(s, i), strict=True):
                for event, n in counts.items():
                    total[event] = total.get(event, 0) + n
    kept = [0] * len(plan.sources)
    for k, (s, _) in enumerate(_output_metas(plan, parts)):
        kept[s] += keep is None or keep[k]
    return RunReport(
        [dict(sorted(t.items())) for t in totals],
        [[dict(sorted(t.items())) for t in own] for own in own_totals],
        kept,
    )


def write_dataset(plan: Plan, parts: PartStore, executor_info: dict[str, Any], bar: Any) -> Path:
    """Write `plan.destination` from the finished `parts` (every executor's), atomically; returns it."""
    from shiftkit.datasets.writer import DatasetWriter, lerobot_roots

    def outputs() -> Iterator[tuple[Episode, dict]]:
        for s, source in enumerate(plan.sources):
            for i in range(source.num_episodes):
                yield from parts.read(s, i)
                bar.update(1)

    keep = selection(plan, parts)
    writer = DatasetWriter(plan.repo_id, plan.destination, plan.fps, plan.features, robot_type=plan.robot_type)
    with writer:
        for k, (episode, stats) in enumerate(outputs()):
            if keep is None or keep[k]:
                writer.add_episode(episode, stats)
        provenance = build_provenance(
            plan, executor_info, writer.num_episodes, writer.num_frames, run_report(plan, parts, keep)
        )
        if writer.video_modes:  # per video feature: "copied" from the source's packets or "encoded"
            provenance["video"] = dict(sorted(writer.video_modes.items()))
        writer.close(provenance=provenance, carry_from=lerobot_roots(plan.sources))
    return plan.destination


def build_provenance(
    plan: Any, executor: dict[str, Any], num_episodes: int, num_frames: int, report: Any
) -> dict[str, Any]:
    """A pipeline run's provenance. `report` (`assembly.RunReport`): the run's totals of the events
    each stage counted (`Stage.report`), stored as the stage entry's "report" when it counted any,
    and the output episodes per source. Each source entry records its fps, its own stages and
    the range of output episodes it became (`episodes`: [first, end)) and, where its depth is stored
    in another unit, which (`depth_units`: feature -> [source unit, output unit])."""
    sources, start = [], 0
    for s, source in enumerate(plan.sources):
        count = report.source_episodes[s]
        converted = plan.depth_units(s)  # depth stored in another unit than the source's
        sources.append(
            {
                **source.describe(),
                "fps": source.fps,
                "stages": _stage_entries(plan.source_stages[s], report.source_stages[s]),
                "episodes": [start, start + count],
                **({"depth_units": converted} if converted else {}),
            }
        )
        start += count
    return make_provenance(
        repo_id=plan.repo_id,
        fps=plan.fps,
        num_episodes=num_episodes,
        num_frames=num_frames,
        sources=sources,
        stages=_stage_entries(plan.stages, report.stages),
        seed=plan.config.seed,
        executor=executor,
        # The pipeline config itself: `shiftkit run` accepts this object saved as a .json file.
        pipeline=config_record(plan.config),
    )


def _stage_entries(stages: list[Any], report: list[dict[str, int]]) -> list[dict[str, Any]]:
    return [
        {**s.describe(), "report": counts} if counts else s.describe() for s, counts in zip(stages, report, strict=True)
    ]
