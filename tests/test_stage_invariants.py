"""Every registered stage, true to its source, on datasets written by lerobot 0.6.1's own writer.

* A property test draws lerobot-written recordings (`tests/lerobot_recordings.py`: fps, episode
  lengths from one frame, one or two RGB cameras, depth in float32 metres or uint16 millimetres on a
  shared or a camera of its own, images or video, task segments, success / done / intervention flags,
  language columns, camera metadata) and runs every registered stage that accepts the recording, with
  its identity, example and frame-rate parameters, through the runner's frame maps. Each output is
  checked against its source (`tests/stage_truth.py`): kept frames hold the source's values, events
  land on the frame that stands for theirs, segments and language rows follow, camera metadata
  follows its feature; identity parameters give the source back. A new stage is covered without an
  edit here; the stages that need a simulator recording are covered the same way on their own
  example inputs in tests/test_stage_conformance.py.
* Cases each fixed against the old code: `resample` to the recording's own fps and to half of it on
  lerobot's float32 timestamps, depth of different units merged, the depth of a camera resized
  without its RGB, a camera feature renamed, `depth_image unit = "mm"` on float depth, and
  `validate --deep` on depth stored under the wrong unit.
"""

from __future__ import annotations

import json
import shutil
from datetime import timedelta

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from shiftkit.datasets.errors import ConfigError, DatasetError
from shiftkit.datasets.features import check_episode
from shiftkit.datasets.reader import open_lerobot_dataset
from shiftkit.datasets.sources import SourceConfig, open_source
from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, PipelineSource, StageSpec
from shiftkit.pipelines.planner import build_chain
from shiftkit.pipelines.runner import run_pipeline
from shiftkit.pipelines.stage import STAGES
from tests.lerobot_recordings import Recording, depth_metres, recording, recordings

EXAMPLES = 12  # recordings per run; each is written by lerobot (about a second) and every stage runs on it


def applicable_stages(features, fps) -> dict:
    """The registered stages whose example parameters plan on a recording of `features` (the others
    need a simulator recording: multiview, force_match, replay_join)."""
    out = {}
    for name, cls in STAGES.items():
        try:
            build_chain([StageSpec(name, cls.example_params or {})], features, fps, name)
        except (ConfigError, DatasetError):
            continue
        out[name] = cls
    return out


def test_every_stage_the_recordings_fit_is_drawn():
    """Every stage whose example runs on the synthetic recordings runs on the lerobot-written ones."""
    src = open_source(SourceConfig(path=str(recording(Recording()))))
    synthetic = {n for n, cls in STAGES.items() if cls.example_input == "synthetic"}
    assert synthetic <= set(applicable_stages(src.features, src.fps))


def _param_sets(cls, features, fps, data) -> list[tuple[str, dict]]:
    """Identity (if the stage has one), its example, and for frame-rate stages a drawn setting."""
    sets = []
    identity = cls.identity_params(features, fps)
    if identity is not None:
        sets.append(("identity", identity))
    sets.append(("example", dict(cls.example_params or {})))
    if cls.resampling_params:
        drawn = {k: data.draw(st.sampled_from(v), label=f"{cls.name}.{k}") for k, v in cls.resampling_params.items()}
        sets.append(("drawn", {**(cls.example_params or {}), **drawn}))
    return sets


def run_stage(stage, features, fps, episodes, seed=0) -> list[tuple]:
    """The stage on each source episode as the runner runs it (frame maps followed), outputs checked
    against the planned schema; (source, outputs) pairs."""
    stage.setup()
    out_features, out_fps = stage.transform_features(features), stage.transform_fps(fps)
    pairs = []
    for ep in episodes:
        rng = np.random.default_rng([seed, 0, int(ep.meta["source_episode_index"]), 0])
        outputs = [o.follow(ep, stage.name) for o in stage.process(ep, rng)]
        for o in outputs:
            check_episode(o, out_features, out_fps, f"{stage.name} output")
        pairs.append((ep, outputs))
    return pairs


def assert_identity(name: str, pairs: list[tuple]) -> None:
    from tests.stage_truth import as_stored  # imported late: the cases below also run on older code

    for ep, outputs in pairs:
        assert len(outputs) == 1, f"{name} with identity parameters made {len(outputs)} episodes of one"
        (out,) = outputs
        assert np.array_equal(out.origin(), np.arange(len(ep))), f"{name} identity: not every frame kept"
        assert out.meta == ep.meta, f"{name} identity: meta {out.meta} != {ep.meta}"
        assert set(out.frames) == set(ep.frames)
        for key, arr in ep.frames.items():
            if key == "timestamp":  # stored as float32: 0.2 and float32(0.2) are one timestamp
                np.testing.assert_array_equal(out.frames[key].astype(np.float32), arr.astype(np.float32))
            elif np.asarray(arr).dtype == object:
                assert as_stored(out.frames[key]) == as_stored(arr), f"{name} identity changed {key!r}"
            else:
                np.testing.assert_array_equal(out.frames[key], arr, err_msg=f"{name} identity changed {key!r}")


@settings(
    max_examples=EXAMPLES,
    deadline=timedelta(seconds=90),  # a drawn recording is written by lerobot first: seconds on 2 shared cores
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(rec=recordings(), data=st.data())
def test_every_stage_is_true_to_its_source(rec, data):
    from tests.stage_truth import check_against_source  # imported late: the cases below also run on older code

    src = open_source(SourceConfig(path=str(recording(rec))))
    episodes = list(src.iter_episodes(list(range(src.num_episodes))))
    for name, cls in applicable_stages(src.features, src.fps).items():
        for kind, params in _param_sets(cls, src.features, src.fps, data):
            try:
                (stage,), _, _ = build_chain([StageSpec(name, params)], src.features, src.fps, name)
            except ConfigError:
                continue  # e.g. `subsample every = 3` at 10 fps: refused when planned
            pairs = run_stage(stage, src.features, src.fps, episodes)
            for ep, outputs in pairs:
                check_against_source(stage, src.features, ep, outputs)
            if kind == "identity":
                assert_identity(name, pairs)


# --------------------------------------------------------------------------- resample


def _pipeline(sources, dest, stages=(), **destination) -> PipelineConfig:
    return PipelineConfig(
        sources=[s if isinstance(s, PipelineSource) else PipelineSource(path=str(s)) for s in sources],
        destination=DestinationConfig(root=str(dest), **destination),
        stages=[StageSpec(n, p) for n, p in stages],
    )


@pytest.mark.parametrize("fps", [20, 10])
def test_resample_on_lerobot_timestamps(tmp_path, fps):
    """A lerobot-written 20 fps dataset with episodes of 77, 78 and 93 frames, each ending in success
    and done: to 20 fps it is the same dataset (float32 timestamps like 3.7999999 s once lost the
    last frame and moved its success to the frame before); to 10 fps it keeps 39, 39 and 47 frames,
    success and done on the last."""
    rec = Recording(
        fps=20, lengths=(77, 78, 93), cameras=("front",), depth=(), language=False, camera_meta=False, final_success=1.0
    )
    src = recording(rec)
    out = run_pipeline(_pipeline([src], tmp_path / "out", [("resample", {"fps": fps})]), progress=False)
    episodes = list(open_lerobot_dataset(out).iter_episodes())
    assert [len(ep) for ep in episodes] == ([77, 78, 93] if fps == 20 else [39, 39, 47])
    source = list(open_lerobot_dataset(src).iter_episodes())
    for ep, s in zip(episodes, source, strict=True):
        assert ep.frames["next.done"][-1].all() and not ep.frames["next.done"][:-1].any()
        assert ep.frames["next.success"][-1].all() and s.frames["next.success"][-1].all()
        kept = np.arange(len(ep)) * (20 // fps)
        np.testing.assert_array_equal(ep.frames["observation.state"], s.frames["observation.state"][kept])
        np.testing.assert_array_equal(ep.frames["observation.images.front"], s.frames["observation.images.front"][kept])
    if fps == 20:  # the identity: lerobot's own bytes
        import pyarrow.parquet as pq

        table = lambda root: pq.read_table(next((root / "data").rglob("*.parquet")))  # noqa: E731
        assert table(out).equals(table(src))


def test_resample_success_on_the_last_frame(tmp_path):
    """20 -> 10 fps: the success of an even-length episode's last frame, which no grid frame stands
    for, lands on the last grid frame, not before it."""
    rec = Recording(fps=20, lengths=(78,), cameras=(), depth=(), language=False, camera_meta=False, seed=1)
    src = open_source(SourceConfig(path=str(recording(rec))))
    (ep,) = src.iter_episodes([0])
    success = np.zeros_like(ep.frames["next.success"])
    success[-1] = True
    ep = ep.with_frames(**{"next.success": success})
    (stage,), _, _ = build_chain([StageSpec("resample", {"fps": 10})], src.features, 20, "resample")
    ((_, (out,)),) = run_stage(stage, src.features, 20, [ep])
    assert len(out) == 39 and out.frames["next.success"][-1].all() and not out.frames["next.success"][:-1].any()


# --------------------------------------------------------------------------- depth units


@pytest.mark.parametrize("first", ["m", "mm"])
def test_merging_depth_of_two_units_reads_back_each_source(tmp_path, first):
    """Float-metre and uint16-millimetre depth merged (both orders): every frame reads back within
    0.5 mm of its source, stored in the first source's unit; the provenance says which source was
    converted. (Before, the second source's numbers were stored under the first's unit: metres
    read as millimetres, or millimetres as metres.)"""
    other = "mm" if first == "m" else "m"
    recs = [Recording(depth_unit=u, lengths=(5, 4), seed=i, language=False) for i, u in enumerate((first, other))]
    roots = [recording(r) for r in recs]
    out = run_pipeline(_pipeline(roots, tmp_path / "out"), progress=False)
    info = json.loads((out / "meta" / "info.json").read_text())
    assert info["features"]["observation.depth.front"]["info"]["depth_unit"] == first
    merged = list(open_lerobot_dataset(out).iter_episodes())
    truth = [depth_metres(rec, e, t, 0) for rec in recs for e in range(2) for t in range(rec.lengths[e])]
    got = np.concatenate([ep.frames["observation.depth.front"] for ep in merged])
    assert np.abs(got - np.stack(truth)).max() <= 0.0005 + 1e-6
    sources = json.loads((out / "meta" / "shiftkit_provenance.json").read_text())["sources"]
    assert "depth_units" not in sources[0]
    assert sources[1]["depth_units"] == {"observation.depth.front": [other, first]}
    from shiftkit.datasets.check import recompute_stats, validate_dataset

    validate_dataset(out)
    recompute_stats(out)  # validate --deep: values possible in the declared unit


def test_depth_image_unit_converts_native_depth(tmp_path):
    """`depth_image unit = "mm"` on float-metre depth stores uint16 millimetres (it was a no-op)."""
    src = recording(Recording(depth_unit="m", language=False))
    out = run_pipeline(_pipeline([src], tmp_path / "out", [("depth_image", {"unit": "mm"})]), progress=False)
    info = json.loads((out / "meta" / "info.json").read_text())
    assert info["features"]["observation.depth.front"]["info"]["depth_unit"] == "mm"
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ours, theirs = (
        np.concatenate([e.frames["observation.depth.front"] for e in open_lerobot_dataset(r).iter_episodes()])
        for r in (out, src)
    )
    assert np.abs(ours - theirs).max() <= 0.0005 + 1e-6
    # lerobot itself reads the frames as millimetres
    stored = np.asarray(LeRobotDataset("test/recording", root=out).hf_dataset[0]["observation.depth.front"])
    np.testing.assert_array_equal(
        stored[..., None] if stored.ndim == 2 else stored.reshape(theirs[0].shape), np.rint(theirs[0] * 1000)
    )


def test_other_declared_units_must_match(tmp_path):
    """A unit a feature declares (an `info` key `unit` or `*_unit`) is part of the schema: sources
    that differ in it do not plan, with one line naming it (no stage converts it)."""
    src = recording(Recording(language=False, camera_meta=False))
    other = shutil.copytree(src, tmp_path / "other")
    info = json.loads((other / "meta" / "info.json").read_text())
    info["features"]["action"]["info"] = {"unit": "mm/s"}
    (other / "meta" / "info.json").write_text(json.dumps(info))
    from shiftkit.pipelines.planner import plan_pipeline

    with pytest.raises(DatasetError, match=r"feature 'action' has units \{'unit': 'mm/s'\}, sources\[0\] has \{\}"):
        plan_pipeline(_pipeline([src, other], tmp_path / "out"))


@pytest.mark.parametrize("unit", ["m", "mm"])
def test_validate_deep_flags_depth_in_another_unit(tmp_path, unit):
    """Depth stored under the other unit's label (what the mixed merge wrote) fails `validate --deep`
    with one line; the shallow check cannot tell."""
    from tests.reliability.harness import cli

    ds = shutil.copytree(recording(Recording(depth_unit=unit, language=False, camera_meta=False)), tmp_path / "ds")
    info_path = ds / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    info["features"]["observation.depth.front"]["info"]["depth_unit"] = "m" if unit == "mm" else "mm"
    info_path.write_text(json.dumps(info))
    outcome = cli(["validate", "--deep", str(ds)])
    assert (
        outcome.code == 2
        and "impossible in" in outcome.error_line
        and "'observation.depth.front'" in outcome.error_line
    )


# --------------------------------------------------------------------------- camera metadata


def _cameras(root):
    return open_lerobot_dataset(root).cameras


def test_resizing_only_the_depth_leaves_the_rgb_intrinsics(tmp_path):
    """RGB and depth of `front` share their intrinsics; resizing the depth alone gives it intrinsics
    of its own and leaves the RGB's (they were both scaled by 2 before)."""
    rec = Recording(size=(12, 16), language=False)
    src = recording(rec)
    resize = ("resize", {"width": 8, "height": 6, "features": ["observation.depth.front"]})
    out = run_pipeline(_pipeline([src], tmp_path / "out", [resize]), progress=False)
    cams = next(open_lerobot_dataset(out).iter_episodes()).meta["cameras"]
    own = cams["front"].get("features", {})  # a feature's own entries (docs/camera_metadata.md)
    rgb, depth = (
        own.get(f"observation.{k}.front", {}).get("intrinsics", cams["front"].get("intrinsics"))
        for k in ("images", "depth")
    )
    original = next(open_lerobot_dataset(src).iter_episodes()).meta["cameras"]["front"]
    assert rgb == original["intrinsics"]
    assert (depth["width"], depth["height"], depth["fx"]) == (8, 6, original["intrinsics"]["fx"] / 2)
    assert cams["front"]["extrinsics"] == original["extrinsics"]  # shared by both, kept once


def test_rename_moves_the_camera_metadata(tmp_path):
    """Renaming `observation.images.front` to `observation.images.left` moves its intrinsics and
    extrinsics to camera `left`; `front` keeps them for its depth map."""
    src = recording(Recording(language=False))
    mapping = {"observation.images.front": "observation.images.left"}
    out = run_pipeline(_pipeline([src], tmp_path / "out", [("rename", {"mapping": mapping})]), progress=False)
    cams = next(open_lerobot_dataset(out).iter_episodes()).meta["cameras"]
    original = next(open_lerobot_dataset(src).iter_episodes()).meta["cameras"]["front"]
    assert cams["left"] == original and cams["front"] == original
