"""Validate a pipeline without running it: open sources, build stages, predict the output schema."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from shiftkit.pipelines.config import PipelineConfig
from shiftkit.pipelines.errors import DatasetError
from shiftkit.pipelines.features import Features, check_features, plain_camera_features
from shiftkit.pipelines.sources import Source, open_source
from shiftkit.pipelines.stage import Stage, StageContext, build_stage


@dataclass
class Plan:
    config: PipelineConfig
    sources: list[Source]
    stages: list[Stage]
    input_features: Features
    input_fps: int
    features: Features
    fps: int
    robot_type: str | None

    @property
    def destination(self) -> Path:
        return Path(self.config.destination.root)

    @property
    def repo_id(self) -> str:
        return self.config.destination.repo_id or f"local/{self.destination.name}"

    @property
    def num_source_episodes(self) -> int:
        return sum(s.num_episodes for s in self.sources)


def plan_pipeline(config: PipelineConfig, check_destination: bool = True) -> Plan:
    sources = [open_source(s) for s in config.sources]
    first = sources[0]
    for i, src in enumerate(sources[1:], start=1):
        if src.features != first.features or src.fps != first.fps:
            diff = sorted(set(src.features) ^ set(first.features)) or "dtypes/shapes/names"
            raise DatasetError(
                f"sources[{i}] does not match sources[0] (fps {src.fps} vs {first.fps}; features: {diff})"
            )
    features, fps = first.features, first.fps
    stages = []
    for i, spec in enumerate(config.stages):
        stage = build_stage(spec.name, spec.params, StageContext(fps=fps), f"stages[{i}]", spec.version)
        fps = stage.transform_fps(fps)
        features = stage.transform_features(features)
        check_features(features, where=f"output of stages[{i}] ({spec.name})")
        stages.append(stage)
    if config.destination.video is not None:
        features = plain_camera_features(features, "video" if config.destination.video else "image")
    plan = Plan(config, sources, stages, first.features, first.fps, features, fps, first.robot_type)
    if check_destination and plan.destination.exists():
        raise DatasetError(f"destination already exists: {plan.destination}")
    for i, src in enumerate(config.sources):
        if src.path is not None and plan.destination.resolve().is_relative_to(Path(src.path).resolve()):
            raise DatasetError(f"destination {plan.destination} lies inside sources[{i}]; choose one outside it")
    return plan


def format_plan(plan: Plan) -> str:
    lines = [f"sources: {len(plan.sources)} ({plan.num_source_episodes} episodes, {plan.input_fps} fps)"]
    for i, stage in enumerate(plan.stages):
        lines.append(f"  stages[{i}] {stage.name} v{stage.version} {stage.describe()['params']}")
    lines.append(f"output: {plan.destination} (repo_id {plan.repo_id}, {plan.fps} fps)")
    width = max(len(k) for k in plan.features)
    for key, ft in plan.features.items():
        names = ft.get("names")
        shown = ", ".join(map(str, names[:6])) + (", ..." if names and len(names) > 6 else "") if names else ""
        lines.append(f"  {key:<{width}}  {ft['dtype']:<8} {str(tuple(ft['shape'])):<14} {shown}")
    return "\n".join(lines)
