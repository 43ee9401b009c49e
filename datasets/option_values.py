"""Numeric option values (command-line flags, env constructor arguments) checked by one rule each,
with one message per rule wherever the value comes from: `positive_int`, `non_negative_int`,
`integer`, `positive_float` and `finite_float` are argparse types (`option_type` makes any of them);
`DataclassOptions` generates a command's options from its config dataclass and picks them by field;
`check_env_kwargs` holds the numeric `--env-kwarg` values to the rules of the env constructor's
arguments."""

from __future__ import annotations

import argparse
import dataclasses
import types
import typing
from typing import Any, Literal, Union, get_args, get_origin

from shiftkit.datasets.dataclass_config import RULES, csv_list, field_docs, key_value, meets
from shiftkit.datasets.errors import ConfigError


def option_type(rule: str, allow_none: bool = False):
    """The argparse `type` of `rule` (a key of RULES); with `allow_none`, `none` gives None."""
    if rule not in RULES:
        raise ValueError(f"unknown option rule {rule!r} (choose from {', '.join(RULES)})")
    expected = RULES[rule] + (" or none" if allow_none else "")

    def parse(text: str) -> int | float | None:
        if allow_none and text.strip().lower() == "none":
            return None
        try:
            value = int(text) if rule.endswith("_int") else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {expected}, got {text!r}") from None
        if not meets(rule, value):
            raise argparse.ArgumentTypeError(f"must be {expected}, got {text!r}")
        return value

    parse.__name__ = rule  # argparse names the type in its "invalid ... value" fallback
    return parse


positive_int = option_type("positive_int")
non_negative_int = option_type("non_negative_int")
non_negative_float = option_type("non_negative_float")
integer = option_type("any_int")
positive_float = option_type("positive_float")
finite_float = option_type("finite_float")


class _ExtendItems(argparse.Action):
    """A list option: one or more values, space- or comma-separated (`--hidden 256,256` or
    `--hidden 256 256`), parsed item by item; repeating the option replaces the list."""

    def __call__(self, parser, namespace, values, option_string=None):  # noqa: ANN001 - argparse's signature
        setattr(namespace, self.dest, [item for value in values for item in value])


@dataclasses.dataclass(frozen=True)
class DataclassOptions[T]:
    """The command-line options of a config dataclass, made by one generator for every command.

    Each init field becomes `--field-name` (or the name in `flags`): its type sets the argparse type,
    `choices` and `nargs` (int / float: an `option_values` rule, `rules[name]` or else any integer /
    any finite number, `none` accepted where the field may be None; list / tuple: one or more values,
    space- or comma-separated; dict: `--flag KEY=VALUE`, repeatable; bool: `--flag` / `--no-flag`;
    `Literal`: its values), its docstring is the help and its default the shown default. Nothing is
    defaulted by argparse (`SUPPRESS`): `build` passes only the options given, so every default lives
    once, in the dataclass (`cli_defaults` names the few a command changes, e.g. a progress bar on).

    Why a generator of our own rather than draccus (lerobot's) or tyro: the commands are argparse
    subcommands whose parser must build without importing the trainers (so `shiftkit --help` stays
    fast), the flag names are the CLI's documented ones (`--output`, `--ensemble`), and every number
    goes through the one rule set of `option_values`; these are some 150 lines on argparse and
    `field_docs`, where either library would add a dependency and its own naming and validation.
    """

    cls: type[T]
    skip: tuple[str, ...] = ()
    """Fields without an option (set by the command, or preset-only)."""
    flags: dict[str, str] = dataclasses.field(default_factory=dict)
    """Field -> flag without the dashes, where it differs from the field name."""
    rules: dict[str, str] = dataclasses.field(default_factory=dict)
    """Field -> `RULES` key of a number or of a list's items, for a dataclass whose fields do not
    carry their rule themselves yet (`dataclass_config.option(rule=...)`, which wins)."""
    choices: dict[str, tuple[Any, ...]] = dataclasses.field(default_factory=dict)
    """Field -> allowed values, likewise where the field does not carry them (`option(choices=...)`)."""
    required: tuple[str, ...] | None = None
    """Fields the command needs (default: those without a default); checked by `build`."""
    cli_defaults: dict[str, Any] = dataclasses.field(default_factory=dict)
    """Field -> default on the command line where it differs from the dataclass's."""
    metavars: dict[str, str] = dataclasses.field(default_factory=dict)
    """Field -> metavar where the flag's name in capitals says less (`--from RAW_DIR`)."""
    positional: tuple[str, ...] = ()
    """Fields given as positional arguments, in order (an importer's input files: one or more for a
    list field)."""
    nested: dict[str, DataclassOptions] = dataclasses.field(default_factory=dict)
    """Field -> the generator of a field that is itself a config dataclass, where plain
    `DataclassOptions(its type)` would not do (its own `flags`, ...). Such a field's fields become
    `--FIELD.FLAG` options (draccus' dotted spelling, `--bc.hidden`), in a help group of their own,
    with the nested default's values as defaults; `build` replaces the options given in it."""

    def fields(self) -> list[dataclasses.Field]:
        """The dataclass fields that get an option (init fields not in `skip`)."""
        return [f for f in dataclasses.fields(self.cls) if f.init and f.name not in self.skip]

    def flag(self, name: str) -> str:
        """The option of field `name`, with its dashes."""
        return "--" + self.flags.get(name, name.replace("_", "-"))

    def _required(self) -> tuple[str, ...]:
        if self.required is not None:
            return self.required
        return tuple(f.name for f in self.fields() if _default(f) is dataclasses.MISSING)

    def add_to(self, parser: argparse.ArgumentParser) -> None:
        """Add one option per field to `parser` (a nested dataclass field's in a group of their own)."""
        self._add(parser, parser, "", None)

    def _nested_fields(self) -> dict[str, DataclassOptions]:
        """The generators of the fields that are config dataclasses themselves."""
        hints = typing.get_type_hints(self.cls)
        return {
            f.name: self.nested.get(f.name) or DataclassOptions(hints[f.name])
            for f in self.fields()
            if dataclasses.is_dataclass(hints[f.name])
        }

    def _default(self, f: dataclasses.Field, defaults: Any) -> Any:
        """Field `f`'s default on the command line: the command's, else that of the nested default
        `defaults` holding the field (None at the top), else the dataclass's."""
        if f.name in self.cli_defaults:
            return self.cli_defaults[f.name]
        return _default(f) if defaults is None else getattr(defaults, f.name)

    def _add(self, parser: argparse.ArgumentParser, target: Any, prefix: str, defaults: Any) -> None:
        """Add the options to `target` (`parser` or one of its groups), each flag and dest after
        `prefix` (`bc.` in a nested field)."""
        hints = typing.get_type_hints(self.cls)
        docs = field_docs(self.cls)
        nested = self._nested_fields()
        for f in self.fields():
            default = self._default(f, defaults)
            if f.name in nested:
                group = parser.add_argument_group(f"{prefix}{f.name} options", docs.get(f.name, "").replace("%", "%%"))
                nested[f.name]._add(parser, group, f"{prefix}{f.name}.", default)
                continue
            settings = self._settings(f, hints[f.name])
            numeric = settings.pop("numeric", False)
            named = self.flag(f.name)[2:].upper().replace("-", "_")
            if f.name in self.metavars:
                settings["metavar"] = self.metavars[f.name]
            elif settings.get("action") is _ExtendItems:
                settings["metavar"] = "N" if numeric else named
            elif "metavar" not in settings and "choices" not in settings and "action" not in settings:
                settings["metavar"] = named
            if f.name in self.positional:
                settings.pop("action", None)  # one or more values as argparse collects them (no csv splitting)
                settings["type"] = str
                settings["metavar"] = self.metavars.get(f.name, f.name.upper())
                target.add_argument(f.name, help=docs.get(f.name, "").replace("%", "%%"), **settings)
                continue
            required = f.name in self._required()  # a dataclass default the command does not use is not shown
            shown = "" if required else _shown(default)
            text = (
                docs.get(f.name, "") + (f" (default: {shown})" if shown else "") + (" (required)" if required else "")
            )
            target.add_argument(
                "--" + prefix + self.flag(f.name)[2:],
                dest=prefix + f.name,
                default=argparse.SUPPRESS,
                help=text.replace("%", "%%"),
                **settings,
            )

    def _settings(self, f: dataclasses.Field, tp: Any) -> dict[str, Any]:
        args = [a for a in get_args(tp) if a is not type(None)]
        optional = get_origin(tp) in (Union, types.UnionType) and len(args) < len(get_args(tp))
        base = args[0] if optional else tp
        origin = get_origin(base)
        choices = f.metadata.get("choices") or self.choices.get(f.name)
        rule = f.metadata.get("rule") or self.rules.get(f.name)
        if choices or origin is Literal:
            values = choices or get_args(base)
            kinds = {type(v) for v in values}  # numbers are parsed before they are compared
            return {"choices": values, **({"type": kinds.pop()} if kinds in ({int}, {float}) else {})}
        if base is bool:
            return {"action": argparse.BooleanOptionalAction}
        if base in (int, float):
            rule = rule or ("any_int" if base is int else "finite_float")
            return {"type": option_type(rule, allow_none=optional), "metavar": "N" if base is int else "X"}
        if origin in (list, tuple):
            item = get_args(base)[0] if get_args(base) else str
            if item in (int, float):
                one = option_type(rule or ("any_int" if item is int else "finite_float"))
            else:
                one = item
            parse = lambda text: [one(x) for x in csv_list(text)]  # noqa: E731
            return {"nargs": "+", "type": parse, "action": _ExtendItems, "numeric": item in (int, float)}
        if origin is dict:
            return {"action": "append", "type": key_value, "metavar": "KEY=VALUE"}
        return {"type": base}

    def values(self, args: argparse.Namespace, **values: Any) -> dict[str, Any]:
        """The fields given in `args` (as the dataclass takes them: pairs -> dict, list -> tuple, a
        nested field's options -> its default with them replaced), the command's `cli_defaults` and
        `values` it sets; a missing required option is a ConfigError naming its flag."""
        given = self._given(args, "", None, values)
        missing = [self.flag(n) for n in self._required() if n not in given]
        if missing:
            raise ConfigError(f"the following arguments are required: {', '.join(missing)}")
        return given

    def _given(self, args: argparse.Namespace, prefix: str, defaults: Any, values: dict[str, Any]) -> dict[str, Any]:
        """The fields given in `args` under dests after `prefix`, the `cli_defaults` and `values`, as
        the dataclass takes them (`defaults`: the nested default holding them, None at the top)."""
        hints = typing.get_type_hints(self.cls)
        nested = self._nested_fields()
        given = {**self.cli_defaults}
        for f in self.fields():
            if f.name in nested:
                inner = self._default(f, defaults)
                changes = nested[f.name]._given(args, f"{prefix}{f.name}.", inner, {})
                if changes:
                    given[f.name] = dataclasses.replace(inner, **changes)
            elif hasattr(args, prefix + f.name):
                given[f.name] = getattr(args, prefix + f.name)
        given.update(values)
        for name, value in given.items():
            origin = get_origin(hints.get(name))
            if origin is dict and isinstance(value, list):
                keys = [key for key, _ in value]
                twice = next((key for key in keys if keys.count(key) > 1), None)
                if twice is not None:  # a later KEY=VALUE would silently replace the earlier one
                    raise ConfigError(f"--{prefix}{self.flag(name)[2:]} {twice}=...: {twice!r} is given twice")
                given[name] = dict(value)
            elif origin is tuple and isinstance(value, list):
                given[name] = tuple(value)
        return given

    def build(self, args: argparse.Namespace, **values: Any) -> T:
        """The dataclass from `values(args, **values)`; the fields not given keep its defaults."""
        return self.cls(**self.values(args, **values))


def _default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


def _shown(default: Any) -> str:
    """A default as the help shows it (nothing for none / empty / missing / off; "on" for true)."""
    if default is dataclasses.MISSING or default is None or default is False or default in ("", [], (), {}):
        return ""
    if default is True:
        return "on"
    if isinstance(default, (list, tuple)):
        return ",".join(map(str, default))
    return str(default)
