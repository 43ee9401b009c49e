"""User-facing errors: the CLI prints these as one line and exits non-zero (no traceback)."""


class ShiftkitError(Exception):
    """A problem with the user's input (paths, configs, datasets); the message names it in one line."""


class ConfigError(ShiftkitError):
    """A malformed pipeline/stage/trainer configuration (unknown key, wrong type, bad value)."""


class DatasetError(ShiftkitError):
    """A missing, corrupt or mismatched dataset (raw or LeRobot)."""
