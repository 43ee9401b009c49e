"""Every registered stage: predicted schema == written schema, same seed -> same bytes, input
untouched, bad config -> one-line ConfigError. A new stage must add its example parameters here."""

from __future__ import annotations

import dataclasses
import json
import shutil

import pytest

from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, StageSpec
from shiftkit.pipelines.errors import ConfigError
from shiftkit.pipelines.planner import plan_pipeline
from shiftkit.pipelines.runner import run_pipeline
from shiftkit.pipelines.sources import SourceConfig
from shiftkit.pipelines.stage import registered_stages
from tests.helpers import tree_hashes

# Parameters that make each stage do real work on the synthetic fixture (10 fps, 3 episodes).
EXAMPLE_PARAMS = {
    "filter": {"min_length": 2, "keep_fraction": 0.7},
    "trim": {"head": 1, "tail": 2},
    "subsample": {"every": 2, "offset": 1},
    "resample": {"fps": 5},
    "rename": {"mapping": {"observation.environment_state": "observation.goal"}},
    "drop": {"features": ["observation.environment_state"]},
    "cast": {"dtypes": {"action": "float64"}},
    "depth_image": {"unit": "mm"},
    "success_examples": {"n_per_task": 3, "states": "success"},
    # the synthetic gripper command flips from open (1) to closed (-1) near the goal: a "contact"
    # replays the recording in the simulator (position mode needs no calibration file)
    "force_match": {"mode": "position", "hold_steps": 2},
    "mode_label": {
        "signal": "observation.state",
        "signal_dims": ["gripper"],
        "on_threshold": 1.0,
        "off_threshold": 0.5,
    },
    "multiview": {"num_views": 2, "depth": True},
    "resize": {"width": 32, "height": 24},
    "select": {"feature": "observation.state", "names": ["gripper", "ee_x"], "rename": {"ee_x": "x"}},
    "pad": {"feature": "observation.state", "names": ["ee_x", "ee_y", "ee_z", "ee_yaw", "gripper"], "value": 0.5},
    "map_tasks": {"mapping": {"reach": "reach the goal"}},
    "replay_join": {"env": "door-tactile"},
}
# Stages that replay or re-render simulator recordings run on a recording of their kind: stage -> fixture.
STAGE_INPUTS = {"multiview": "mv_lift_raw", "force_match": "kinesthetic_raw", "replay_join": "replay_recording"}

# Every stage shiftkit ships (tests may register their own stages; those are not covered here).
STAGES = sorted(name for name, cls in registered_stages().items() if cls.__module__.startswith("shiftkit."))
# Further parameter sets that change a stage's schema another way: id -> (stage, params, fixture).
VARIANTS = {
    # a fixed-mode baseline: the door recording's action loses sts_mode, its state shows visual mode
    "mode_label-visual": ("mode_label", {"source": "visual"}, "kinesthetic_raw"),
    # depth (nearest-neighbour) and intrinsics scale with RGB
    "resize-depth": ("resize", {"width": 40, "height": 30}, "mv_lift_raw"),
    # a replay plan for a robot: target poses + STS mode only
    "force_match-plan": ("force_match", {"mode": "position", "execute": "plan"}, "kinesthetic_raw"),
}
CASES = [
    *(pytest.param(n, EXAMPLE_PARAMS[n], STAGE_INPUTS.get(n, "synthetic_raw_images"), id=n) for n in STAGES),
    *(pytest.param(*case, id=case_id) for case_id, case in VARIANTS.items()),
]


def config_for(raw, dest, name, params, seed=0):
    return PipelineConfig(
        sources=[SourceConfig(path=str(raw))],
        destination=DestinationConfig(root=str(dest)),
        stages=[StageSpec(name=name, params=params)],
        seed=seed,
    )


def test_every_stage_has_example_params():
    assert set(STAGES) <= set(EXAMPLE_PARAMS), f"add example params for {set(STAGES) - set(EXAMPLE_PARAMS)}"


@pytest.fixture(scope="module")
def kinesthetic_raw(tmp_path_factory):
    """One simulated kinesthetic door demonstration with wrist and STS images."""
    from shiftkit.pipelines.sources.simulator import CollectConfig, collect

    out = tmp_path_factory.mktemp("kinesthetic") / "raw"
    collect(CollectConfig(env="door-tactile", task="knob-open", episodes=1, expert="kinesthetic", out=str(out)))
    return out


@pytest.fixture(scope="module")
def replay_recording(kinesthetic_raw, tmp_path_factory):
    """The simulated robot's recording of the kinesthetic demonstration's replay plan."""
    from shiftkit.transforms.replay_join import execute_replay_plan

    out = tmp_path_factory.mktemp("replay")
    plan = config_for(kinesthetic_raw, out / "plan", "force_match", {"mode": "position", "execute": "plan"})
    run_pipeline(plan, progress=False)
    execute_replay_plan(out / "plan", out / "recording")
    return out / "recording"


@pytest.fixture
def mv_lift_raw(tmp_path):
    """Two mv-lift expert episodes with simulator state, base-camera RGB-D and camera metadata."""
    from shiftkit.pipelines.sources.simulator import CollectConfig, collect

    out, _ = collect(
        CollectConfig(env="mv-lift", task="lift", episodes=2, out=str(tmp_path / "mv"), cameras=("base",), depth=True)
    )
    return out


@pytest.mark.parametrize(("name", "params", "fixture"), CASES)
def test_stage_conformance(name, params, fixture, request, tmp_path):
    raw = request.getfixturevalue(fixture)
    before = tree_hashes(raw)
    dest = tmp_path / "out"
    config = config_for(raw, dest, name, params, seed=7)
    plan = plan_pipeline(config)
    run_pipeline(config, progress=False)

    info = json.loads((dest / "meta" / "info.json").read_text())
    written = {
        k: {"dtype": v["dtype"], "shape": tuple(v["shape"]), "names": v["names"]}
        for k, v in info["features"].items()
        if k not in ("timestamp", "frame_index", "episode_index", "index", "task_index")
    }
    predicted = {
        k: {"dtype": v["dtype"], "shape": tuple(v["shape"]), "names": v.get("names")} for k, v in plan.features.items()
    }
    assert written == predicted
    assert info["fps"] == plan.fps

    first = tree_hashes(dest)
    shutil.rmtree(dest)
    run_pipeline(dataclasses.replace(config), progress=False)
    assert tree_hashes(dest) == first, "same seed must give the same dataset bytes"
    assert tree_hashes(raw) == before, "the input must not be modified"


@pytest.mark.parametrize("name", STAGES)
def test_stage_rejects_bad_config(name, synthetic_raw, tmp_path):
    with pytest.raises(ConfigError, match="unknown key 'no_such_option'") as info:
        plan_pipeline(config_for(synthetic_raw, tmp_path / "o", name, {**EXAMPLE_PARAMS[name], "no_such_option": 1}))
    assert "\n" not in str(info.value)
    first_key = next(iter(EXAMPLE_PARAMS[name]))
    with pytest.raises(ConfigError, match=rf"\.{first_key}: expected"):
        plan_pipeline(config_for(synthetic_raw, tmp_path / "o", name, {first_key: object()}))
