"""Scripted experts (a few seeds per task), play episodes with segment labels, and
`shiftkit collect` into raw episodes and LeRobot. The 50-seed table is `bench/expert_success.py`
(and the opt-in `learning` test below)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from shiftkit.app.cli import main as cli
from shiftkit.envs import ENV_TASKS, make
from shiftkit.envs.panda_play.experts import PLAY_SEQUENCES, play_rollout, rollout

TASKS = ENV_TASKS["panda-play"]


@pytest.mark.parametrize("task", TASKS)
def test_expert_succeeds_on_a_few_seeds(task):
    env = make("panda-play", task)
    for seed in (0, 1):
        r = rollout(env, seed)
        assert r.succeeded, f"{task} expert failed on seed {seed}"
        assert r.success[-1] and r.observations.shape == (len(r.actions), 59)
        # success only once the predicate has held for the hold time
        assert int(np.argmax(r.success)) + 1 >= env.task.hold_steps(env.control_hz)
    env.close()


@pytest.mark.parametrize("task", TASKS)
def test_expert_succeeds_at_5hz(task):
    env = make("panda-play", task, control_hz=5)
    for seed in (0, 1):
        assert rollout(env, seed).succeeded, f"{task} expert failed at 5 Hz on seed {seed}"
    env.close()


def test_expert_rollouts_are_deterministic():
    env = make("panda-play", "stack")
    a, b = rollout(env, 5), rollout(env, 5)
    assert np.array_equal(a.actions, b.actions) and np.array_equal(a.qpos, b.qpos)
    env.close()


def test_replaying_recorded_sim_state_reproduces_observations():
    env = make("panda-play", "lift")
    r = rollout(env, 2)
    for t in (0, len(r.actions) // 2, len(r.actions) - 1):
        obs = env.set_sim_state(r.qpos[t], r.qvel[t])
        # finger history and wrench depend on more than the instantaneous state
        assert np.allclose(obs[:6], r.observations[t][:6], atol=1e-5)
        assert np.allclose(obs[12:53], r.observations[t][12:53], atol=1e-5)
    env.close()


def test_play_episode_labels_contiguous_segments():
    env = make("panda-play", "stack")
    r = play_rollout(env, 0, PLAY_SEQUENCES["stack"])
    tasks = [s["task"] for s in r.segments]
    assert tasks == list(PLAY_SEQUENCES["stack"])
    assert all(s["success"] for s in r.segments)
    assert r.segments[0]["start"] == 0 and r.segments[-1]["end"] == len(r.actions)
    assert all(a["end"] == b["start"] for a, b in zip(r.segments, r.segments[1:], strict=False))
    for s in r.segments:
        assert r.success[s["end"] - 1] and not r.success[s["start"] : s["end"] - 1].all()
    env.close()


def test_collect_raw_then_lerobot(tmp_path, capsys):
    from shiftkit.datasets.sources.raw import open_raw_dataset

    out = tmp_path / "raw"
    assert (
        cli(
            [
                "collect",
                "--env",
                "panda-play",
                "--task",
                "reach",
                "--episodes",
                "2",
                "--seed",
                "4",
                "--out",
                str(out),
                "--cameras",
                "front",
                "--depth",
            ]
        )
        == 0
    )
    raw = open_raw_dataset(out)
    index = json.loads((out / "dataset.json").read_text())
    assert raw.num_episodes == 2 and index["fps"] == 20 and len(index["names"]["state"]) == 18
    ep = raw.read_episode(0)
    meta = json.loads((out / "episode_000000" / "meta.json").read_text())
    assert meta["outcome"] == "success" and meta["seed"] == 4 and meta["sim_model"] == "panda-play-v1"
    success = np.load(out / "episode_000000" / "arrays" / "success.npy")
    assert success.dtype == bool and success[-1]
    qpos = np.load(out / "episode_000000" / "arrays" / "sim_qpos.npy")
    assert qpos.shape[1] == 23
    assert ep is not None

    # same seed -> same bytes
    again = tmp_path / "raw2"
    cli(["collect", "--task", "reach", "--episodes", "1", "--seed", "4", "--out", str(again)])
    for name in ("action", "state", "environment_state", "sim_qpos", "success"):
        assert (again / "episode_000000" / "arrays" / f"{name}.npy").read_bytes() == (
            out / "episode_000000" / "arrays" / f"{name}.npy"
        ).read_bytes()

    root = tmp_path / "lerobot"
    assert (
        cli(
            [
                "collect",
                "--task",
                "lift",
                "--episodes",
                "1",
                "--play",
                "--sequence",
                "reach,lift",
                "--lerobot",
                "local/panda_play_test",
                "--root",
                str(root),
            ]
        )
        == 0
    )
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset("local/panda_play_test", root=root)
    assert ds.num_episodes == 1 and "next.success" in ds.features
    assert ds.features["observation.environment_state"]["shape"] == (41,)
    assert set(ds.meta.tasks.index) == {"reach", "lift"}


def test_collect_rejects_bad_input(tmp_path, capsys):
    assert cli(["collect", "--task", "fly", "--out", str(tmp_path / "x")]) == 2
    assert "unknown task 'fly'" in capsys.readouterr().err
    assert cli(["collect", "--task", "lift"]) == 2
    (tmp_path / "exists").mkdir()
    assert cli(["collect", "--task", "lift", "--out", str(tmp_path / "exists")]) == 2
    assert "already exists" in capsys.readouterr().err


@pytest.mark.learning
@pytest.mark.parametrize("task", TASKS)
def test_expert_success_rate_50_seeds(task):
    env = make("panda-play", task)
    rate = np.mean([rollout(env, seed).succeeded for seed in range(50)])
    print(f"{task}: {rate:.2f}")
    assert rate >= 0.9


def test_suboptimal_expert_varies_pace_and_approach_from_its_seed_and_still_succeeds():
    """The suboptimal expert (FIRE's human-like demonstrator): per seed its own pace and hover height,
    the same bytes for the same seed, slower than the scripted expert, and still successful; `collect
    --expert suboptimal` records it and FIRE's oracle can take over with it."""
    from shiftkit.envs import env_family
    from shiftkit.envs.panda_play.experts import SUBOPTIMAL_HOVER, SuboptimalExpert, suboptimal_rollout

    env = make("panda-play", "lift", control_hz=5)
    runs = [suboptimal_rollout(env, seed) for seed in range(6)]
    assert all(r.succeeded for r in runs)
    again = suboptimal_rollout(env, 3)
    assert np.array_equal(again.actions, runs[3].actions) and np.array_equal(again.qpos, runs[3].qpos)
    scripted = [rollout(env, seed) for seed in range(6)]
    assert sum(len(r.actions) for r in runs) > sum(len(r.actions) for r in scripted)
    env.reset(seed=0)
    drawn = [SuboptimalExpert(env, seed) for seed in range(6)]
    assert len({round(e.speed, 6) for e in drawn}) == 6
    assert all(SUBOPTIMAL_HOVER[0] <= e.base.above <= SUBOPTIMAL_HOVER[1] for e in drawn)
    family = env_family("panda-play")
    assert family.experts["suboptimal"] is suboptimal_rollout
    policy = family.expert_policies["suboptimal"](env, 7)
    policy.reset()
    assert policy.act({}).shape == (4,)
    env.close()
