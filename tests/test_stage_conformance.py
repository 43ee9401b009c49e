"""Every registered stage: predicted schema == written schema (`info` included), the output true to
its source (`tests/stage_truth.py`: every kept frame holds its source frame's values, events,
segments and camera metadata follow the frame map) and the written dataset true to the output, same
seed -> same bytes, input untouched, bad config -> one-line ConfigError. The stages and their
examples come from the registry (`Stage.example_params`, `Stage.example_input`): a new stage module
needs no edit here. tests/test_stage_invariants.py runs the same truth checks over lerobot-written
recordings drawn by hypothesis."""

from __future__ import annotations

import dataclasses
import shutil

import pytest

from shiftkit.datasets.errors import ConfigError
from shiftkit.datasets.sources import SourceConfig
from shiftkit.envs.registry import import_modules
from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, StageSpec
from shiftkit.pipelines.planner import plan_pipeline
from shiftkit.pipelines.runner import run_pipeline
from shiftkit.pipelines.stage import STAGES as REGISTRY
from tests.helpers import tree_hashes
from tests.stage_truth import check_against_source, check_written

# The recordings a stage's `example_input` names: example input -> fixture.
EXAMPLE_INPUTS = {
    "synthetic": "synthetic_raw_images",
    "mv-lift": "mv_lift_raw",
    "door-kinesthetic": "kinesthetic_raw",
    "door-replay": "replay_recording",
}


def shipped_stages() -> dict[str, type]:
    """Every stage shiftkit ships (tests may register their own stages; those are not covered here)."""
    return {name: cls for name, cls in REGISTRY.items() if cls.__module__.startswith("shiftkit.")}


STAGES = sorted(shipped_stages())
# Further parameter sets that change a stage's schema another way: id -> (stage, params, fixture).
VARIANTS = {
    # a fixed-mode baseline: the door recording's action loses sts_mode, its state shows visual mode
    "mode_label-visual": ("mode_label", {"source": "visual"}, "kinesthetic_raw"),
    # depth (nearest-neighbour) and intrinsics scale with RGB
    "resize-depth": ("resize", {"width": 40, "height": 30}, "mv_lift_raw"),
    # the depth map alone: the RGB of the same camera keeps its intrinsics
    "resize-depth-only": ("resize", {"width": 32, "height": 24, "features": ["observation.depth.base"]}, "mv_lift_raw"),
    # a replay plan for a robot: target poses + STS mode only
    "force_match-plan": ("force_match", {"mode": "position", "execute": "plan"}, "kinesthetic_raw"),
}


def stage_cases() -> list:
    """One conformance case per shipped stage, from its registration."""
    return [
        pytest.param(n, cls.example_params, EXAMPLE_INPUTS[cls.example_input], id=n)
        for n, cls in shipped_stages().items()
    ]


CASES = [
    *stage_cases(),
    *(pytest.param(*case, id=case_id) for case_id, case in VARIANTS.items()),
]


def config_for(raw, dest, name, params, seed=0):
    return PipelineConfig(
        sources=[SourceConfig(path=str(raw))],
        destination=DestinationConfig(root=str(dest)),
        stages=[StageSpec(name=name, params=params)],
        seed=seed,
    )


def test_every_stage_has_an_example():
    missing = {n for n, cls in shipped_stages().items() if not cls.example_params}
    assert not missing, f"give {missing} example_params"
    unknown = {n: cls.example_input for n, cls in shipped_stages().items() if cls.example_input not in EXAMPLE_INPUTS}
    assert not unknown, f"unknown example_input {unknown}"


@pytest.fixture(scope="module")
def kinesthetic_raw(tmp_path_factory):
    """One simulated kinesthetic door demonstration with wrist and STS images."""
    from shiftkit.app.collect import CollectConfig, collect

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
    from shiftkit.app.collect import CollectConfig, collect

    out, _ = collect(
        CollectConfig(env="mv-lift", task="lift", episodes=2, out=str(tmp_path / "mv"), cameras=("base",), depth=True)
    )
    return out


@pytest.mark.parametrize(("name", "params", "fixture"), CASES)
def test_stage_conformance(name, params, fixture, request, tmp_path):
    assert_conforms(name, params, request.getfixturevalue(fixture), tmp_path)


def assert_conforms(name, params, raw, tmp_path):
    """Predicted schema and fps == written ones, same seed -> same bytes, input untouched."""
    before = tree_hashes(raw)
    dest = tmp_path / "out"
    config = config_for(raw, dest, name, params, seed=7)
    plan = plan_pipeline(config)
    expected = transformed_and_checked(plan)
    run_pipeline(config, progress=False)
    check_written(dest, plan.features, plan.fps, expected)

    first = tree_hashes(dest)
    shutil.rmtree(dest)
    run_pipeline(dataclasses.replace(config), progress=False)
    assert tree_hashes(dest) == first, "same seed must give the same dataset bytes"
    assert tree_hashes(raw) == before, "the input must not be modified"


# A recording as users' data is, written by lerobot's own writer: RGB and depth video (depth in
# uint16 millimetres), two cameras, task segments, language columns, camera metadata.
LEROBOT_RECORDING = dict(
    fps=10,
    lengths=(9, 6),
    cameras=("front", "wrist"),
    depth=("front",),
    depth_unit="mm",
    video=True,
    size=(16, 32),
    tasks=("reach", "grasp"),
)


def _lerobot_recording_cases() -> list:
    return [pytest.param(n, id=n) for n, cls in sorted(shipped_stages().items()) if cls.example_input == "synthetic"]


@pytest.mark.parametrize("name", _lerobot_recording_cases())
def test_stage_is_true_on_a_lerobot_recording(name, tmp_path):
    """Each stage that runs on the synthetic recordings, on a lerobot-written video recording: the
    output true to its source, the written dataset true to the output (video within its coding
    error, millimetre depth within 0.5 mm), `info` as predicted (the video's recorded size and
    frame rate those written)."""
    from tests.lerobot_recordings import Recording, recording

    src = recording(Recording(**LEROBOT_RECORDING))
    config = config_for(src, tmp_path / "out", name, REGISTRY.get(name).example_params, seed=7)
    plan = plan_pipeline(config)
    expected = transformed_and_checked(plan)
    run_pipeline(config, progress=False)
    check_written(tmp_path / "out", plan.features, plan.fps, expected)


def transformed_and_checked(plan) -> list:
    """The plan's outputs computed in memory as the runner computes them (frame maps followed, the
    dataset-level `select` applied), each checked against its source episode."""
    from shiftkit.pipelines.stage import select_outputs
    from shiftkit.pipelines.work import set_up_worker, transform_episode

    set_up_worker(plan)
    outputs = []
    for s, src in enumerate(plan.sources):
        for episode in src.iter_episodes(list(range(src.num_episodes))):
            outs, _ = transform_episode(plan, s, episode)
            check_against_source(plan.stages[0], src.features, episode, outs)
            outputs += outs
    keep = select_outputs(plan.stages, lambda: [o.meta for o in outputs])
    return [o for k, o in enumerate(outputs) if keep is None or keep[k]]


@pytest.mark.parametrize("name", STAGES)
def test_stage_rejects_bad_config(name, synthetic_raw, tmp_path):
    assert_rejects_bad_config(name, synthetic_raw, tmp_path)


def assert_rejects_bad_config(name, raw, tmp_path):
    """An unknown key and a wrongly typed value are one-line ConfigErrors naming the key."""
    example = REGISTRY.get(name).example_params
    with pytest.raises(ConfigError, match="unknown key 'no_such_option'") as info:
        plan_pipeline(config_for(raw, tmp_path / "o", name, {**example, "no_such_option": 1}))
    assert "\n" not in str(info.value)
    first_key = next(iter(example))
    with pytest.raises(ConfigError, match=rf"\.{first_key}: expected"):
        plan_pipeline(config_for(raw, tmp_path / "o", name, {first_key: object()}))


THROWAWAY_STAGE = '''"""`scale_action`: multiply the action by a factor (a stage a test adds as a new module)."""

from dataclasses import dataclass

from shiftkit.pipelines.stage import Stage, register_stage


@dataclass
class ScaleActionConfig:
    factor: float = 1.0
    """Factor on every action dimension."""


@register_stage
class ScaleAction(Stage):
    name = "scale_action"
    version = 1
    Config = ScaleActionConfig
    example_params = {"factor": 2.0}

    def transform_features(self, features):
        return features

    def carried_features(self, features):
        # the action is computed anew; every other feature is the input's (the truth checks hold it to that)
        return {k: v for k, v in super().carried_features(features).items() if k != "action"}

    def process(self, episode, rng):
        yield episode.with_frames(action=episode.frames["action"] * self.config.factor)
'''


def test_a_new_stage_module_is_discovered_and_checked(synthetic_raw_images, tmp_path, monkeypatch):
    """Adding a stage is one new module in the stages package: discovery registers it, `plan --stages`
    lists it, and the conformance and truth checks above run on it from its registration alone."""
    import sys

    import shiftkit.transforms
    from shiftkit.pipelines import stage as stage_module

    folder = tmp_path / "new_stages"
    folder.mkdir()
    (folder / "scale_action.py").write_text(THROWAWAY_STAGE)
    assert "cast" in REGISTRY  # discovered: the registry has loaded shiftkit's stages
    monkeypatch.setattr(REGISTRY, "_items", dict(REGISTRY._items))
    monkeypatch.setattr(shiftkit.transforms, "__path__", [*shiftkit.transforms.__path__, str(folder)])
    monkeypatch.delitem(sys.modules, "shiftkit.transforms.scale_action", raising=False)
    assert "scale_action" not in REGISTRY

    import_modules("shiftkit.transforms", shiftkit.transforms.__path__)  # what the stages package does
    assert "scale_action" in [case.id for case in stage_cases()]
    assert "scale_action (v1): `scale_action`: multiply the action by a factor" in stage_module.describe_stages()
    name, params, fixture = next(case.values for case in stage_cases() if case.id == "scale_action")
    assert fixture == "synthetic_raw_images"
    assert_conforms(name, params, synthetic_raw_images, tmp_path / "conforms")
    assert_rejects_bad_config(name, synthetic_raw_images, tmp_path / "bad")
    # the same stage not saying that it computes the action anew: the truth checks catch it
    monkeypatch.setattr(REGISTRY.get(name), "carried_features", stage_module.Stage.carried_features)
    with pytest.raises(AssertionError, match="'action': frame 0 does not hold source frame 0's values"):
        assert_conforms(name, params, synthetic_raw_images, tmp_path / "silent")
    sys.modules.pop("shiftkit.transforms.scale_action")
