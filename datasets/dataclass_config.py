"""Typed dataclass configs from plain dicts (TOML/YAML) and from command-line options.

`from_dict`: unknown keys, missing required keys and values of the wrong type are `ConfigError`s
naming the key and where it was found; nothing is coerced silently except int -> float.
`field_docs` gives the field docstrings that the command-line option generator
(`option_values.DataclassOptions`) turns into help.

A field's validation rule lives in the field itself (`option(rule=..., choices=...)`, in its
metadata): `from_dict` (config files), the command-line generator (`DataclassOptions`, as argparse
types and choices) and `check_fields` (a dataclass built in code, from its `__post_init__`) read the
same rule and give the same message (`rule_error`). A rule is one of `RULES`; what relates two
fields stays in the dataclass's `__post_init__`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import tomllib
import types
import typing
from pathlib import Path
from typing import Any, Literal, Union, get_args, get_origin

from shiftkit.datasets.errors import ConfigError

RULES = {
    "positive_int": "a positive integer",
    "non_negative_int": "an integer >= 0",
    "any_int": "an integer",
    "positive_float": "a positive finite number",
    "non_negative_float": "a finite number >= 0",
    "finite_float": "a finite number",
    "fraction": "a number in [0, 1)",
}


def rule_error(name: str, rule: str, value: Any) -> str:
    """The one message for a value that breaks `rule`."""
    return f"{name} must be {RULES[rule]}, got {value!r}"


def meets(rule: str, value: Any) -> bool:
    """Whether `value` is a number that meets `rule` (a `RULES` key); bools never do."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    if rule.endswith("_int") and not (isinstance(value, int) or (math.isfinite(value) and value == int(value))):
        return False
    if not math.isfinite(value):
        return False
    if rule == "fraction":
        return 0 <= value < 1
    return {"positive": value > 0, "non": value >= 0, "finite": True, "any": True}[rule.split("_")[0]]


def option(
    default: Any = dataclasses.MISSING,
    *,
    default_factory: Any = dataclasses.MISSING,
    rule: str | None = None,
    choices: tuple[Any, ...] | None = None,
) -> Any:
    """A dataclass field with its validation in its metadata: `rule` (a `RULES` key) for a number or
    a list's numbers, `choices` for a value from a fixed set. Every reader of the dataclass checks it
    (see the module docstring)."""
    if rule is not None and rule not in RULES:
        raise ValueError(f"unknown option rule {rule!r} (choose from {', '.join(RULES)})")
    metadata = {k: v for k, v in (("rule", rule), ("choices", choices)) if v is not None}
    return dataclasses.field(default=default, default_factory=default_factory, metadata=metadata)


def option_of(
    cls: type, name: str, default: Any = dataclasses.MISSING, *, default_factory: Any = dataclasses.MISSING
) -> Any:
    """Field `name` of dataclass `cls` with another default, its rule and choices kept: a subclass's
    own default for an inherited field (its docstring, when the subclass gives none, stays the base
    class's: `field_docs`)."""
    base = {f.name: f for f in dataclasses.fields(cls)}[name]
    return dataclasses.field(default=default, default_factory=default_factory, metadata=base.metadata)


def field_problem(f: dataclasses.Field, value: Any, name: str | None = None) -> str | None:
    """What is wrong with `value` for field `f` by its metadata's rule or choices, None when nothing
    (the message names the field `name`, default its own)."""
    name = name or f.name
    if value is None:
        return None
    rule, choices = f.metadata.get("rule"), f.metadata.get("choices")
    values = value if isinstance(value, (list, tuple)) else [value]
    if rule is not None:
        bad = next((v for v in values if not meets(rule, v)), None)
        if bad is not None:
            return rule_error(name, rule, bad)
    if choices is not None and value not in choices:
        return f"{name} must be one of {', '.join(map(str, choices))}, got {value!r}"
    return None


def check_fields(obj: Any, prefix: str = "") -> None:
    """Check every field of the dataclass `obj`, and of the dataclasses it nests, against its
    metadata's rule (`option`); ConfigError with the first broken rule's message (a nested field
    named by its dotted path, `bc.hidden`)."""
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            check_fields(value, f"{prefix}{f.name}.")
            continue
        problem = field_problem(f, value, prefix + f.name)
        if problem:
            raise ConfigError(problem)


def field_help(cls: type, name: str) -> str:
    """Field `name`'s docstring as argparse help text (its `%` signs escaped: argparse %-formats help)."""
    return field_docs(cls).get(name, "").replace("%", "%%")


def field_docs(cls: type) -> dict[str, str]:
    """Per-field docstrings (the string literal right after each field), for help and cards; an
    inherited field's from the nearest class that documents it."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if dataclasses.is_dataclass(klass):
            docs.update(_own_field_docs(klass))
    return docs


def _own_field_docs(cls: type) -> dict[str, str]:
    """The field docstrings written in the body of `cls` itself."""
    import ast
    import inspect
    import textwrap

    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    except (OSError, TypeError):
        return {}
    body = tree.body[0].body  # type: ignore[attr-defined]
    docs = {}
    for node, nxt in zip(body, body[1:], strict=False):
        if (
            isinstance(node, ast.AnnAssign)
            and isinstance(node.target, ast.Name)
            and isinstance(nxt, ast.Expr)
            and isinstance(getattr(nxt, "value", None), ast.Constant)
        ):
            docs[node.target.id] = " ".join(str(nxt.value.value).split())
    return docs


def from_dict[T](cls: type[T], data: Any, where: str) -> T:
    """Build dataclass `cls` from `data`, validating every key and type."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a table of parameters, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{where}: unknown key {unknown[0]!r} (valid keys: {', '.join(sorted(fields)) or 'none'})")
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, f in fields.items():
        if name in data:
            kwargs[name] = _check(data[name], hints[name], f"{where}.{name}")
            problem = field_problem(f, kwargs[name])
            if problem:
                raise ConfigError(f"{where}: {problem}")
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ConfigError(f"{where}: missing required key {name!r}")
    try:
        return cls(**kwargs)
    except (ValueError, TypeError) as exc:  # __post_init__ range checks
        raise ConfigError(f"{where}: {exc}") from None


def to_dict(obj: Any) -> dict[str, Any]:
    """The dataclass `obj` as plain data (what `from_dict` reads back)."""
    return dataclasses.asdict(obj)


def _type_name(tp: Any) -> str:
    if get_origin(tp) is Literal:
        return " | ".join(repr(a) for a in get_args(tp))
    return getattr(tp, "__name__", str(tp).replace("typing.", ""))


def _check(value: Any, tp: Any, where: str) -> Any:
    origin, args = get_origin(tp), get_args(tp)
    if tp is Any:
        return value
    if origin in (Union, types.UnionType):
        errors = []
        for arg in args:
            try:
                return _check(value, arg, where)
            except ConfigError as exc:
                errors.append(exc)
        raise ConfigError(f"{where}: expected {' or '.join(_type_name(a) for a in args)}, got {value!r}")
    if tp is type(None):
        if value is None:
            return None
        raise ConfigError(f"{where}: expected null, got {value!r}")
    if origin is Literal:
        if value in args:
            return value
        raise ConfigError(f"{where}: expected one of {', '.join(repr(a) for a in args)}, got {value!r}")
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise ConfigError(f"{where}: expected {len(args)} values, got {len(value)}")
            return tuple(_check(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args, strict=True)))
        item = args[0] if args else Any
        checked = [_check(v, item, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(checked) if origin is tuple else checked
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a table, got {value!r}")
        kt, vt = args if args else (Any, Any)
        return {_check(k, kt, f"{where} key"): _check(v, vt, f"{where}.{k}") for k, v in value.items()}
    if dataclasses.is_dataclass(tp):
        return from_dict(tp, value, where)
    if tp is bool:
        if isinstance(value, bool):
            return value
    elif tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if value != value:  # NaN
                raise ConfigError(f"{where}: NaN is not a valid value")
            return float(value)
    elif tp is str:
        if isinstance(value, str):
            return value
    elif isinstance(tp, type) and isinstance(value, tp):
        return value
    raise ConfigError(f"{where}: expected {_type_name(tp)}, got {value!r}")


def add_env_kwarg(parser: Any, example: str = "view=fixed", **options: Any) -> None:
    """The `--env-kwarg KEY=VALUE` option every command that builds an env shares (repeatable; a list
    of (key, value) pairs, `[]` unless `options` say otherwise, e.g. `dest` or `default=None`)."""
    settings = {"action": "append", "default": [], "type": key_value, "metavar": "KEY=VALUE"}
    settings["help"] = f"env constructor argument (JSON value), repeatable, e.g. {example}"
    parser.add_argument("--env-kwarg", **{**settings, **options})


def key_value(text: str) -> tuple[str, object]:
    """`KEY=VALUE` from the command line (an argparse `type`): VALUE as JSON if it parses, else the
    string (`view=multiview`, `control_hz=5`, `noise=[0.1, 0.2]`)."""
    import json

    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    try:
        return key, json.loads(value)
    except json.JSONDecodeError:
        return key, value


def csv_list(text: str | None) -> list[str]:
    """A comma-separated command-line list (`front,wrist`), blanks dropped."""
    return [x.strip() for x in (text or "").split(",") if x.strip()]


def int_list(text: str) -> list[int]:
    """A comma-separated list of integers (`256,256`), as an argparse `type`."""
    return [int(x) for x in csv_list(text)]


def read_config_file(path: str | Path, what: str = "pipeline config") -> Any:
    """The plain data in a .toml, .yaml/.yml or .json file; a ConfigError names a missing or malformed one."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError(f"{what} not found: {path}") from None
    except IsADirectoryError:
        raise ConfigError(f"{what} is a directory: {path}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not UTF-8 text") from None
    suffix = path.suffix.lower()
    try:
        if suffix == ".toml":
            return tomllib.loads(text)
        if suffix in (".yaml", ".yml"):
            import yaml

            return yaml.safe_load(text)
        if suffix == ".json":
            return json.loads(text)
        raise ConfigError(f"{path}: unknown config format {suffix!r} (use .toml, .yaml or .json)")
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: invalid TOML ({exc})") from None
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{path}: invalid JSON ({exc.msg} at line {exc.lineno})") from None
    except Exception as exc:  # yaml.YAMLError and friends
        if isinstance(exc, ConfigError):
            raise
        raise ConfigError(f"{path}: invalid YAML ({str(exc).splitlines()[0]})") from None
