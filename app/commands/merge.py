"""`shiftkit merge A B ... --fps N --out DIR --repo-id ID`: write, print and run the pipeline that
merges datasets that differ (docs/merging.md).

Per source it chooses `resample` (to `--fps`), `drop` (features not every source has), `cast`
(numeric dtypes to the first source's), `select` (the vector dimensions every source has, in the
first source's order) and `resize` (cameras to `--size`, default the first source's). A choice
it cannot make (no dimension in common) is one error; write that pipeline by hand then.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from shiftkit.pipelines.dataclass_config import field_docs
from shiftkit.pipelines.option_values import DataclassOptions

HELP = "merge datasets that differ (fps, features, cameras): write, print and run the merging pipeline"


@dataclass(frozen=True)
class MergeArgs:
    """What `shiftkit merge` merges, into what, and how it runs the pipeline."""

    sources: list[str]
    """Dataset directories or dataset IDs, in output order."""
    fps: int
    """Frame rate of the merged dataset."""
    out: str
    """Output dataset directory (must not exist)."""
    repo_id: str
    """Dataset ID of the merged dataset."""
    size: str | None = None
    """Camera size WIDTHxHEIGHT; default: the first source's."""
    workers: int = 1
    """Worker processes."""
    dry_run: bool = False
    """Only print the pipeline."""
    progress: bool = True
    """Show a progress bar."""


OPTIONS = DataclassOptions(
    MergeArgs, skip=("sources",), rules={"fps": "positive_int", "workers": "positive_int"}, metavars={"out": "DIR"}
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `merge`."""
    parser.add_argument("sources", nargs="+", help=field_docs(MergeArgs)["sources"])
    OPTIONS.add_to(parser)


def _size(text: str | None) -> tuple[int, int] | None:
    from shiftkit.pipelines.errors import ConfigError

    if text is None:
        return None
    w, sep, h = text.lower().partition("x")
    if not (sep and w.isdigit() and h.isdigit() and int(w) > 0 and int(h) > 0):
        raise ConfigError(f"--size: expected WIDTHxHEIGHT, e.g. 64x48, got {text!r}")
    return int(w), int(h)


def merge_pipeline(refs: list[str], fps: int, out: str, repo_id: str, size: tuple[int, int] | None) -> str:
    """The pipeline TOML that brings the datasets `refs` to one schema and writes them to `out`."""
    from shiftkit.pipelines.errors import ConfigError
    from shiftkit.pipelines.features import CAMERA_DTYPES, NUMERIC_DTYPES
    from shiftkit.pipelines.planner import toml_value
    from shiftkit.pipelines.sources import SourceConfig, open_source

    if fps < 1:
        raise ConfigError(f"--fps must be >= 1, got {fps}")
    specs = [SourceConfig(path=str(Path(r).resolve())) if Path(r).exists() else SourceConfig(repo_id=r) for r in refs]
    sources = [open_source(s) for s in specs]
    ref = sources[0].features
    common = [k for k in ref if all(k in s.features for s in sources)]
    lines = []
    for spec, src in zip(specs, sources, strict=True):
        stages: list[tuple[str, dict[str, Any]]] = []
        if src.fps != fps:
            stages.append(("resample", {"fps": fps}))
        extra = [k for k in src.features if k not in common]
        if extra:
            stages.append(("drop", {"features": extra}))
        casts = {
            k: ref[k]["dtype"]
            for k in common
            if src.features[k]["dtype"] != ref[k]["dtype"]
            and {src.features[k]["dtype"], ref[k]["dtype"]} <= NUMERIC_DTYPES
        }
        if casts:
            stages.append(("cast", {"dtypes": casts}))
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
                stages.append(("select", {"feature": key, "names": keep}))
        target = size
        for key in common:
            ft = src.features[key]
            if ft["dtype"] in CAMERA_DTYPES:
                h, w = tuple(ref[key]["shape"])[:2]
                want = target or (w, h)
                if tuple(ft["shape"])[:2] != (want[1], want[0]):
                    stages.append(("resize", {"width": want[0], "height": want[1], "features": [key]}))
        where = f"path = {json.dumps(spec.path)}" if spec.path else f"repo_id = {json.dumps(spec.repo_id)}"
        lines.append(f"[[sources]]\n{where}")
        if stages:
            body = ",\n".join(f"  {{name = {json.dumps(n)}, params = {toml_value(p)}}}" for n, p in stages)
            lines.append(f"stages = [\n{body},\n]")
        lines.append("")
    dest = json.dumps(str(Path(out).resolve()))
    lines.append(f"[destination]\nroot = {dest}\nrepo_id = {json.dumps(repo_id)}\n")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Write and print the merging pipeline, then run it unless `--dry-run`; return the exit code."""
    import tomllib

    from shiftkit.pipelines.config import parse_pipeline_config
    from shiftkit.pipelines.hub import validate_repo_id
    from shiftkit.pipelines.planner import plan_pipeline
    from shiftkit.pipelines.provenance import recorded_verdict_lines
    from shiftkit.pipelines.runner import run_pipeline

    config = OPTIONS.build(args, sources=args.sources)
    validate_repo_id(config.repo_id)
    text = merge_pipeline(config.sources, config.fps, config.out, config.repo_id, _size(config.size))
    pipeline = parse_pipeline_config(tomllib.loads(text), Path.cwd(), "merge pipeline")
    plan_pipeline(pipeline)  # a difference the choices above do not cover fails here, before printing
    print(text)
    if config.dry_run:
        return 0
    path = run_pipeline(pipeline, workers=config.workers, progress=config.progress)
    print(f"wrote {path}")
    for line in recorded_verdict_lines(path):
        print(line)
    return 0
