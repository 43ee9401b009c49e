"""User-facing errors: the CLI prints these as one line and exits non-zero (no traceback)."""

from typing import Any


class ShiftkitError(Exception):
    """A problem with the user's input (paths, configs, datasets); the message names it in one line."""


class ConfigError(ShiftkitError):
    """A malformed pipeline/stage/trainer configuration (unknown key, wrong type, bad value)."""


class DatasetError(ShiftkitError):
    """A missing, corrupt or mismatched dataset (raw or LeRobot)."""


def require_positive(config: Any, *names: str, allow_zero: bool = False) -> None:
    """Raises ConfigError naming the first of `config`'s fields `names` that is not > 0 (>= 0 with
    `allow_zero`)."""
    for name in names:
        value = getattr(config, name)
        if not (value >= 0 if allow_zero else value > 0):
            raise ConfigError(f"{name} must be {'>= 0' if allow_zero else 'positive'}, got {value}")
