"""`mode_label`: STS mode labels from operator presses or the contact signal (hysteresis), the
active mode's image kept, label timing vs true first contact reported."""

from __future__ import annotations

import json

import numpy as np
import pytest

from shiftkit.datasets.episode import META_COLUMN
from shiftkit.datasets.errors import ConfigError, DatasetError
from shiftkit.datasets.reader import open_lerobot_dataset
from shiftkit.datasets.sources import SourceConfig
from shiftkit.datasets.sources.raw import RawDatasetWriter, open_raw_dataset
from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, StageSpec
from shiftkit.pipelines.planner import plan_pipeline
from shiftkit.pipelines.runner import run_pipeline
from shiftkit.transforms.mode_labels import contact_modes, operator_modes, timing_report

VISUAL, TACTILE = 40, 200  # grey levels of the two synthetic STS images


def write_tactile_raw(path, episodes: int = 4, length: int = 16, seed: int = 0):
    """Kinesthetic-like episodes: a raw wrench whose Fz rises at the true first contact (with noise
    and an offset), an operator press near it, and constant-grey visual / tactile STS images."""
    rng = np.random.default_rng(seed)
    names = {"action": ["dx", "dy", "dz", "drx", "dry", "drz"]}
    with RawDatasetWriter(path, fps=10, robot="panda", env="synthetic", names=names) as w:
        for e in range(episodes):
            contact = int(rng.integers(5, 10))
            wrench = rng.normal(0.0, 0.03, (length, 4)) + [0.02, -0.03, 0.11, 0.0]
            wrench[contact:, 2] += np.linspace(0.8, 3.0, length - contact)
            wrench[contact:, 0] += 0.4
            shape = (length, 8, 8, 3)
            w.add_episode(
                arrays={
                    "timestamp": np.arange(length) / 10.0,
                    "action": rng.normal(0, 0.1, (length, 6)).astype(np.float32),
                    "wrench_raw": wrench.astype(np.float32),
                },
                images={
                    "sts_visual": np.full(shape, VISUAL, np.uint8),
                    "sts_tactile": np.full(shape, TACTILE, np.uint8),
                },
                meta={
                    "task": "knob-open" if e % 2 else "flat-handle-open",
                    "labels": {"mode_switch_step": [contact + int(rng.integers(-1, 2))]},
                    "first_contact_step": contact,
                },
            )
    return path


def run(raw, dest, params):
    config = PipelineConfig(
        sources=[SourceConfig(path=str(raw))],
        destination=DestinationConfig(root=str(dest)),
        stages=[StageSpec(name="mode_label", params=params)],
    )
    return plan_pipeline(config), run_pipeline(config, progress=False)


IMAGES = {"visual_image": "observation.images.sts_visual", "tactile_image": "observation.images.sts_tactile"}


@pytest.mark.parametrize("source", ["contact", "operator"])
def test_labels_action_dim_and_active_image(tmp_path, source):
    raw = write_tactile_raw(tmp_path / "raw")
    plan, _ = run(raw, tmp_path / "out", {"source": source, **IMAGES})
    assert plan.features["action"]["names"][-1] == "sts_mode"
    assert "observation.images.sts" in plan.features and "observation.images.sts_visual" not in plan.features
    reader = open_lerobot_dataset(tmp_path / "out")
    metas = []
    for ep in reader.iter_episodes():
        mode = ep.frames["action"][:, -1]
        assert set(np.unique(mode)) == {0.0, 1.0}
        switch = int(np.argmax(mode > 0))
        assert (mode[switch:] == 1).all() and (mode[:switch] == 0).all()
        grey = ep.frames["observation.images.sts"][:, 0, 0, 0]
        observed = np.r_[0.0, mode[:-1]]  # a frame shows the mode chosen the frame before
        assert (grey == np.where(observed > 0, TACTILE, VISUAL)).all()
        assert grey[switch] == VISUAL and (grey[switch + 1 :] == TACTILE).all()
        assert ep.meta["sts_mode_switch_step"] == switch
        diff = ep.meta["sts_mode_switch_minus_contact"]
        assert diff == switch - ep.meta["first_contact_step"]
        if source == "contact":
            assert diff == 0  # the hysteresis threshold sits below the contact step's rise
        else:
            assert diff == ep.meta["labels"]["mode_switch_step"][0] - ep.meta["first_contact_step"]
        metas.append(ep.meta)
    table = timing_report(metas, tmp_path / "hist.png")
    assert "| flat-handle-open | 2 |" in table and "| knob-open | 2 |" in table
    assert (tmp_path / "hist.png").read_bytes()[:4] == b"\x89PNG"
    stored = [json.loads(m) for m in reader.episodes[META_COLUMN]]
    assert [m["sts_mode_switch_step"] for m in stored] == [m["sts_mode_switch_step"] for m in metas]


@pytest.mark.parametrize("lead", [2, -1])
def test_lead_steps_shift_the_switch_before_or_after_contact(tmp_path, lead):
    """The demonstrator's choice (thesis 4.3.7): with lead_steps the label, and the image it selects,
    switch that many frames before (positive) or after (negative) the contact signal does."""
    raw = write_tactile_raw(tmp_path / "raw")
    run(raw, tmp_path / "at", {"source": "contact", **IMAGES})
    run(raw, tmp_path / "lead", {"source": "contact", "lead_steps": lead, **IMAGES})
    at = list(open_lerobot_dataset(tmp_path / "at").iter_episodes())
    led = list(open_lerobot_dataset(tmp_path / "lead").iter_episodes())
    for a, b in zip(at, led, strict=True):
        assert b.meta["sts_mode_switch_step"] == a.meta["sts_mode_switch_step"] - lead
        assert b.meta["sts_mode_switch_minus_contact"] == -lead
        mode = b.frames["action"][:, -1]
        assert mode.sum() == a.frames["action"][:, -1].sum() + lead  # the episodes end in contact
        grey = b.frames["observation.images.sts"][:, 0, 0, 0]
        assert (grey == np.where(np.r_[0.0, mode[:-1]] > 0, TACTILE, VISUAL)).all()
        np.testing.assert_array_equal(b.frames["action"][:, :-1], a.frames["action"][:, :-1])


def write_door_like_raw(path, lengths=(20, 24), contact=6, seed=3):
    """Episodes with a door-like state (marker estimate, mode dim) recorded in tactile mode from
    first contact on, constant-grey STS images and a raw wrench that rises at contact."""
    rng = np.random.default_rng(seed)
    state_names = ["rel_x", "sts_fx", "sts_fy", "sts_fz", "sts_tau_z", "sts_mode", "door_angle"]
    names = {"action": ["dx", "dy", "dz", "drx", "dry", "drz"], "state": state_names}
    with RawDatasetWriter(path, fps=10, names=names) as w:
        for length in lengths:
            recorded = (np.arange(length) > contact).astype(np.float32)  # the replay's own mode
            state = rng.normal(0, 1, (length, 7)).astype(np.float32)
            state[:, 1:5] *= recorded[:, None]
            state[:, 5] = recorded
            wrench = np.zeros((length, 4), np.float32)
            wrench[contact:, 2] = 2.0
            w.add_episode(
                arrays={
                    "timestamp": np.arange(length) / 10.0,
                    "action": rng.normal(0, 0.3, (length, 6)).astype(np.float32),
                    "state": state,
                    "wrench_raw": wrench,
                },
                images={
                    "sts_visual": np.full((length, 8, 8, 3), VISUAL, np.uint8),
                    "sts_tactile": np.full((length, 8, 8, 3), TACTILE, np.uint8),
                },
                meta={"task": "knob-open", "first_contact_step": contact},
            )
    return path


def test_state_follows_the_observed_mode_and_late_switch_frames_show_visual(tmp_path):
    """The state's mode dim and marker estimate show the mode each frame was observed in (the
    label of the frame before); `late_switch` frames keep a tactile label but show what a sensor
    still in visual mode shows (visual image, mode 0, no estimate), reproducibly from the seed."""
    raw = write_door_like_raw(tmp_path / "raw")
    recorded = [e.frames["observation.state"] for e in open_raw_dataset(tmp_path / "raw").iter_episodes()]
    params = {"source": "contact", "baseline_frames": 0, **IMAGES}
    run(raw, tmp_path / "plain", params)
    for ep, before in zip(open_lerobot_dataset(tmp_path / "plain").iter_episodes(), recorded, strict=True):
        observed = np.r_[0.0, ep.frames["action"][:-1, -1]]
        state = ep.frames["observation.state"]
        np.testing.assert_array_equal(state[:, 5], observed)
        np.testing.assert_array_equal(state[:, 1:5], np.where(observed[:, None] > 0, before[:, 1:5], 0.0))
        np.testing.assert_array_equal(state[:, [0, 6]], before[:, [0, 6]])
    late = {"late_switch": 0.5, **params}
    run(raw, tmp_path / "late", late)
    run(raw, tmp_path / "late2", late)
    episodes = list(open_lerobot_dataset(tmp_path / "late").iter_episodes())
    for ep, again in zip(episodes, open_lerobot_dataset(tmp_path / "late2").iter_episodes(), strict=True):
        np.testing.assert_array_equal(ep.frames["observation.state"], again.frames["observation.state"])
        label = ep.frames["action"][:, -1]
        observed = np.r_[0.0, label[:-1]] > 0
        grey = ep.frames["observation.images.sts"][:, 0, 0, 0]
        shown_visual = observed & (grey == VISUAL)
        assert 0 < shown_visual.sum() < observed.sum()  # some, not all, tactile frames show visual
        assert ep.meta["sts_late_switch_frames"] == shown_visual.sum()
        state = ep.frames["observation.state"]
        assert (state[shown_visual, 5] == 0).all() and (state[shown_visual, 1:5] == 0).all()
        assert (state[observed & ~shown_visual, 5] == 1).all()
        assert (label[observed] == 1).all()  # the label stays tactile
    for bad, message in [({"late_switch": 1.5}, "late_switch must be in"), ({"late_switch": 0.2}, "late_switch needs")]:
        with pytest.raises(ConfigError, match=message):
            run(raw, tmp_path / "bad", {"source": "contact", **bad})


def test_existing_mode_dim_is_overwritten(tmp_path):
    raw = tmp_path / "raw"
    names = {"action": ["dx", "sts_mode"], "wrench_raw": ["Fx", "Fy", "Fz", "tau_z"]}
    with RawDatasetWriter(raw, fps=10, names=names) as w:
        wrench = np.zeros((6, 4), np.float32)
        wrench[3:, 2] = 1.0
        w.add_episode(
            {"timestamp": np.arange(6) / 10.0, "action": np.ones((6, 2), np.float32), "wrench_raw": wrench},
            meta={"task": "t"},
        )
    plan, _ = run(raw, tmp_path / "out", {"baseline_frames": 0})
    assert plan.features["action"]["names"] == ["dx", "sts_mode"]
    ep = next(open_lerobot_dataset(tmp_path / "out").iter_episodes())
    assert ep.frames["action"][:, 1].tolist() == [0, 0, 0, 1, 1, 1]
    assert ep.meta["sts_mode_switch_minus_contact"] is None


def test_hysteresis_and_presses():
    level = np.array([0.0, 0.5, 0.3, 0.1, 0.35, 0.5, 0.45])[:, None]
    assert contact_modes(level, 0, on=0.4, off=0.2).tolist() == [0, 1, 1, 0, 0, 1, 1]
    assert operator_modes([2, 5], 7, "ep").tolist() == [0, 0, 1, 1, 1, 0, 0]
    with pytest.raises(DatasetError, match="outside the 7 frames"):
        operator_modes([9], 7, "ep")
    with pytest.raises(DatasetError, match="no operator mode-switch presses"):
        operator_modes(None, 7, "ep")


def test_bad_configs_are_one_line_errors(tmp_path):
    raw = write_tactile_raw(tmp_path / "raw", episodes=1)
    for params, message in [
        ({"signal_dims": ["Fw"]}, r"has no dim\(s\) \['Fw'\]"),
        ({"signal": "observation.nope"}, "no vector signal feature"),
        ({"visual_image": "observation.images.sts_visual"}, "give both"),
        ({"on_threshold": 0.1, "off_threshold": 0.5}, "must be <= on_threshold"),
        ({"visual_image": "observation.images.x", "tactile_image": "observation.images.sts_tactile"}, "no image"),
    ]:
        with pytest.raises(ConfigError, match=message) as info:
            run(raw, tmp_path / "o", params)
        assert "\n" not in str(info.value)


def test_dataset_timing_report(tmp_path):
    from shiftkit.transforms.mode_labels import dataset_timing_report

    raw = write_tactile_raw(tmp_path / "raw")
    run(raw, tmp_path / "out", {"source": "contact"})
    table = dataset_timing_report(tmp_path / "out", tmp_path / "h.png")
    assert "| flat-handle-open | 2 | 100% | +0.00 |" in table
    from tests.helpers import write_raw_as_lerobot

    plain = write_raw_as_lerobot(raw, "test/plain", tmp_path / "plain")
    with pytest.raises(DatasetError, match="no episode has mode labels"):
        dataset_timing_report(plain)


@pytest.mark.parametrize("fixed", ["visual", "tactile"])
def test_fixed_sources_make_the_fixed_mode_baselines(tmp_path, fixed):
    """source "visual" / "tactile" (thesis Fig. 4.13 baselines): that mode's image on every frame,
    no `sts_mode` action dim, the state as the door env shows it in that fixed mode."""

    rng = np.random.default_rng(3)
    state_names = ["rel_x", "sts_fx", "sts_fy", "sts_fz", "sts_tau_z", "sts_mode", "door_angle"]
    names = {"action": ["dx", "dy", "dz", "drx", "dry", "drz", "sts_mode"], "state": state_names}
    with RawDatasetWriter(tmp_path / "raw", fps=10, names=names) as w:
        for length in (9, 12):
            mode = (np.arange(length) >= 4).astype(np.float32)  # the recording switched at frame 4
            state = rng.normal(0, 1, (length, 7)).astype(np.float32)
            state[:, 1:5] *= mode[:, None]
            state[:, 5] = mode
            action = np.concatenate([rng.normal(0, 0.3, (length, 6)), mode[:, None]], axis=1).astype(np.float32)
            w.add_episode(
                arrays={"timestamp": np.arange(length) / 10.0, "action": action, "state": state},
                images={
                    "sts_visual": np.full((length, 8, 8, 3), VISUAL, np.uint8),
                    "sts_tactile": np.full((length, 8, 8, 3), TACTILE, np.uint8),
                },
                meta={"task": "knob-open", "first_contact_step": 4},
            )
    plan, _ = run(tmp_path / "raw", tmp_path / "out", {"source": fixed, **IMAGES})
    assert plan.features["action"]["names"] == ["dx", "dy", "dz", "drx", "dry", "drz"]
    assert tuple(plan.features["action"]["shape"]) == (6,)
    assert "observation.images.sts" in plan.features and "observation.images.sts_tactile" not in plan.features
    raw_episodes = list(open_raw_dataset(tmp_path / "raw").iter_episodes())
    out_episodes = list(open_lerobot_dataset(tmp_path / "out").iter_episodes())
    assert len(out_episodes) == 2
    tactile = fixed == "tactile"
    for before, after in zip(raw_episodes, out_episodes, strict=True):
        grey = after.frames["observation.images.sts"][:, 0, 0, 0]
        assert (grey == (TACTILE if tactile else VISUAL)).all()
        np.testing.assert_array_equal(after.frames["action"], before.frames["action"][:, :6])
        state, recorded = after.frames["observation.state"], before.frames["observation.state"]
        assert (state[:, 5] == float(tactile)).all()
        np.testing.assert_array_equal(state[:, [0, 6]], recorded[:, [0, 6]])
        # visual mode shows no marker wrench estimate; tactile keeps the recorded one
        np.testing.assert_array_equal(state[:, 1:5], recorded[:, 1:5] if tactile else 0.0)
        assert after.meta["sts_mode_switch_step"] == (0 if tactile else None)
        assert after.meta["sts_mode_switch_minus_contact"] is None  # no label timing for a fixed mode
        assert after.meta["sts_mode_source"] == fixed
