"""`--env-kwarg` values checked against the env's constructor before any work (the same rules and
messages as every other numeric option, `datasets/option_values.py`)."""

from __future__ import annotations

import inspect
from importlib import import_module
from typing import Any

from shiftkit.datasets.dataclass_config import meets, rule_error
from shiftkit.datasets.errors import ConfigError
from shiftkit.envs import env_family

# No env quantity (a rate, a size, a duration in seconds) comes near this; a larger value is a typo,
# and the env's arithmetic on it (seconds x rate -> steps) would overflow into a traceback.
LARGEST = 1e9


def check_env_kwargs(env_name: str, kwargs: dict[str, Any]) -> None:
    """Every numeric env constructor argument (rates, sizes, durations) is positive, at most
    `LARGEST`, and an integer where the constructor's default is one; ConfigError with the rule's
    message otherwise. Unknown
    envs and arguments are left to the env (its own one-line error)."""
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
        if value > LARGEST:
            raise ConfigError(f"--env-kwarg {key} must be at most {LARGEST:g}, got {value!r}")
