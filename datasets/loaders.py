"""The one boundary for the files shiftkit reads: typed loaders that check type, shape and range once.

Every JSON file shiftkit reads back (a dataset's `meta/info.json`, `meta/stats.json` and provenance,
a run folder's `config.json`, `metrics.jsonl`, `card.json` and `eval/*.json`) goes through a loader
here, which parses it and checks it against a schema: a malformed or hand-edited file is one line
naming the file, the key and what it must be (`DatasetError`), and the code behind the loader reads
checked values only (no `.get` on a value of unknown type). Arrays (`.npy` plans and recordings) go
through `load_array`. A schema checks the keys its readers use and lets other keys through, so files
written by newer versions still load.

A schema is built from small checkers: `obj(...)` (an object with required keys and `key=opt(...)`
optional ones), `list_of`, `map_of`, `nullable`, `integer`, `number`, `string`, `boolean`,
`numeric` (a number or nested lists of numbers) and `ANY`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from shiftkit.datasets.errors import DatasetError

Check = Callable[[Any, str], Any]  # (value, key path) -> the value; raises _Invalid


class _Invalid(Exception):
    def __init__(self, where: str, expected: str, value: Any) -> None:
        super().__init__(where, expected, value)
        self.where, self.expected, self.value = where, expected, value


def _shown(value: Any) -> str:
    text = repr(value) if not isinstance(value, (dict, list)) else type(value).__name__.replace("dict", "an object")
    if isinstance(value, list):
        text = "a list"
    return text if len(text) <= 60 else text[:57] + "..."


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def ANY(value: Any, where: str) -> Any:  # noqa: N802 - a constant-like checker
    """Any JSON value."""
    return value


def string(value: Any, where: str) -> str:
    """A string."""
    if not isinstance(value, str):
        raise _Invalid(where, "a string", value)
    return value


def boolean(value: Any, where: str) -> bool:
    """true or false."""
    if not isinstance(value, bool):
        raise _Invalid(where, "true or false", value)
    return value


def integer(minimum: int | None = None) -> Check:
    """An integer (not a bool, not 1.0), at least `minimum`."""
    expected = {None: "an integer", 0: "a non-negative integer", 1: "a positive integer"}.get(
        minimum, f"an integer >= {minimum}"
    )

    def check(value: Any, where: str) -> int:
        if not _is_int(value) or (minimum is not None and value < minimum):
            raise _Invalid(where, expected, value)
        return value

    return check


def number(low: float | None = None, high: float | None = None, finite: bool = True) -> Check:
    """A number within [low, high], finite unless `finite` is False (JSON's NaN and Infinity)."""
    expected = ("a finite number" if finite else "a number") + (
        f" in [{low}, {high}]" if low is not None and high is not None else ""
    )

    def check(value: Any, where: str) -> float:
        if not _is_number(value) or (finite and not math.isfinite(value)):
            raise _Invalid(where, expected, value)
        if (low is not None and value < low) or (high is not None and value > high):
            raise _Invalid(where, expected, value)
        return value

    return check


def numeric(value: Any, where: str) -> Any:
    """A number or (nested, rectangular) lists of numbers."""
    flat = [value]
    while flat and all(isinstance(v, list) for v in flat):
        flat = [x for v in flat for x in v]
    try:
        ok = all(_is_number(v) for v in flat) and np.asarray(value, dtype=float).size == len(flat)
    except (ValueError, TypeError):
        ok = False
    if not ok:
        raise _Invalid(where, "a number or a rectangular list of numbers", value)
    return value


def nullable(check: Check) -> Check:
    """null or what `check` accepts."""

    def nullable_check(value: Any, where: str) -> Any:
        return None if value is None else check(value, where)

    return nullable_check


def list_of(check: Check, length: int | None = None) -> Check:
    """A list whose items `check` accepts (of `length` items, when given)."""

    def list_check(value: Any, where: str) -> list:
        if not isinstance(value, list) or (length is not None and len(value) != length):
            raise _Invalid(where, f"a list{f' of {length} items' if length is not None else ''}", value)
        return [check(v, f"{where}[{i}]") for i, v in enumerate(value)]

    return list_check


def map_of(check: Check, non_empty: bool = False) -> Check:
    """An object whose values `check` accepts."""

    def map_check(value: Any, where: str) -> dict:
        if not isinstance(value, dict) or (non_empty and not value):
            raise _Invalid(where, "a non-empty object" if non_empty else "an object", value)
        return {k: check(v, f"{where}.{k}" if where else k) for k, v in value.items()}

    return map_check


class opt:  # noqa: N801 - reads as a marker in a schema: key=opt(string)
    """An optional key of `obj`: absent is fine (and reads as `default` when one is given)."""

    def __init__(self, check: Check, default: Any = None, fill: bool = False) -> None:
        self.check, self.default, self.fill = check, default, fill


def obj(**fields: Check | opt) -> Check:
    """An object with these keys (required unless `opt`); other keys pass unchecked."""

    def object_check(value: Any, where: str) -> dict:
        if not isinstance(value, dict):
            raise _Invalid(where, "an object", value)
        out = dict(value)
        for key, check in fields.items():
            at = f"{where}.{key}" if where else key
            if key in value:
                out[key] = (check.check if isinstance(check, opt) else check)(value[key], at)
            elif isinstance(check, opt):
                if check.fill:
                    out[key] = check.default
            else:
                raise _Invalid(at, "present", _MISSING)
        return out

    return object_check


class _Missing:
    def __repr__(self) -> str:
        return "nothing"


_MISSING = _Missing()


def check_value(value: Any, check: Check, where: str) -> Any:
    """`value` checked by `check`; DatasetError `WHERE: 'key' must be ..., got ...` otherwise."""
    try:
        return check(value, "")
    except _Invalid as exc:
        key = f"'{exc.where}' " if exc.where else ""
        if exc.value is _MISSING:
            raise DatasetError(f"{where}: {key}is missing") from None
        raise DatasetError(f"{where}: {key or 'the file '}must be {exc.expected}, got {_shown(exc.value)}") from None


# --------------------------------------------------------------------------- files


def _text(path: Path, what: str) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise DatasetError(f"{path} is missing ({what})") from None
    except UnicodeDecodeError:
        raise DatasetError(f"{path}: not UTF-8 text") from None
    except IsADirectoryError:
        raise DatasetError(f"{path} is a folder, not {what}") from None
    except OSError as exc:
        raise DatasetError(f"{path}: unreadable ({exc.strerror})") from None


def load_json(path: str | Path, what: str) -> Any:
    """A JSON file parsed; missing, unreadable or malformed is one line (`what` says what it should be)."""
    path = Path(path)
    text = _text(path, what)
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{path}: invalid JSON ({exc.msg} at line {exc.lineno})") from None
    except RecursionError:
        raise DatasetError(f"{path}: JSON nested too deeply") from None


def load_checked(path: str | Path, check: Check, what: str) -> Any:
    """A JSON file checked against a schema."""
    return check_value(load_json(path, what), check, str(path))


def load_json_object(path: str | Path, what: str) -> dict[str, Any]:
    """A JSON file that must hold an object."""
    return load_checked(path, map_of(ANY), what)


FEATURE = obj(dtype=string, shape=list_of(integer(0)), names=opt(ANY))
INFO = obj(
    fps=integer(1),
    features=map_of(FEATURE, non_empty=True),
    codebase_version=opt(string),
    data_path=opt(string),
    video_path=opt(nullable(string)),
    total_episodes=opt(integer(0)),
    total_frames=opt(integer(0)),
    total_tasks=opt(integer(0)),
    robot_type=opt(nullable(string)),
    chunks_size=opt(integer(1)),
)


def load_info(path: str | Path) -> dict[str, Any]:
    """A LeRobot `meta/info.json` (v2.1 or v3.0): fps, features (each a dtype and a shape) and counts."""
    return load_checked(path, INFO, "not a LeRobot dataset")


STATS = map_of(map_of(numeric))


def load_stats(path: str | Path) -> dict[str, dict[str, Any]]:
    """A LeRobot `meta/stats.json`: per feature, per statistic, a number or nested lists of them."""
    return load_checked(path, STATS, "dataset statistics")


STAGE_ENTRY = obj(name=string, version=opt(integer(0)), params=opt(map_of(ANY)), report=opt(map_of(integer(0))))
PROVENANCE = obj(
    sources=opt(
        list_of(
            obj(
                kind=opt(nullable(string)),
                env=opt(nullable(string)),
                task=opt(nullable(string)),
                stages=opt(list_of(STAGE_ENTRY)),
            )
        )
    ),
    stages=opt(list_of(STAGE_ENTRY)),
    output=opt(obj(repo_id=opt(nullable(string)))),
    importer=opt(obj(name=opt(nullable(string)), kind=opt(nullable(string)))),
    seed=opt(nullable(integer())),
    versions=opt(map_of(ANY), default={}, fill=True),
    quality=opt(
        nullable(
            obj(
                verdict=string,
                chunk_size=integer(1),
                episodes=integer(0),
                findings=list_of(obj(check=string, severity=string, message=string, by=string)),
            )
        )
    ),
)


def load_provenance(path: str | Path) -> dict[str, Any]:
    """A dataset's `meta/shiftkit_provenance.json`: sources, stages (each with its name and event
    counts), output and importer, each of the type its readers take."""
    return load_checked(path, PROVENANCE, "provenance")


DATASET_RECORD = obj(
    id=opt(nullable(string)),
    root=opt(nullable(string)),
    revision=opt(nullable(string)),
    fingerprint=opt(nullable(string)),
    fps=opt(nullable(integer(1))),
)
RUN_CONFIG = obj(
    trainer=string,
    args=map_of(ANY),
    datasets=opt(list_of(DATASET_RECORD), default=[], fill=True),
    env=opt(nullable(string)),
    seed=opt(nullable(integer())),
    versions=opt(map_of(ANY), default={}, fill=True),
    normalization=opt(nullable(map_of(ANY))),
)


def load_run_config(path: str | Path) -> dict[str, Any]:
    """A run folder's `config.json`: trainer, args (an object), the datasets it trained on, versions."""
    return load_checked(path, RUN_CONFIG, "the run's config")


EVALUATION = obj(
    env=string,
    task=string,
    policy=opt(nullable(string)),
    seed=integer(0),
    episodes=integer(0),
    successes=opt(integer(0)),
    success_rate=number(0.0, 1.0),
    ci95=list_of(number(0.0, 1.0), length=2),
)


def load_evaluation(path: str | Path) -> dict[str, Any]:
    """An evaluation result (`RUN/eval/*.json`, written by `shiftkit eval`)."""
    return load_checked(path, EVALUATION, "an evaluation result")


def load_jsonl(path: str | Path, line: Check, keep: Callable[[dict], bool] | None = None) -> list[Any]:
    """The lines of a JSON-lines file (blank lines skipped), each checked by `line`; with `keep`, only
    the lines it keeps are checked and returned (`keep` sees values `line` has not checked yet, so it
    reads them with care)."""
    path = Path(path)
    text = _text(path, "JSON lines")
    lines = []
    for n, row in enumerate(text.splitlines(), start=1):
        if not row.strip():
            continue
        try:
            value = json.loads(row)
        except (json.JSONDecodeError, RecursionError) as exc:
            raise DatasetError(f"{path}: line {n}: invalid JSON ({getattr(exc, 'msg', 'nested too deeply')})") from None
        if keep is None or keep(value):
            lines.append(check_value(value, line, f"{path}: line {n}"))
    return lines


METRIC_LINE = obj(step=integer(0), split=string)


def load_metrics(path: str | Path, line: Check | None = None, split: str | None = None) -> list[dict[str, Any]]:
    """The lines of a `metrics.jsonl`, each an object with an integer `step` and a `split`; only the
    lines of `split` when given, and those checked by `line` too (e.g. the fields a figure reads)."""
    lines = load_jsonl(path, METRIC_LINE)
    if split is None:
        return lines
    kept = [x for x in lines if x["split"] == split]
    return [check_value(x, line, f"{path}: step {x['step']}") for x in kept] if line is not None else kept


def h5_item(parent: Any, name: str, where: str, group: bool) -> Any:
    """`parent[name]` of an open HDF5 file, which must be a group (`group`) or a dataset: one line
    naming `where` when it is missing or the other kind (h5py's own errors name neither)."""
    kind = "a group" if group else "a dataset"
    if name not in parent:
        raise DatasetError(f"{where} is missing (expected {kind})")
    item = parent[name]
    if hasattr(item, "keys") != group or (not group and not hasattr(item, "shape")):
        raise DatasetError(f"{where} must be {kind}, got {'a group' if hasattr(item, 'keys') else 'a dataset'}")
    return item


def load_array(
    path: str | Path, what: str, kinds: str = "biuf", ndim: tuple[int, ...] | None = None, finite: bool = True
) -> np.ndarray:
    """A `.npy` array read as data (`allow_pickle=False`): a truncated or foreign file, another dtype
    kind than `kinds` (numpy's: b bool, i/u integers, f floats), another number of dimensions than
    `ndim` or a NaN/inf (with `finite`) is one line naming the file."""
    path = Path(path)
    try:
        array = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise DatasetError(f"{path} is missing ({what})") from None
    except (ValueError, EOFError, OSError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else "truncated or not a .npy array"
        raise DatasetError(f"{path}: unreadable {what} ({reason})") from None
    if not isinstance(array, np.ndarray) or array.dtype.kind not in kinds:
        raise DatasetError(f"{path}: {what} must be a numeric array, got dtype {getattr(array, 'dtype', '?')}")
    if ndim is not None and array.ndim not in ndim:
        raise DatasetError(
            f"{path}: {what} must have {' or '.join(map(str, ndim))} dimensions, got shape {array.shape}"
        )
    if finite and array.dtype.kind == "f" and not np.isfinite(array).all():
        raise DatasetError(f"{path}: {what} holds NaN or infinite values")
    return array
