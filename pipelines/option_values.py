"""Numeric option values (command-line flags, env constructor arguments) checked by one rule each,
with one message per rule wherever the value comes from: `positive_int`, `non_negative_int`,
`positive_float` and `finite_float` are argparse types; `check_env_kwargs` holds the numeric
`--env-kwarg` values to the rules of the env constructor's arguments."""

from __future__ import annotations

import argparse
import inspect
import math
from typing import Any

from shiftkit.pipelines.errors import ConfigError

RULES = {
    "positive_int": "a positive integer",
    "non_negative_int": "an integer >= 0",
    "positive_float": "a positive finite number",
    "finite_float": "a finite number",
}


def rule_error(name: str, rule: str, value: Any) -> str:
    """The one message for a value that breaks `rule`."""
    return f"{name} must be {RULES[rule]}, got {value!r}"


def meets(rule: str, value: Any) -> bool:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    if rule.endswith("_int") and not (isinstance(value, int) or (math.isfinite(value) and value == int(value))):
        return False
    if not math.isfinite(value):
        return False
    return {"positive": value > 0, "non": value >= 0, "finite": True}[rule.split("_")[0]]


def _argparse_type(rule: str):
    def parse(text: str) -> int | float:
        try:
            value = int(text) if rule.endswith("_int") else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {RULES[rule]}, got {text!r}") from None
        if not meets(rule, value):
            raise argparse.ArgumentTypeError(f"must be {RULES[rule]}, got {text!r}")
        return value

    parse.__name__ = rule
    return parse


positive_int = _argparse_type("positive_int")
non_negative_int = _argparse_type("non_negative_int")
positive_float = _argparse_type("positive_float")
finite_float = _argparse_type("finite_float")


def check_env_kwargs(env_name: str, kwargs: dict[str, Any]) -> None:
    """Every numeric env constructor argument (rates, sizes, durations) is positive, and an integer
    where the constructor's default is one; ConfigError with the rule's message otherwise. Unknown
    envs and arguments are left to the env (its own one-line error)."""
    from importlib import import_module

    from shiftkit.envs import env_family

    try:
        module, _, cls = env_family(env_name).entry_point.partition(":")
    except ValueError:
        return
    params = inspect.signature(getattr(import_module(module), cls)).parameters
    for key, value in kwargs.items():
        default = params[key].default if key in params else None
        numeric = isinstance(value, (int, float)) and not isinstance(value, bool)
        if key not in params or not (numeric or isinstance(default, (int, float))) or isinstance(default, bool):
            continue
        if params[key].default is None and value is None:
            continue
        rule = "positive_int" if isinstance(default, int) else "positive_float"
        if not meets(rule, value):
            raise ConfigError(rule_error(f"--env-kwarg {key}", rule, value))
