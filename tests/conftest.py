"""Test session setup: offline hub, temporary caches, headless MuJoCo, and opt-in markers."""

from __future__ import annotations

import os
import tempfile

# Before lerobot / huggingface_hub / mujoco are imported anywhere: they read these at import time.
_TMP = tempfile.mkdtemp(prefix="shiftkit-tests-")
os.environ["HF_HUB_OFFLINE"] = "1"
os.environ["HF_LEROBOT_HOME"] = os.path.join(_TMP, "lerobot-home")
os.environ["HF_DATASETS_CACHE"] = os.path.join(_TMP, "datasets-cache")
os.environ["HF_HOME"] = os.path.join(_TMP, "hf-home")
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")

import pytest  # noqa: E402


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--run-learning", action="store_true", help="run long learning checks (marker `learning`)")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    # The Ray executor tests run first, from a fresh pytest process: after the BC tests had run in
    # the same process, datatrove's Ray rank pool sometimes never received its task (seen here;
    # never when these tests ran first or alone). Known issue, see docs/executors.md.
    items.sort(key=lambda item: 0 if item.path.name == "test_executors.py" else 1)
    if config.getoption("--run-learning"):
        return
    skip = pytest.mark.skip(reason="long learning check: run with --run-learning")
    for item in items:
        if "learning" in item.keywords:
            item.add_marker(skip)


_SCHEDULING = (os.sched_getscheduler(0), os.sched_getparam(0))


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item: pytest.Item):
    # lerobot's own encoder (SVT-AV1), run as root in this process by a fixture (lerobot-written
    # recordings), makes this thread real-time, and every process a test starts would inherit it
    # (datasets/video.py `scheduling_kept`): each test body starts at the session's policy.
    if os.sched_getscheduler(0) != _SCHEDULING[0]:
        os.sched_setscheduler(0, *_SCHEDULING)
    yield


@pytest.fixture
def synthetic_raw(tmp_path):
    """A small synthetic raw dataset (5 episodes, state + action + success)."""
    from shiftkit.datasets.synthetic import write_synthetic_raw

    return write_synthetic_raw(tmp_path / "raw", episodes=5, length=12, seed=1)


@pytest.fixture
def synthetic_raw_images(tmp_path):
    """Like `synthetic_raw` with a 48x64 RGB camera."""
    from shiftkit.datasets.synthetic import write_synthetic_raw

    return write_synthetic_raw(tmp_path / "raw_img", episodes=3, length=8, seed=2, camera=(48, 64))
