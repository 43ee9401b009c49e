"""Third-party formats as pipeline sources: the importers (`IMPORTERS`, a registry by format name).

An importer reads a format's inputs into episodes: `open(options)` gives a `Source`, so an import
is an ordinary pipeline whose source is the importer (`[[sources]] format = "robomimic"`, `options
= {...}`), with no stages for `shiftkit import FORMAT` or with any stages in a pipeline file, and is
written by the one writer with its provenance (datatrove's model: readers and writers are pipeline
steps). The format's options are a documented dataclass (`Options`): its field docstrings are the
help of `shiftkit import FORMAT`, its fields' rules check the command line and pipeline files alike,
and `inputs` names the fields that hold input files.

A format that lerobot converts itself (`convert`: LeRobot v2.1, whose videos lerobot's converter
copies without decoding) writes through lerobot's code into the writer's staging folder and is
finished like every dataset (`writer.finish`: provenance, card, atomic rename); it is no pipeline
source until the writer can copy unchanged video.

A module of this package, or of an application's plugin package (`shiftkit.app.importers`, found
through the `shiftkit.plugins` entry point), registers its importer with `register_importer`; a new
format is one module and its test.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from shiftkit.datasets.dataclass_config import from_dict
from shiftkit.datasets.errors import ConfigError, DatasetError
from shiftkit.envs.registry import Registry, import_modules, import_plugins


@dataclass(frozen=True)
class Importer:
    """A third-party format, as its module registers it."""

    name: str
    """The format: `shiftkit import FORMAT`, and a `[[sources]]` entry's `format`."""
    help: str
    """One line for `shiftkit import --help`."""
    Options: type
    """The format's options: a documented dataclass (inputs and settings)."""
    inputs: tuple[str, ...]
    """The `Options` fields naming input files or folders (relative to a pipeline file, held apart
    from the destination); the first is positional on the command line."""
    open: Callable[[Any], Any] | None = None
    """The source reading the inputs of an `Options` (a `sources.Source`, with `inputs`: their paths)."""
    convert: Callable[[Any, Path], dict[str, Any]] | None = None
    """For a format lerobot converts: writes the converted dataset of an `Options` into a staging
    folder and returns the provenance source entry; exactly one of `open` and `convert`."""
    report: Callable[[dict[str, Any]], list[str]] = lambda source: []
    """Lines `shiftkit import` prints about what was read, from the source's provenance entry."""

    def __post_init__(self) -> None:
        if (self.open is None) == (self.convert is None):
            raise TypeError(f"importer {self.name!r}: give exactly one of open and convert")

    def options(self, values: dict[str, Any], where: str, base_dir: Path | None = None) -> Any:
        """The `Options` from plain values (a pipeline file's, or the command line's), input paths
        made relative to `base_dir`; ConfigError naming the key for a bad value."""
        values = dict(values)
        for name in self.inputs:
            if base_dir is not None and name in values:
                values[name] = _relative_to(values[name], base_dir)
        return from_dict(self.Options, values, where)

    def named_inputs(self, options: Any) -> list[tuple[str, Path]]:
        """(field, path) of every input file or folder an `Options` names."""
        named = []
        for name in self.inputs:
            value = getattr(options, name)
            named += [(name, Path(v)) for v in (value if isinstance(value, list | tuple) else [value])]
        return named


def _relative_to(value: Any, base_dir: Path) -> Any:
    if isinstance(value, list | tuple):
        return [_relative_to(v, base_dir) for v in value]
    return str((base_dir / value).resolve()) if isinstance(value, str) and not Path(value).is_absolute() else value


IMPORTERS: Registry[Importer] = Registry(
    "import format",
    error=ConfigError,
    discover=[lambda: import_modules(__name__, __path__), import_plugins],
)


def register_importer(importer: Importer) -> Importer:
    """Make `importer` available as `shiftkit import NAME` and as a pipeline source format."""
    if not dataclasses.is_dataclass(importer.Options):
        raise TypeError(f"importer {importer.name!r}: Options must be a dataclass")
    return IMPORTERS.register(importer)


def open_import(format: str, values: dict[str, Any], base_dir: Path | None = None) -> Any:
    """The source (a `sources.Source`) of a `[[sources]]` entry with `format` and its `options` (`values`)."""
    importer = IMPORTERS.get(format)
    if importer.open is None:
        raise ConfigError(
            f"format {format!r} is converted by lerobot's own converter, not read as a pipeline source: "
            f"run `shiftkit import {format}` and use the dataset it writes"
        )
    return importer.open(importer.options(values, f"source format {format!r} options", base_dir))


def convert_import(importer: Importer, options: Any, repo_id: str, root: str | Path) -> Path:
    """A format lerobot converts (`Importer.convert`) into a new dataset at `root`: converted into the
    writer's staging folder and finished like every dataset (`writer.finish`: provenance naming the
    input, card, atomic rename); nothing is left behind on failure."""
    import shutil

    from shiftkit.datasets.hub import validate_repo_id
    from shiftkit.datasets.loaders import load_info
    from shiftkit.datasets.provenance import make_provenance
    from shiftkit.datasets.staging import check_inputs_and_outputs, remove_dead_staging, staging_path
    from shiftkit.datasets.writer import finish

    validate_repo_id(repo_id)
    dest = Path(root).resolve()
    if dest.exists():
        raise DatasetError(f"destination already exists: {dest}")
    check_inputs_and_outputs([(name, path) for name, path in importer.named_inputs(options)], [("--root", dest)])
    tmp = staging_path(dest)
    try:
        dest.parent.mkdir(parents=True, exist_ok=True)
        remove_dead_staging(dest)
        source = importer.convert(options, tmp)
        info = load_info(tmp / "meta" / "info.json")
        provenance = make_provenance(
            repo_id=repo_id,
            fps=info["fps"],
            num_episodes=info["total_episodes"],
            num_frames=info["total_frames"],
            sources=[source],
        )
        return finish(tmp, dest, provenance)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
