"""A policy runs in its env at its dataset's fps: the env is set to that rate when it offers it, and
an evaluation the env cannot run at that rate is refused in one line naming both rates."""

from __future__ import annotations

import pytest

from shiftkit.datasets.errors import ConfigError
from shiftkit.policies.evaluation import _make_env


class _Policy:
    features: dict = {}


def test_env_runs_at_the_policy_rate_when_offered():
    env = _make_env(_Policy(), "panda-play", "lift", {}, rate=5)
    try:
        assert env.control_hz == 5
    finally:
        env.close()


def test_rate_the_env_does_not_offer_is_refused():
    with pytest.raises(ConfigError, match=r"10 fps.*20 Hz.*offers 5, 20 Hz"):
        _make_env(_Policy(), "panda-play", "lift", {}, rate=10)


def test_explicit_other_rate_is_refused():
    with pytest.raises(ConfigError, match=r"20 fps.*5 Hz"):
        _make_env(_Policy(), "panda-play", "lift", {"control_hz": 5}, rate=20)
