"""Pipeline config files (TOML, YAML or JSON): sources, ordered stages, destination, seed.

[[sources]]
path = "raw/lift"            # or repo_id = "org/name" (+ revision), or an importer's format:
stages = [{ name = "resample", params = { fps = 10 } }]   # optional: this source's own stages

[[sources]]
format = "robomimic"         # `shiftkit import --help` lists the formats
options = { file = "demos.hdf5", filter_key = "train" }

[[stages]]
name = "trim"
params = { head = 2 }

[destination]
root = "out/lift"            # relative paths are relative to this file
repo_id = "local/lift"
vcodec = "h264"              # optional encoder settings of re-encoded RGB video (also pix_fmt, g, crf, preset)

seed = 0                     # top-level keys must come before the first table in TOML
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from shiftkit.datasets.dataclass_config import check_fields, from_dict, option, read_config_file
from shiftkit.datasets.errors import ConfigError
from shiftkit.datasets.sources import SourceConfig
from shiftkit.datasets.video_encoder import ENCODER_SETTINGS


@dataclass
class StageSpec:
    """One `[[stages]]` entry: a registered stage by name, with its parameters."""

    name: str
    """Registered stage name (see `shiftkit plan --stages`)."""
    params: dict[str, Any] = field(default_factory=dict)
    """The stage's config values; unknown keys are errors."""
    version: int | None = None
    """Pin the stage version; a mismatch with the installed stage is an error."""


@dataclass
class PipelineSource(SourceConfig):
    """A pipeline input with the stages that bring it to the schema the other sources share."""

    stages: list[StageSpec] = field(default_factory=list)
    """This source's own stages, run on its episodes before the pipeline's common `stages`
    (e.g. `resample`, `rename`, `resize`, `select` to match the other sources; docs/merging.md)."""


@dataclass
class DestinationConfig:
    """The `[destination]` table: where the output dataset goes and whether it is pushed."""

    root: str
    """Output dataset directory; must not exist yet."""
    repo_id: str | None = None
    """Dataset ID recorded in the dataset (default: local/<directory name>)."""
    push: bool = False
    """Push the finished dataset to the hub as `repo_id` (endpoint from HF_ENDPOINT)."""
    revision: str | None = None
    """Hub branch to push to (default: main)."""
    private: bool = False
    """Create the hub repository as private."""
    video: bool | None = None
    """Camera features as lerobot videos (true: RGB with lerobot's AV1 settings, depth with its
    12-bit depth encoder) or images (false: PNG, depth lossless TIFF); unset: as the source has
    them (docs/video_depth.md)."""
    vcodec: str | None = None
    """Codec of the RGB video cameras that are encoded (lerobot's names: "libsvtav1" or "av1", "h264",
    "hevc", "libaom-av1"); unset: the source's, else lerobot's AV1. A camera whose source stream
    already has every setting given here is still copied; one that differs is encoded."""
    pix_fmt: str | None = None
    """Pixel format of the encoded RGB cameras (e.g. "yuv420p", "yuv444p"); unset: the source's,
    else lerobot's yuv420p."""
    g: int | None = option(None, rule="positive_int")
    """GOP size (a keyframe every `g` frames) of the encoded RGB cameras; unset: the source's, else
    lerobot's 2."""
    crf: int | float | None = option(None, rule="non_negative_float")
    """Quality of the encoded RGB cameras (lower: better and larger; the codec's range: AV1 0-63,
    H.264 / HEVC 0-51); unset: the source's, else lerobot's 30."""
    preset: int | str | None = None
    """Speed/quality preset of the encoded RGB cameras (codec-specific: libsvtav1 0-13, H.264 / HEVC
    "ultrafast" ... "veryslow"); unset: the source's when the codec is the source's, else the codec's
    default."""

    def __post_init__(self) -> None:
        check_fields(self)

    def encoder_settings(self) -> dict[str, Any]:
        """The encoder settings given (`datasets.video_encoder.ENCODER_SETTINGS`), by lerobot's names."""
        return {k: getattr(self, k) for k in ENCODER_SETTINGS if getattr(self, k) is not None}


@dataclass
class PipelineConfig:
    """A whole pipeline config: sources, stages, destination and seed."""

    sources: list[PipelineSource]
    """Input datasets; their episodes are processed in order."""
    destination: DestinationConfig
    """Where the output LeRobot dataset goes."""
    stages: list[StageSpec] = field(default_factory=list)
    """Stages applied in order to every episode (after its source's own stages)."""
    seed: int = option(0, rule="non_negative_int")
    """Seed of every random choice a stage makes."""

    def __post_init__(self) -> None:
        if not self.sources:
            raise ValueError("at least one source is required")
        check_fields(self)
        # A plain SourceConfig (built in code) is a source without stages of its own.
        self.sources = [s if isinstance(s, PipelineSource) else PipelineSource(**asdict(s)) for s in self.sources]


def toml_string(text: str) -> str:
    """`text` as a TOML basic string: quotes, backslashes and control characters escaped, every other
    character as it is (TOML files are UTF-8, so a path with an emoji stays one; JSON's escapes
    would write it as a surrogate pair, which TOML refuses)."""
    out = []
    for ch in text:
        code = ord(ch)
        if 0xD800 <= code <= 0xDFFF:
            raise ConfigError(f"{text!r} is not UTF-8 text; a pipeline file cannot hold it")
        if ch in '"\\':
            out.append("\\" + ch)
        elif code < 0x20 or code == 0x7F:
            out.append({"\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f", "\r": "\\r"}.get(ch, f"\\u{code:04x}"))
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def toml_value(value: Any) -> str:
    """A value as written inline in a pipeline TOML file."""
    if isinstance(value, dict):
        return "{" + ", ".join(f"{toml_string(str(k))} = {toml_value(v)}" for k, v in value.items()) + "}"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, str):
        return toml_string(value)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return (
            repr(value) if math.isfinite(value) else ("nan" if math.isnan(value) else ("inf" if value > 0 else "-inf"))
        )
    raise ConfigError(f"a pipeline file cannot hold {type(value).__name__} value {value!r}")


def pipeline_toml(config: PipelineConfig) -> str:
    """`config` as a pipeline TOML file (what `shiftkit merge` prints; `parse_pipeline_config` reads
    it back to the same config). Unset options are left out."""
    lines = [f"seed = {config.seed}", ""] if config.seed else []
    for src in config.sources:
        lines.append("[[sources]]")
        for key in ("path", "repo_id", "revision", "format"):
            if getattr(src, key) is not None:
                lines.append(f"{key} = {toml_string(getattr(src, key))}")
        if src.options:
            lines.append(f"options = {toml_value(src.options)}")
        if src.stages:
            lines.append("stages = [")
            lines += [f"  {_stage_toml(stage)}," for stage in src.stages]
            lines.append("]")
        lines.append("")
    for stage in config.stages:
        lines += ["[[stages]]", f"name = {toml_string(stage.name)}", f"params = {toml_value(stage.params)}"]
        lines += [f"version = {stage.version}"] if stage.version is not None else []
        lines.append("")
    lines.append("[destination]")
    for key, value in asdict(config.destination).items():
        default = DestinationConfig.__dataclass_fields__[key].default
        if value is not None and value != default or key == "root":
            lines.append(f"{key} = {toml_value(value)}")
    return "\n".join(lines) + "\n"


def _stage_toml(stage: StageSpec) -> str:
    version = f", version = {stage.version}" if stage.version is not None else ""
    return f"{{name = {toml_string(stage.name)}, params = {toml_value(stage.params)}{version}}}"


def parse_pipeline_config(data: Any, base_dir: Path, where: str) -> PipelineConfig:
    """A `PipelineConfig` from a config file's plain data (`where` names it in errors); relative paths
    are made relative to `base_dir`."""
    if isinstance(data, dict) and "source" in data:
        if "sources" in data:
            raise ConfigError(f"{where}: give either 'source' or 'sources', not both")
        data = {**data, "sources": [data["source"]]}
        del data["source"]
    config = from_dict(PipelineConfig, data, where)
    if not config.destination.root.strip():
        raise ConfigError(f"{where}: destination root is empty; give the output dataset's folder")
    # Make relative paths relative to the config file, so a pipeline runs from any directory.
    for i, src in enumerate(config.sources):
        if src.path is not None and not Path(src.path).is_absolute():
            src.path = str((base_dir / src.path).resolve())
        if src.format is not None:  # an importer's input files, checked by its options
            from shiftkit.datasets.importers import IMPORTERS

            importer = IMPORTERS.get(src.format)
            src.options = asdict(importer.options(src.options, f"{where}: sources[{i}].options", base_dir))
    if not Path(config.destination.root).is_absolute():
        config.destination.root = str((base_dir / config.destination.root).resolve())
    return config


def config_record(config: PipelineConfig) -> dict[str, Any]:
    """`config` as plain data, as the provenance keeps it (`shiftkit run` reads it back from a .json
    file): a source's `format` and `options` only where it has them."""
    record = asdict(config)
    for source in record["sources"]:
        if source["format"] is None:
            del source["format"], source["options"]
    return record


def load_pipeline_config(path: str | Path) -> PipelineConfig:
    """The `PipelineConfig` in a .toml, .yaml or .json file."""
    path = Path(path)
    return parse_pipeline_config(read_config_file(path), path.parent.resolve(), str(path))
