"""`shiftkit merge A B ... --fps N --out DIR --repo-id ID`: build, print and run the pipeline that
merges datasets that differ (docs/merging.md). The pipeline is built as config objects and printed
as a pipeline file for `shiftkit run`.

Per source it chooses `resample` (to `--fps`), `drop` (features not every source has), `cast`
(numeric dtypes to the first source's), `select` (the vector dimensions every source has, in the
first source's order) and `resize` (cameras to `--size`, default the first source's); the planner
stores depth recorded in another unit in the first source's. A choice it cannot make (no
dimension in common) is one error; write that pipeline by hand then.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from shiftkit.datasets.dataclass_config import field_help, option
from shiftkit.datasets.option_values import DataclassOptions

if TYPE_CHECKING:
    from shiftkit.pipelines.config import PipelineConfig

HELP = "merge datasets that differ (fps, features, cameras): write, print and run the merging pipeline"


@dataclass(frozen=True)
class MergeArgs:
    """What `shiftkit merge` merges, into what, and how it runs the pipeline."""

    sources: list[str]
    """Dataset directories or dataset IDs, in output order."""
    fps: int = option(rule="positive_int")
    """Frame rate of the merged dataset."""
    out: str
    """Output dataset directory (must not exist)."""
    repo_id: str
    """Dataset ID of the merged dataset."""
    size: str | None = None
    """Camera size WIDTHxHEIGHT; default: the first source's."""
    workers: int = option(1, rule="positive_int")
    """Worker processes."""
    dry_run: bool = False
    """Only print the pipeline."""
    progress: bool = True
    """Show a progress bar."""


OPTIONS = DataclassOptions(MergeArgs, skip=("sources",), metavars={"out": "DIR"})


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `merge`."""
    parser.add_argument("sources", nargs="+", help=field_help(MergeArgs, "sources"))
    OPTIONS.add_to(parser)


def _size(text: str | None) -> tuple[int, int] | None:
    from shiftkit.datasets.errors import ConfigError

    if text is None:
        return None
    w, sep, h = text.lower().partition("x")
    if not (sep and w.isdigit() and h.isdigit() and int(w) > 0 and int(h) > 0):
        raise ConfigError(f"--size: expected WIDTHxHEIGHT, e.g. 64x48, got {text!r}")
    return int(w), int(h)


def merge_pipeline(refs: list[str], fps: int, out: str, repo_id: str, size: tuple[int, int] | None) -> PipelineConfig:
    """The pipeline that brings the datasets `refs` to one schema and writes them to `out`, as config
    objects (printed with `config.pipeline_toml`; never parsed back from text)."""
    from shiftkit.datasets.errors import ConfigError
    from shiftkit.datasets.features import CAMERA_DTYPES, NUMERIC_DTYPES
    from shiftkit.datasets.sources import open_source
    from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, PipelineSource, StageSpec

    if fps < 1:
        raise ConfigError(f"--fps must be >= 1, got {fps}")
    specs = [
        PipelineSource(path=str(Path(r).resolve())) if Path(r).exists() else PipelineSource(repo_id=r) for r in refs
    ]
    sources = [open_source(s) for s in specs]
    ref = sources[0].features
    common = [k for k in ref if all(k in s.features for s in sources)]
    for spec, src in zip(specs, sources, strict=True):
        stages = spec.stages
        if src.fps != fps:
            stages.append(StageSpec("resample", {"fps": fps}))
        extra = [k for k in src.features if k not in common]
        if extra:
            stages.append(StageSpec("drop", {"features": extra}))
        casts = {
            k: ref[k]["dtype"]
            for k in common
            if src.features[k]["dtype"] != ref[k]["dtype"]
            and {src.features[k]["dtype"], ref[k]["dtype"]} <= NUMERIC_DTYPES
        }
        if casts:
            stages.append(StageSpec("cast", {"dtypes": casts}))
        for key in common:
            ft, names = src.features[key], ref[key].get("names")
            if ft["dtype"] in CAMERA_DTYPES or len(tuple(ft["shape"])) != 1 or not isinstance(names, list):
                continue
            keep = [n for n in names if all(n in (s.features[key].get("names") or []) for s in sources)]
            if not keep:
                raise ConfigError(
                    f"{key!r} has no dimension name that every source has; choose with 'select' (and its 'rename') "
                    "in a pipeline of your own (docs/merging.md)"
                )
            if ft.get("names") != keep:
                stages.append(StageSpec("select", {"feature": key, "names": keep}))
        for key in common:
            ft = src.features[key]
            if ft["dtype"] in CAMERA_DTYPES:
                h, w = tuple(ref[key]["shape"])[:2]
                want = size or (w, h)
                if tuple(ft["shape"])[:2] != (want[1], want[0]):
                    stages.append(StageSpec("resize", {"width": want[0], "height": want[1], "features": [key]}))
    # depth in other units needs no stage: the planner stores every source's in the first one's
    return PipelineConfig(specs, DestinationConfig(root=str(Path(out).resolve()), repo_id=repo_id))


def run(args: argparse.Namespace) -> int:
    """Write and print the merging pipeline, then run it unless `--dry-run`; return the exit code."""
    from shiftkit import datasets
    from shiftkit.datasets.hub import validate_repo_id
    from shiftkit.datasets.provenance import recorded_verdict_lines
    from shiftkit.pipelines.config import pipeline_toml
    from shiftkit.pipelines.planner import plan_pipeline
    from shiftkit.pipelines.runner import run_pipeline

    config = OPTIONS.build(args, sources=args.sources)
    validate_repo_id(config.repo_id)
    pipeline = merge_pipeline(config.sources, config.fps, config.out, config.repo_id, _size(config.size))
    plan_pipeline(pipeline)  # a difference the choices above do not cover fails here, before printing
    print(pipeline_toml(pipeline))
    if config.dry_run:
        return 0
    path = run_pipeline(pipeline, workers=config.workers, progress=config.progress)
    print(f"wrote {path}")
    for line in recorded_verdict_lines(datasets.open(path.name, root=path).provenance):
        print(line)
    return 0
