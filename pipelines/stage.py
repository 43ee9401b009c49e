"""The stage protocol and registry.

A stage is a registered, versioned class with a typed dataclass `Config`, a schema prediction
(`transform_features`, and `transform_fps` for stages that change the frame rate) and a
per-episode transform (`process`: one episode in, zero or more out). Heavy resources (a
simulator, a model, a calibration) are loaded in `setup`, once per worker. Stages know nothing
about executors: the same object runs in-process, in a process pool or on a Ray worker.

Randomness comes only from the `rng` handed to `process`, seeded from the pipeline seed, the
stage's position and the source episode, so output does not depend on worker count or order.

A stage may count named events while it processes an episode (`report`, e.g. episodes it drops
and why, also for an episode that yields nothing); the runner keeps the counts with that source
episode's part, so their totals over a run do not depend on the executor, the worker count or
resumes, and puts them into the run summary and the provenance.

Two kinds of stage say what they do to an episode's frames, as lerobot's typed processor steps say
what they transform:

* `FrameStage`: frame for frame. Each output episode has its input's frames one for one (it may
  drop an episode or yield several, e.g. re-rendered views); columns are added, removed, renamed
  or recomputed. The cameras it does not touch pass unchanged (`kept_frames`), which the planner
  chains into `Plan.frames_pass_unchanged`.
* `ReindexStage`: keeps, drops, repeats or resamples frames. It gives, per output episode, the map
  from its frames to the input's (`Reindex`); the base moves everything that is not a per-frame value
  (events, task segments, language rows) once, through `frame_map.reindexed`.

A stage that is neither (e.g. a replay that re-enacts a demonstration more slowly) subclasses
`Stage` and sets its outputs' frame maps itself.

The registry (`STAGES`) is filled by the stage modules (`@register_stage`); the engine names no
stage package: the application declares its stages through the `shiftkit.plugins` entry point,
which the registry loads on its first lookup (`shiftkit.envs.registry`).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any, ClassVar, final, override

import numpy as np

from shiftkit.datasets.dataclass_config import from_dict, to_dict
from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import ConfigError
from shiftkit.datasets.features import CAMERA_DTYPES, Features
from shiftkit.envs.registry import Registry, import_plugins
from shiftkit.pipelines.frame_map import reindexed


@dataclass
class StageContext:
    """Dataset-level facts a stage may need: the input's frame rate (after earlier stages)."""

    fps: int


class Stage(ABC):
    """A registered, versioned stage (see the module docstring). Besides its name, version and
    `Config`, a stage class carries what the rest of shiftkit reads from the registry: the
    conformance tests its example, the frame-rate property tests its resampling grid, the dataset
    card (through the provenance) its citation."""

    name: ClassVar[str]
    version: ClassVar[int]
    Config: ClassVar[type]
    citation: ClassVar[str | None] = None
    """The paper the method comes from: recorded with the stage in the provenance, cited by the dataset card."""
    example_params: ClassVar[dict[str, Any] | None] = None
    """Parameters that make the stage do real work on `example_input` (tests/test_stage_conformance.py
    runs every stage that has them; every stage shiftkit ships must)."""
    example_input: ClassVar[str] = "synthetic"
    """The recording `example_params` need: "synthetic" (the synthetic raw episodes with images, 10 fps),
    "mv-lift" (simulated multiview lift episodes with RGB-D and camera metadata), "door-kinesthetic"
    (a simulated kinesthetic door demonstration with STS images) or "door-replay" (the robot's
    recording of that demonstration's replay plan)."""
    resampling_params: ClassVar[dict[str, list[Any]] | None] = None
    """Required of a stage that changes the frame rate (overrides `transform_fps`): values to try per
    parameter in the property tests that episode-end events survive resampling."""

    def __init__(self, config: Any, context: StageContext) -> None:
        self.config = config
        self.context = context
        self._report: dict[str, int] = {}

    def setup(self) -> None:  # noqa: B027 (an optional hook: most stages need no setup)
        """Load simulators/models once per worker before the first episode."""

    def transform_fps(self, fps: int) -> int:
        """The output frame rate for an input one (default: unchanged)."""
        return fps

    @abstractmethod
    def transform_features(self, features: Features) -> Features:
        """The output schema for an input schema, without touching data."""

    @abstractmethod
    def process(self, episode: Episode, rng: np.random.Generator) -> Iterable[Episode]:
        """Transform one episode into zero or more episodes. Must not modify `episode` in place."""

    def select(self, metas: list[dict[str, Any]]) -> list[bool] | None:
        """Optional dataset-level step, run once after `process` has seen every source episode:
        given the `meta` of every output episode (in output order), which ones to keep. None (the
        default) keeps all. Only metadata is seen, so a choice made from values that `process`
        drew from its `rng` (e.g. a random key per episode) does not depend on workers or order."""
        return None

    def report(self, event: str, count: int = 1) -> None:
        """Count `count` occurrences of a named event (e.g. "episodes_dropped") in the episode being
        processed. The run's totals appear in the run summary and under this stage in the
        provenance; counting 0 makes an event appear even when its total is 0."""
        self._report[event] = self._report.get(event, 0) + int(count)

    def take_report(self) -> dict[str, int]:
        """The counts reported since the last call, and reset them (the runner calls this after
        each source episode)."""
        counts, self._report = self._report, {}
        return counts

    @classmethod
    def identity_params(cls, features: Features, fps: int) -> dict[str, Any] | None:
        """Parameters with which the stage gives back its input, a dataset with `features` at `fps`,
        unchanged (tests/test_stage_invariants.py checks: the same frames, values and bytes), or
        None when no parameters do (e.g. `multiview` always re-renders)."""
        return None

    def carried_features(self, features: Features) -> dict[str, str]:
        """Output feature -> the input feature it carries through the frame map
        (`Episode.source_frames`): every output frame holds the value of the frame it stands for,
        and events (`frame_map.EVENT_KEYS`, lerobot's language columns) land where
        `frame_map.reindexed` puts them; `task` included. `features` is the input schema. Default:
        every feature the stage outputs under the input's name, dtype, shape and names; a stage
        that computes new values for such a feature leaves it out. The invariant tests
        (tests/test_stage_invariants.py) hold every stage to it."""
        out = self.transform_features(features)
        same = {k: k for k, ft in out.items() if k in features and _schema(ft) == _schema(features[k])}
        return {**same, "task": "task"}

    def kept_frames(self, features: Features) -> dict[str, str]:
        """Output camera feature -> the input camera whose frames it holds unchanged (same pixels,
        stored alike): one for one, or each output episode a selection of its input's frames, each
        shown once and in order (`trim`, `subsample`, a downsampling `resample`), for an input
        schema `features`. A stage that is not known to keep frames (`Stage`,
        `ReindexStage`) keeps none; `FrameStage` keeps what it carries (`carried_cameras`)."""
        return {}

    def carried_cameras(self, features: Features) -> dict[str, str]:
        """The cameras this stage carries (`carried_features`) under an unchanged feature entry."""
        out = self.transform_features(features)
        return {
            key: source
            for key, source in self.carried_features(features).items()
            if key in out and out[key]["dtype"] in CAMERA_DTYPES and out[key] == features.get(source)
        }

    def dropped_unread(self, features: Features) -> set[str]:
        """Input features this stage removes without reading their values (for an input schema
        `features`): a camera only dropped is never decoded (`Plan.video_refs`). Default: none."""
        return set()

    def describe(self) -> dict[str, Any]:
        """The stage as the provenance records it (the dataset card cites `citation`)."""
        entry = {"name": self.name, "version": self.version, "params": to_dict(self.config)}
        if self.citation:
            entry["citation"] = self.citation
        return entry


class FrameStage(Stage):
    """A stage that works frame for frame (see the module docstring): every episode it yields has its
    input's frames one for one; the runner refuses one of another length or with a frame map of its
    own. The cameras it carries under the same name and feature entry pass unchanged."""

    @override
    def kept_frames(self, features: Features) -> dict[str, str]:
        return self.carried_cameras(features)


@dataclass
class Reindex:
    """One output episode of a `ReindexStage`, as a map from its frames to the input's."""

    index: np.ndarray
    """Per output frame, the input frame it stands for (non-decreasing)."""
    timestamps: np.ndarray
    """The output frames' times (seconds from the episode start)."""
    frames: dict[str, np.ndarray] | None = None
    """Per-frame values the stage computes itself (e.g. interpolated); every other feature takes the
    stood-for frame's value."""
    cover: tuple[int, int] | None = None
    """The input frames [start, stop) the output stands for (default: all; `trim`: the kept ones)."""
    meta: dict[str, Any] | None = None
    """The output's meta (default: the input's, its task segments moved)."""


class ReindexStage(Stage):
    """A stage that keeps, drops, repeats or resamples frames (see the module docstring): it says
    which input frame each output frame stands for (`reindex`); values, events, segments and
    language rows move from that map alone (`frame_map.reindexed`)."""

    @abstractmethod
    def reindex(self, episode: Episode, rng: np.random.Generator) -> Iterable[Reindex]:
        """The frame maps of the episodes made from `episode` (none: it is dropped)."""

    @final
    @override
    def process(self, episode: Episode, rng: np.random.Generator) -> Iterable[Episode]:
        for r in self.reindex(episode, rng):
            out = reindexed(episode, r.index, r.timestamps, r.frames, r.cover)
            if r.meta is not None:
                out.meta = r.meta
            yield out


def check_output(stage: Stage, out: Episode, parent: Episode) -> None:
    """A `FrameStage`'s output keeps its input's frames (`Episode.follow` has set its frame map)."""
    if isinstance(stage, FrameStage) and not np.array_equal(out.origin(), parent.origin()):
        raise ValueError(
            f"frame stage {stage.name!r} changed its episode's frames ({len(parent)} -> {len(out)}, or another "
            "frame map): a stage that keeps, drops or resamples frames is a ReindexStage"
        )


def _schema(feature: dict[str, Any]) -> tuple:
    """What makes two features' values comparable frame for frame: dtype, shape and names."""
    return feature["dtype"], tuple(feature["shape"]), feature.get("names")


STAGES: Registry[type[Stage]] = Registry("stage", error=ConfigError, discover=[import_plugins])


def register_stage(cls: type[Stage]) -> type[Stage]:
    """Class decorator: make a stage available to pipelines under `cls.name` (in `STAGES`)."""
    for attr in ("name", "version", "Config"):
        if not hasattr(cls, attr):
            raise TypeError(f"stage {cls.__name__} lacks class attribute {attr!r}")
    if cls.transform_fps is not Stage.transform_fps and not cls.resampling_params:
        raise TypeError(f"stage {cls.__name__} changes the frame rate but gives no resampling_params")
    return STAGES.register(cls)


def selecting_stages(stages: list[Stage]) -> list[Stage]:
    """The stages that override the dataset-level `select` hook."""
    return [s for s in stages if type(s).select is not Stage.select]


def select_outputs(stages: list[Stage], read_metas: Callable[[], list[dict[str, Any]]]) -> list[bool] | None:
    """Apply the stages' `select` hooks in pipeline order to the metas of all output episodes.

    Returns a keep-mask, or None without calling `read_metas` when no stage overrides `select`.
    """
    selecting = selecting_stages(stages)
    if not selecting:
        return None
    metas = read_metas()
    keep = [True] * len(metas)
    for stage in selecting:
        kept = [k for k, flag in enumerate(keep) if flag]
        chosen = stage.select([metas[k] for k in kept])
        if chosen is None:
            continue
        if len(chosen) != len(kept):
            raise TypeError(f"stage {stage.name!r}: select() returned {len(chosen)} flags for {len(kept)} episodes")
        for k, flag in zip(kept, chosen, strict=True):
            keep[k] = bool(flag)
    return keep


def build_stage(
    name: str, params: dict[str, Any] | None, context: StageContext, where: str, version: int | None = None
) -> Stage:
    """Instantiate a registered stage from config values, with one-line errors."""
    try:
        cls = STAGES.get(name)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    if version is not None and version != cls.version:
        raise ConfigError(f"{where}: stage {name!r} is version {cls.version}, the config asks for version {version}")
    config = from_dict(cls.Config, params or {}, f"{where} ({name})")
    return cls(config, context)


def describe_stages() -> str:
    """Every registered stage with its parameters, defaults and docs (for `shiftkit plan --stages`)."""
    import dataclasses
    import sys

    from shiftkit.datasets.dataclass_config import field_docs

    lines = []
    for name, cls in STAGES.items():
        doc = (sys.modules[cls.__module__].__doc__ or "").strip().splitlines()
        lines.append(f"{name} (v{cls.version}): {doc[0] if doc else ''}")
        docs = field_docs(cls.Config)
        for f in dataclasses.fields(cls.Config):
            default = (
                f.default
                if f.default is not dataclasses.MISSING
                else (f.default_factory() if f.default_factory is not dataclasses.MISSING else "(required)")
            )
            lines.append(f"    {f.name} = {default!r}  {docs.get(f.name, '')}")
    return "\n".join(lines)
