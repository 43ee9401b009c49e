"""Validate a pipeline without running it: open sources, build stages, predict the output schema.

Each source first runs its own stages (`[[sources]] stages`), which must bring every source to one
schema (features, dtypes, shapes, dimension names, units, fps); the pipeline's common stages then
run on that schema. Where the sources still differ, the plan fails with one line naming the source,
the feature, the difference and the stage that would remove it (docs/merging.md).

Units are part of the schema. Depth in different units (float32 metres, uint16 millimetres) is
not a difference to fix by hand: shiftkit holds depth in metres, so every source's depth is stored
in the first source's unit (or the unit a `depth_image` stage chooses) and the provenance records
each source's conversion (`depth_units`). Any other declared unit (a feature `info` key named
`unit` or `*_unit`) must match.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from shiftkit.datasets.depth import depth_unit, is_depth
from shiftkit.datasets.errors import ConfigError, DatasetError
from shiftkit.datasets.features import CAMERA_DTYPES, NUMERIC_DTYPES, Features, check_features, plain_camera_features
from shiftkit.datasets.sources import Source, input_paths, open_source
from shiftkit.datasets.video import check_frame_size, codec_for
from shiftkit.datasets.video_copy import shows_frames_at
from shiftkit.datasets.video_encoder import check_rgb_encoder, encoded_info, stream_matches
from shiftkit.pipelines.config import PipelineConfig, StageSpec, toml_string, toml_value
from shiftkit.pipelines.stage import ReindexStage, Stage, StageContext, build_stage, selecting_stages


@dataclass
class Plan:
    """A checked pipeline: its open sources, built stages, and the input and output schema and fps."""

    config: PipelineConfig
    sources: list[Source]
    stages: list[Stage]
    input_features: Features
    input_fps: int
    features: Features
    fps: int
    robot_type: str | None
    source_stages: list[list[Stage]] | None = None
    """Per source, its own stages (run before `stages`); None: no source has any."""

    def __post_init__(self) -> None:
        if self.source_stages is None:
            self.source_stages = [[] for _ in self.sources]

    def depth_units(self, source: int) -> dict[str, list[str]]:
        """The depth features of `source` that the output stores in another unit: feature ->
        [the source's unit, the output's] (the provenance records it)."""
        own = self.sources[source].features
        return {
            key: [depth_unit(own[key]), depth_unit(ft)]
            for key, ft in self.features.items()
            if key in own and is_depth(ft) and is_depth(own[key]) and depth_unit(own[key]) != depth_unit(ft)
        }

    @property
    def destination(self) -> Path:
        """The output dataset's folder."""
        return Path(self.config.destination.root)

    @property
    def repo_id(self) -> str:
        """The output dataset's ID (default: local/<folder name>)."""
        return self.config.destination.repo_id or f"local/{self.destination.name}"

    @property
    def num_source_episodes(self) -> int:
        """Episodes over all sources."""
        return sum(s.num_episodes for s in self.sources)

    def chain(self, source: int) -> list[Stage]:
        """Every stage an episode of `source` goes through: its own, then the common ones."""
        return [*self.source_stages[source], *self.stages]

    def _stage_inputs(self, source: int) -> list[Features]:
        """The input schema of each stage of `source`'s chain."""
        inputs, features = [], self.sources[source].features
        for stage in self.source_stages[source]:
            inputs.append(features)
            features = stage.transform_features(features)
        features = self.input_features  # the common stages start from sources[0]'s schema (units)
        for stage in self.stages:
            inputs.append(features)
            features = stage.transform_features(features)
        return inputs

    def kept_source(self, feature: str, source: int) -> str | None:
        """The camera of source `source` whose frames the output camera `feature` holds unchanged
        through every stage of its chain (`Stage.kept_frames`, following renames), or None."""
        inputs = self._stage_inputs(source)
        name: str | None = feature
        for stage, stage_input in zip(reversed(self.chain(source)), reversed(inputs), strict=True):
            name = stage.kept_frames(stage_input).get(name)
            if name is None:
                return None
        return name

    def frames_pass_unchanged(self, feature: str) -> bool:
        """Whether every frame of the output camera `feature`, from every source, is its source
        frame's pixels, stored alike: each stage of each chain keeps that camera's frames, one for one
        or a selection shown in order (`Stage.kept_frames`, following renames back to the source's
        feature), and the source stores it as the output does (image or video, shape, depth unit; at
        another fps, `subsample`'s or `resample`'s, its frames are shown at the output's). What the
        writer needs to know to copy a source's encoded frames (a video's) instead of decoding and
        encoding them again."""
        out = self.features.get(feature)
        if out is None or out["dtype"] not in CAMERA_DTYPES:
            return False
        for s, source in enumerate(self.sources):
            name = self.kept_source(feature, s)
            if name is None or not _stored_alike(source.features.get(name), out):
                return False
        return True

    @functools.cached_property
    def video_copies(self) -> dict[str, list[str]]:
        """Output video feature -> per source, the source video feature whose encoded frames it copies
        (`datasets/video_copy.py`): the frames pass unchanged from every source (RGB, or depth in
        the same unit), as video whose
        streams concatenate (same codec, size, pixel format, time base, codec parameters) with every
        episode starting on a keyframe (`video_copy.copy_signature`), and for RGB already encoded as
        the destination's encoder settings ask (`video_encoder.stream_matches`); where a stage keeps
        some of an episode's frames (`trim`, `subsample`, `resample`), streams that can be cut between
        keyframes (`video_copy.cuttable`), and at another fps a clock that shows frames at it
        (`video_copy.shows_frames_at`). The others are encoded."""
        copies = {}
        settings = self.config.destination.encoder_settings()
        for key, ft in self.features.items():
            if ft["dtype"] != "video" or not self.frames_pass_unchanged(key):
                continue
            names = [self.kept_source(key, s) for s in range(len(self.sources))]
            if not is_depth(ft) and not all(
                stream_matches(source.features[name].get("info"), settings)
                for source, name in zip(self.sources, names, strict=True)
            ):
                continue  # the user asked for another stream than the source's
            signatures = {_copy_signature(source, name) for source, name in zip(self.sources, names, strict=True)}
            if None in signatures or len(signatures) != 1:
                continue
            if any(source.fps != self.fps for source in self.sources) and not shows_frames_at(
                next(iter(signatures)), self.fps
            ):
                continue  # copied frames shown at the new rate need a clock that ticks at it
            if all(
                source.video_cuttable(name)
                for s, (source, name) in enumerate(zip(self.sources, names, strict=True))
                if any(isinstance(stage, ReindexStage) for stage in self.chain(s))
            ):
                copies[key] = names
        return copies

    @functools.cached_property
    def video_transcodes(self) -> frozenset[str]:
        """Output RGB video features whose frames pass unchanged from LeRobot video sources but are
        encoded, not copied (the destination asks for other encoder settings, a merge's streams
        differ, a cut in a stream that cannot be cut): the reader leaves them encoded too, and the
        workers encode them from the decoder's pixels (`video.transcode_episode`), not through RGB."""
        return frozenset(
            key
            for key, ft in self.features.items()
            if ft["dtype"] == "video"
            and not is_depth(ft)
            and key not in self.video_copies
            and self.frames_pass_unchanged(key)
            and all(callable(getattr(source, "video_copy_signature", None)) for source in self.sources)
        )

    def video_refs(self, source: int) -> frozenset[str]:
        """The video features of source `source` its reader leaves encoded (`VideoRef`): those the
        output copies or transcodes, and cameras that stages pass on unchanged until one drops them
        unread (`Stage.dropped_unread`)."""
        copied = {names[source] for names in self.video_copies.values()}
        copied |= {self.kept_source(key, source) for key in self.video_transcodes}
        chain, inputs = self.chain(source), self._stage_inputs(source)
        for key, ft in self.sources[source].features.items():
            if ft["dtype"] != "video" or key in copied:
                continue
            name = key
            for stage, stage_input in zip(chain, inputs, strict=True):
                if name in stage.dropped_unread(stage_input):
                    copied.add(key)
                    break
                kept = [out for out, src in stage.kept_frames(stage_input).items() if src == name]
                if len(kept) != 1:
                    break
                name = kept[0]
        return frozenset(copied)


def build_chain(specs: list[StageSpec], features: Features, fps: int, where: str) -> tuple[list[Stage], Features, int]:
    """The stages of `specs` built on an input schema, with the schema and fps they produce."""
    stages = []
    for i, spec in enumerate(specs):
        stage = build_stage(spec.name, spec.params, StageContext(fps=fps), f"{where}[{i}]", spec.version)
        fps = stage.transform_fps(fps)
        features = stage.transform_features(features)
        check_features(features, where=f"output of {where}[{i}] ({spec.name})")
        stages.append(stage)
    return stages, features, fps


def plan_pipeline(config: PipelineConfig, worker: bool = False) -> Plan:
    """Open the sources and build the stage chains, checking that the sources match after their own
    stages and that the destination is free and outside them. A worker's plan (`worker`) leaves out
    what its main process checked: the destination and its encoder settings."""
    sources = [open_source(s) for s in config.sources]
    chains = []
    for i, (spec, src) in enumerate(zip(config.sources, sources, strict=True)):
        own, features, fps = build_chain(spec.stages, src.features, src.fps, f"sources[{i}].stages")
        if selecting_stages(own):
            raise ConfigError(
                f"sources[{i}].stages: stage {selecting_stages(own)[0].name!r} selects among all of a "
                "dataset's episodes; put it in the pipeline's common stages"
            )
        chains.append((own, features, fps))
    _, first_features, first_fps = chains[0]
    for i, (_, features, fps) in enumerate(chains[1:], start=1):
        features = in_units_of(first_features, features)
        mismatch = schema_mismatch(first_features, first_fps, features, fps, config.destination.video is not None)
        if mismatch:
            raise DatasetError(f"{_source_name(config, i)} {mismatch}")
    stages, features, fps = build_chain(config.stages, first_features, first_fps, "stages")
    if config.destination.video is not None:
        features = plain_camera_features(features, "video" if config.destination.video else "image")
    features = {k: _video_at(ft, fps) for k, ft in features.items()}
    settings = config.destination.encoder_settings()
    for key, ft in features.items():  # the destination's encoder settings, checked before anything runs
        if not worker and ft["dtype"] == "video" and not is_depth(ft):
            check_rgb_encoder(key, ft, settings)
    plan = Plan(
        config,
        sources,
        stages,
        first_features,
        first_fps,
        features,
        fps,
        sources[0].robot_type,
        [own for own, _, _ in chains],
    )
    if settings:  # the RGB video cameras that are encoded: with the destination's settings, which the writer reads
        plan.features = {
            k: {**ft, "info": encoded_info(ft.get("info"), settings)} if _encoded_rgb(plan, k) else ft
            for k, ft in plan.features.items()
        }
    for key, ft in plan.features.items():  # a size the encoder would crash on, said before anything runs
        if ft["dtype"] == "video" and key not in plan.video_copies:
            try:
                check_frame_size(codec_for(ft).vcodec, *tuple(ft["shape"])[:2])
            except DatasetError as exc:
                raise ConfigError(f"{key}: {exc}") from None
    if not worker and plan.destination.exists():
        raise DatasetError(f"destination already exists: {plan.destination}")
    check_sources_and_destination(config, sources, plan.destination)
    return plan


def check_sources_and_destination(config: PipelineConfig, sources: list[Any], destination: Path) -> None:
    """No source twice (by resolved path or, for LeRobot datasets, content; with the same own stages)
    and the destination outside every source (`staging.check_inputs_and_outputs`)."""
    from shiftkit.datasets.ids import dataset_fingerprint
    from shiftkit.datasets.staging import check_inputs_and_outputs

    groups: dict[str, list[tuple[str, Path]]] = {}
    for i, (spec, src) in enumerate(zip(config.sources, sources, strict=True)):
        for path in input_paths(spec, src):  # a source listed twice with other own stages yields other episodes
            groups.setdefault(repr(spec.stages), []).append((_source_name(config, i), path))
    for inputs in groups.values():
        check_inputs_and_outputs(inputs, [("destination", destination)], content_key=dataset_fingerprint)


def _encoded_rgb(plan: Plan, key: str) -> bool:
    """Whether output feature `key` is RGB video that the writer encodes (not copies)."""
    ft = plan.features[key]
    return ft["dtype"] == "video" and not is_depth(ft) and key not in plan.video_copies


def _copy_signature(source: Source, key: str) -> tuple | None:
    """A LeRobot source's `video_copy_signature` of `key` (None for other sources)."""
    signature = getattr(source, "video_copy_signature", None)
    return signature(key) if signature is not None else None


def _stored_alike(source: dict[str, Any] | None, out: dict[str, Any]) -> bool:
    """Whether a source camera feature is stored as the output one: dtype (image or video), shape, and
    for depth its unit."""
    return (
        source is not None
        and (source["dtype"], tuple(source["shape"])) == (out["dtype"], tuple(out["shape"]))
        and is_depth(source) == is_depth(out)
        and (not is_depth(out) or depth_unit(source) == depth_unit(out))
    )


def _video_at(feature: dict[str, Any], fps: int) -> dict[str, Any]:
    """A video feature's recorded frame rate is the output's (lerobot's writer records it anew)."""
    info = feature.get("info") or {}
    if "video.fps" not in info or info["video.fps"] == fps:
        return feature
    return {**feature, "info": {**info, "video.fps": fps}}


def in_units_of(ref: Features, features: Features) -> Features:
    """`features` with each depth feature in the unit of `ref`'s feature of that name: depth is
    float32 metres inside shiftkit, the unit only says how the writer stores it."""
    out = dict(features)
    for key, ft in features.items():
        if key in ref and is_depth(ft) and is_depth(ref[key]) and depth_unit(ft) != depth_unit(ref[key]):
            out[key] = {**ft, "info": {**(ft.get("info") or {}), "depth_unit": depth_unit(ref[key])}}
    return out


def declared_units(feature: dict[str, Any]) -> dict[str, Any]:
    """A feature's declared units other than depth's: its `info` keys `unit` and `*_unit`."""
    info = feature.get("info") or {}
    return {k: v for k, v in info.items() if (k == "unit" or k.endswith("_unit")) and k != "depth_unit"}


def _source_name(config: PipelineConfig, i: int) -> str:
    src = config.sources[i]
    return f"sources[{i}] ({Path(src.path).name if src.path is not None else src.repo_id or src.format})"


def _fix(where: str, name: str, params: dict[str, Any]) -> str:
    shown = ", ".join(f"{k} = {toml_value(v)}" for k, v in params.items())
    return f"add {{name = {toml_string(name)}, params = {{{shown}}}}} to {where}"


def schema_mismatch(ref: Features, ref_fps: int, features: Features, fps: int, any_camera_storage: bool) -> str | None:
    """How a source's schema (after its stages) differs from sources[0]'s, as "what differs; the fix"
    for the first difference (and how many more there are), or None when they match.
    `any_camera_storage`: the destination sets the camera storage, so image vs video is no difference."""
    problems = []
    own, first = "its stages", "sources[0]'s stages"
    if fps != ref_fps:
        problems.append(f"has fps {fps}, sources[0] has {ref_fps}; {_fix(own, 'resample', {'fps': ref_fps})}")
    missing = [k for k in ref if k not in features]
    extra = [k for k in features if k not in ref]
    for key in missing:
        twins = [k for k in extra if _kind(features[k]) == _kind(ref[key])]
        if len(twins) == 1:
            problems.append(
                f"lacks feature {key!r} and has {twins[0]!r} of the same kind; "
                + _fix(own, "rename", {"mapping": {twins[0]: key}})
            )
            extra.remove(twins[0])
        else:
            problems.append(f"lacks feature {key!r} that sources[0] has; {_fix(first, 'drop', {'features': [key]})}")
    for key in extra:
        problems.append(f"has feature {key!r} that sources[0] lacks; {_fix(own, 'drop', {'features': [key]})}")
    for key in (k for k in ref if k in features):
        diff = _feature_mismatch(key, ref[key], features[key], any_camera_storage)
        if diff:
            problems.append(f"feature {key!r} {diff}")
    if not problems:
        return None
    more = f" (and {len(problems) - 1} more difference{'s' if len(problems) > 2 else ''})" if len(problems) > 1 else ""
    return f"does not match sources[0] after its stages: {problems[0]}{more}"


def _kind(ft: dict[str, Any]) -> tuple:
    """What makes two features interchangeable under a rename."""
    if ft["dtype"] in CAMERA_DTYPES:
        return ("camera", tuple(ft["shape"])[-1], is_depth(ft))
    return (ft["dtype"], tuple(ft["shape"]), ft.get("names") if isinstance(ft.get("names"), list) else None)


def _feature_mismatch(key: str, ref: dict[str, Any], ft: dict[str, Any], any_camera_storage: bool) -> str | None:
    own = "its stages"
    dtype, ref_dtype = ft["dtype"], ref["dtype"]
    shape, ref_shape = tuple(ft["shape"]), tuple(ref["shape"])
    cameras = dtype in CAMERA_DTYPES and ref_dtype in CAMERA_DTYPES
    if dtype != ref_dtype and not (cameras and any_camera_storage):
        if dtype in NUMERIC_DTYPES and ref_dtype in NUMERIC_DTYPES:
            return f"has dtype {dtype}, sources[0] has {ref_dtype}; {_fix(own, 'cast', {'dtypes': {key: ref_dtype}})}"
        if cameras:
            return f"is stored as {dtype}, sources[0] as {ref_dtype}; set [destination] video = true or false"
        return f"has dtype {dtype}, sources[0] has {ref_dtype}; no stage converts one to the other, drop it"
    if declared_units(ft) != declared_units(ref):
        return (
            f"has units {declared_units(ft)}, sources[0] has {declared_units(ref)}; no stage converts them, "
            "convert the data or drop it"
        )
    if cameras:
        if is_depth(ft) != is_depth(ref):
            return "is a depth map in one source and RGB in the other; drop or rename it"
        if shape != ref_shape:
            if shape[-1] != ref_shape[-1]:
                return f"has {shape[-1]} channels, sources[0] has {ref_shape[-1]}; drop it"
            params = {"width": ref_shape[1], "height": ref_shape[0], "features": [key]}
            return f"has shape {shape}, sources[0] has {ref_shape}; {_fix(own, 'resize', params)}"
        return None
    names, ref_names = ft.get("names"), ref.get("names")
    if len(shape) == 1 and isinstance(names, list) and isinstance(ref_names, list) and names != ref_names:
        if set(ref_names) <= set(names):
            return f"has names {names}, sources[0] has {ref_names}; {_fix(own, 'select', {'feature': key, 'names': ref_names})}"
        if set(names) <= set(ref_names):
            return f"has names {names}, sources[0] has {ref_names}; {_fix(own, 'pad', {'feature': key, 'names': ref_names})}"
        if len(names) == len(ref_names):
            params = {"feature": key, "names": names, "rename": dict(zip(names, ref_names, strict=True))}
            return f"has names {names}, sources[0] has {ref_names}; {_fix(own, 'select', params)}"
        return (
            f"has names {names}, sources[0] has {ref_names}; pick the dimensions both have with "
            "'select' (and 'rename' them) in both sources"
        )
    if shape != ref_shape:
        return f"has shape {shape}, sources[0] has {ref_shape}; no stage reshapes it, drop it"
    if names != ref_names and len(shape) == 1:
        return f"has names {names}, sources[0] has {ref_names}"
    return None


def format_plan(plan: Plan) -> str:
    """The plan as the text `shiftkit plan` prints: sources, stages and the output schema."""
    lines = [f"sources: {len(plan.sources)} ({plan.num_source_episodes} episodes, {plan.input_fps} fps)"]
    for s, own in enumerate(plan.source_stages):
        if own:
            lines.append(f"  sources[{s}] ({plan.sources[s].num_episodes} episodes, {plan.sources[s].fps} fps):")
        for i, stage in enumerate(own):
            lines.append(f"    stages[{i}] {stage.name} v{stage.version} {stage.describe()['params']}")
    for i, stage in enumerate(plan.stages):
        lines.append(f"  stages[{i}] {stage.name} v{stage.version} {stage.describe()['params']}")
    lines.append(f"output: {plan.destination} (repo_id {plan.repo_id}, {plan.fps} fps)")
    width = max(len(k) for k in plan.features)
    for key, ft in plan.features.items():
        names = ft.get("names")
        shown = ", ".join(map(str, names[:6])) + (", ..." if names and len(names) > 6 else "") if names else ""
        lines.append(f"  {key:<{width}}  {ft['dtype']:<8} {str(tuple(ft['shape'])):<14} {shown}")
    return "\n".join(lines)
