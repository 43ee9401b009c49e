"""FIRE end to end: the oracle's forks, `shiftkit fire` on a tiny dataset, the aggregated dataset in
LeRobotDataset / lerobot-train / `shiftkit train bc`, kill + resume, plots and one-line errors.

Environments come from the registry: every family whose scripted expert acts from any state."""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from shiftkit.app.cli import main
from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import ConfigError, DatasetError
from shiftkit.envs import families, make
from shiftkit.policies.fire.oracle import SimulatedOracle, fork_env, scripted_expert, sim_state
from tests.helpers import lerobot_train_two_steps

# a task per family whose tiny BC policy both fails and succeeds (families not listed: their first task)
TASK = {"panda-play": "lift"}


def _expert_envs() -> list[tuple[str, str]]:
    out = []
    for name, family in families().items():
        task = TASK.get(name, next(iter(family.tasks)))
        env = make(name, task)
        try:
            scripted_expert(name, env)
        except ConfigError:
            continue
        finally:
            env.close()
        out.append((name, task))
    return out


EXPERT_ENVS = _expert_envs()


def _data_arrays(env) -> dict[str, np.ndarray]:
    data = env.unwrapped.physics.data if hasattr(env.unwrapped, "physics") else env.unwrapped.data
    names = ("qpos", "qvel", "act", "ctrl", "qacc_warmstart", "xpos", "xquat", "sensordata", "time")
    return {n: np.array(getattr(data, n), copy=True) for n in names}


@pytest.mark.parametrize(("env_name", "task"), EXPERT_ENVS)
def test_oracle_look_ahead_leaves_the_episode_bit_identical(env_name, task):
    env, twin = make(env_name, task), make(env_name, task)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (40, env.action_space.shape[0])).astype(np.float32)
    obs, _ = env.reset(seed=7)
    twin.reset(seed=7)
    for a in actions[:5]:
        obs, *_ = env.step(a)
        twin.step(a)
    before = _data_arrays(env)
    calls = []

    def agent(sim, o):  # a fixed open-loop policy, applied in the fork
        calls.append(sim)
        return actions[5 + min(len(calls), 30)], {"d": 0.5, "doubt": 0.0}

    oracle = SimulatedOracle(env_name, agent, check_step=5)
    failed = oracle.will_fail(env, obs, t=5)
    assert oracle.forks == 1 and oracle.look_ahead_steps == len(calls) > 1
    assert all(sim is not env for sim in calls)
    after = _data_arrays(env)
    for key in before:
        np.testing.assert_array_equal(after[key], before[key], err_msg=key)
    # the original continues exactly as a twin that was never forked
    for a in actions[5:]:
        o1, r1, _, _, i1 = env.step(a)
        o2, r2, _, _, i2 = twin.step(a)
        np.testing.assert_array_equal(o1, o2)
        assert (r1, i1["is_success"]) == (r2, i2["is_success"])
    # a fork is independent both ways
    sim = fork_env(env)
    sim.step(actions[0])
    assert not np.array_equal(sim_state(sim)[0], sim_state(env)[0]) or not np.array_equal(
        sim_state(sim)[1], sim_state(env)[1]
    )
    assert isinstance(failed, bool)
    env.close()
    twin.close()


def _reference_look_ahead(env, obs, agent_step, stall_steps=5, tolerance=1e-3) -> tuple[bool, list, list]:
    """The look-ahead as a plain deep copy of the env runs it (nothing shared with the original), to
    success, the episode's end or a standstill (the last `stall_steps` qpos within `tolerance`):
    (failed, actions, (qpos, qvel) per step)."""
    sim = copy.deepcopy(env)
    actions, states = [], []
    while True:
        states.append(sim_state(sim))
        action, _ = agent_step(sim, obs)
        obs, _, terminated, truncated, info = sim.step(action)
        actions.append(action)
        if info.get("is_success", False):
            return False, actions, states
        last = [q for q, _ in states[-stall_steps:]]
        still = len(last) == stall_steps and all(np.abs(q - last[-1]).max() < tolerance for q in last)
        if terminated or truncated or still:
            return True, actions, states


@pytest.mark.parametrize(("env_name", "task"), EXPERT_ENVS)
def test_oracle_decisions_equal_a_plain_deep_copy_look_ahead(env_name, task):
    """Seeded episodes, a closed-loop policy that fails and the scripted expert that succeeds: the
    oracle's forks give the same verdict, actions and states, bit for bit, as a look-ahead on a plain
    deep copy of the env."""
    env = make(env_name, task)
    weights = np.random.default_rng(1).normal(0.0, 0.3, (env.action_space.shape[0], env.observation_space.shape[0]))
    experts = {}

    def linear(sim, o):  # deterministic and state-dependent: any difference in the fork would grow
        return np.tanh(weights @ np.nan_to_num(np.asarray(o, dtype=np.float64))).astype(np.float32), {}

    def expert(sim, o):  # one scripted expert per simulator copy, acting from that copy's state
        if id(sim) not in experts:
            experts[id(sim)] = scripted_expert(env_name, sim)
            experts[id(sim)].reset()
        return np.asarray(experts[id(sim)].act(o), dtype=np.float32), {}

    verdicts = []
    for seed, agent_step in ((11, linear), (12, linear), (13, expert)):
        obs, _ = env.reset(seed=seed)
        for _ in range(3):
            obs, *_ = env.step(linear(env, obs)[0])
        experts.clear()
        failed, actions, states = _reference_look_ahead(env, obs, agent_step)
        experts.clear()
        oracle = SimulatedOracle(env_name, agent_step, check_step=3)
        assert oracle.will_fail(env, obs, 3) is failed
        ahead = oracle.look_ahead
        assert oracle.look_ahead_steps == len(actions) == len(ahead.states)
        for (q1, v1), (q2, v2) in zip(ahead.states, states, strict=True):
            np.testing.assert_array_equal(q1, q2)
            np.testing.assert_array_equal(v1, v2)
        verdicts.append(failed)
    assert verdicts == [True, True, False]
    env.close()


@pytest.mark.parametrize(("env_name", "task"), EXPERT_ENVS)
def test_oracle_answers_from_one_look_ahead_and_the_expert_finishes(env_name, task):
    env = make(env_name, task)
    obs, _ = env.reset(seed=3)
    hold = np.zeros(env.action_space.shape[0], dtype=np.float32)  # never solves the task
    oracle = SimulatedOracle(env_name, lambda sim, o: (hold, {"d": 0.1, "doubt": 0.0}), check_step=2)
    assert oracle.will_fail(env, obs, 0) is True
    obs, *_ = env.step(hold)
    assert oracle.will_fail(env, obs, 1) is True and oracle.forks == 1  # the same future, no new fork
    obs, *_ = env.step(hold)
    assert oracle.stops_unpredicted(env, obs, 2) == "deadline"
    expert = oracle.take_over(env)
    info = {"is_success": False}
    truncated = False
    while not info["is_success"] and not truncated:
        obs, _, _, truncated, info = env.step(expert.act(obs))
    assert info["is_success"]
    env.close()


@pytest.mark.parametrize(("env_name", "task"), EXPERT_ENVS)
def test_oracle_stops_a_standstill_as_it_shows_and_a_wandering_failure_at_the_deadline(env_name, task):
    """Unpredicted failures are stopped where a person would see them: once nothing has moved for
    `stall_steps` (qpos within the tolerance), else at `check_step`; never when the policy would
    still succeed."""
    env = make(env_name, task)
    dim = env.action_space.shape[0]
    hold = np.zeros(dim, dtype=np.float32)
    oracle = SimulatedOracle(env_name, lambda sim, o: (hold, {}), check_step=60, stall_steps=4, stall_tolerance=1e-3)
    obs, info = env.reset(seed=4)
    oracle.start_episode()
    seen = []
    for t in range(60):
        seen.append(info["qpos"])
        reason = oracle.stops_unpredicted(env, obs, t)
        window = seen[-4:]
        still = len(window) == 4 and all(np.max(np.abs(q - window[-1])) < 1e-3 for q in window)
        assert (reason == "stalled") is still, t
        if reason:
            break
        obs, _, _, _, info = env.step(hold)
    assert reason == "stalled" and t >= 3

    def wander(sim, o):  # keeps moving back and forth (simulated time sets the phase), never solves the task
        data = sim.unwrapped.physics.data if hasattr(sim.unwrapped, "physics") else sim.unwrapped.data
        return np.full(dim, 0.6 * np.sin(4.0 * data.time), dtype=np.float32), {}

    oracle = SimulatedOracle(env_name, wander, check_step=12, stall_steps=4, stall_tolerance=1e-3)
    obs, _ = env.reset(seed=5)
    oracle.start_episode()
    reasons = []
    for t in range(13):
        reasons.append(oracle.stops_unpredicted(env, obs, t))
        obs, *_ = env.step(wander(env, obs)[0])
    if reasons[-1] is not None:  # the wandering run failed: stopped at the deadline, not before
        assert reasons == [None] * 12 + ["deadline"]
    experts = {}

    def expert(sim, o):
        if id(sim) not in experts:
            experts[id(sim)] = scripted_expert(env_name, sim)
            experts[id(sim)].reset()
        return np.asarray(experts[id(sim)].act(o), dtype=np.float32), {}

    oracle = SimulatedOracle(env_name, expert, check_step=0, stall_steps=4, stall_tolerance=1e-3)
    obs, _ = env.reset(seed=6)
    assert oracle.stops_unpredicted(env, obs, 0) is None  # past the deadline, but it would succeed
    env.close()


class _HoldAgent:
    """A policy that holds still (it never solves the task), with a constant D."""

    keys = ["observation.state"]

    def __init__(self, dim: int) -> None:
        self.hold = np.zeros(dim, dtype=np.float32)

    def observe(self, env, obs):
        return {"observation.state": np.asarray(obs, dtype=np.float32)}

    def decide(self, features):
        return self.hold, 0.0

    def d_score(self, features, action):
        return 0.1

    def __call__(self, env, obs):
        return self.hold, {"d": 0.1, "doubt": 0.0}


class _AskAt:
    """A predictor that asks at the given steps (and records what it was told)."""

    def __init__(self, steps):
        self.steps, self.told, self.resets = set(steps), [], 0

    def reset(self):
        self.resets += 1

    def predict(self, t, d, doubt=0.0):
        return t in self.steps

    def feedback(self, kind):
        self.told.append(kind)


def test_an_episode_holds_several_interventions_and_none_before_d_is_ready():
    """`run_episode`: before D is ready nothing asks, stops or takes over, whatever the predictor
    says; afterwards every agreed prediction starts a correction that ends where the expert hands
    back (here a person who hands back after two steps, too early), and the policy drives again."""
    from shiftkit.policies.fire.episode import run_episode

    env_name, task = EXPERT_ENVS[-1]
    env = make(env_name, task)
    agent = _HoldAgent(env.action_space.shape[0])

    class EarlyHandBack(SimulatedOracle):
        calls = 0

        def can_finish(self, env, obs, t):
            EarlyHandBack.calls += 1
            return t - self.taken >= 2

        def take_over(self, env, seed=0):
            self.taken = self._t
            return super().take_over(env, seed)

        def will_fail(self, env, obs, t):
            self._t = t
            return super().will_fail(env, obs, t)

    oracle = EarlyHandBack(env_name, agent, check_step=10**6, stall_steps=10**6)  # no stops of its own
    features = {"observation.state": {}}
    warm = run_episode(env, 3, agent, _AskAt(range(200)), oracle, False, features, fp_cooldown=5)
    assert not warm.frames["intervention"].any() and not warm.frames["intervention_request"].any()
    assert warm.feedback == [] and warm.interventions == [] and oracle.forks == 0 and EarlyHandBack.calls == 0
    assert [(s.start, s.expert, s.failed) for s in warm.segments] == [(0, False, not warm.success)]

    asker = _AskAt([3, 9])
    ep = run_episode(env, 3, agent, asker, oracle, True, features, fp_cooldown=5)
    assert asker.told == ["tp", "tp"] and asker.resets == 3  # the episode's start and two hand-backs
    assert [(x["start"], x["end"], x["kind"]) for x in ep.interventions] == [(3, 5, "tp"), (9, 11, "tp")]
    flags = ep.frames["intervention"][:, 0]
    np.testing.assert_array_equal(np.flatnonzero(flags), [3, 4, 9, 10])
    np.testing.assert_array_equal(ep.frames["source"][:, 0], np.where(flags, 2, 1))
    parts = [(s.start, s.expert, s.failed) for s in ep.segments]
    assert parts == [(0, False, True), (3, True, False), (5, False, True), (9, True, False), (11, False, True)]
    assert ep.policy_failed and ep.frames["intervention_request"][[3, 9], 0].all()
    env.close()


# ------------------------------------------------------------------------------ shiftkit fire


def _fire_cli(env_name: str, task: str, demo: Path, out: Path, *extra: str) -> list[str]:
    return [
        "fire",
        "--dataset",
        str(demo),
        "--env",
        env_name,
        "--task",
        task,
        "--output",
        str(out),
        "--max-episodes",
        "4",
        "--budget-expert-samples",
        "100000",
        "--bc.regime",
        "fixed",
        "--bc.steps",
        "150",
        "--bc.ensemble",
        "2",
        "--bc.hidden",
        "32,32",
        "--d-hidden",
        "16,16",
        "--d-start",
        "20",
        "--retrain-every",
        "30",
        "--beta",
        "3",
        "--device",
        "cpu",
        "--threads",
        "1",
        *extra,
    ]


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> tuple[str, str, Path]:
    env_name, task = EXPERT_ENVS[0]
    rate = min(families()[env_name].control_rates)
    root = tmp_path_factory.mktemp("fire") / "demo"
    assert (
        main(
            [
                "collect",
                "--env",
                env_name,
                "--task",
                task,
                "--episodes",
                "3",
                "--control-hz",
                str(rate),
                "--lerobot",
                "test/fire-demo",
                "--root",
                str(root),
            ]
        )
        == 0
    )
    return env_name, task, root


@pytest.fixture(scope="module")
def fire_run(demo, tmp_path_factory) -> tuple[Path, Path]:
    env_name, task, root = demo
    out = tmp_path_factory.mktemp("fire") / "run"
    ds_root = out.parent / "aggregated"
    args = _fire_cli(env_name, task, root, out, "--repo-id", "test/fire-agg", "--dataset-root", str(ds_root))
    assert main([*args, "--predictor", "gda+doubt"]) == 0
    return out, ds_root


def _episode_lines(run: Path) -> list[dict]:
    return [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines() if '"episode"' in x]


def test_fire_writes_the_aggregated_dataset(demo, fire_run):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from shiftkit.datasets.reader import open_lerobot_dataset

    run, ds_root = fire_run
    lines = _episode_lines(run)
    assert len(lines) == 4
    ds = LeRobotDataset("test/fire-agg", root=ds_root)
    assert ds.meta.total_episodes == 3 + 4
    for key, dtype in (("intervention", "bool"), ("source", "int64"), ("discriminator_score", "float32")):
        assert ds.meta.features[key]["dtype"] == dtype and tuple(ds.meta.features[key]["shape"]) == (1,)
    assert ds[len(ds) - 1]["intervention"].numel() == 1  # lerobot hands (1,) features out as scalars
    reader = open_lerobot_dataset(ds_root)
    episodes = list(reader.iter_episodes())
    for ep in episodes[:3]:  # the demonstrations
        assert (ep.frames["source"] == 0).all() and not ep.frames["intervention"].any()
    for ep, line in zip(episodes[3:], lines, strict=True):
        source = ep.frames["source"][:, 0]
        assert ep.meta["fire"]["source"] == "rollout"
        np.testing.assert_array_equal(ep.frames["intervention"][:, 0], source == 2)
        assert np.isin(source, (1, 2)).all()
        assert not ep.frames["intervention_request"][source == 2].any()  # requests only where the policy drove
        # the expert drove exactly the logged interventions, each started by an agreed prediction or a stop
        expected = np.ones(len(ep), dtype=int)
        for x in line["interventions"]:
            expected[x["start"] : x["end"]] = 2
        np.testing.assert_array_equal(source, expected)
        assert [x["kind"] for x in line["interventions"]] == [f for f in line["feedback"] if f != "fp"]
        assert line["intervened_at"] == (line["interventions"][0]["start"] if line["interventions"] else None)
        assert line["length"] == len(ep)
    # lerobot's own declaration of the DAgger flag, kept as it is
    assert ds.meta.features["intervention"]["names"] is None
    assert (ds_root / "meta" / "failure_predictor.pt").is_file() and (ds_root / "meta" / "fire_roc.json").is_file()
    assert sum(line["episode_expert_samples"] for line in lines) == lines[-1]["corrections"]
    assert lines[-1]["env_steps"] == sum(len(ep) for ep in episodes[3:])
    assert main(["info", str(ds_root)]) == 0 and main(["validate", str(ds_root)]) == 0
    # the current policy is a BC run folder that `shiftkit eval` understands
    assert (run / "policy" / "config.json").is_file() and (run / "policy" / "checkpoints" / "last.txt").is_file()
    # the run records its BC settings nested, as the initial BC got them
    bc = json.loads((run / "config.json").read_text())["args"]["bc"]
    initial = json.loads((run / "bc-init" / "config.json").read_text())["args"]
    assert (bc["regime"], bc["steps"], bc["ensemble_size"], bc["hidden"]) == ("fixed", 150, 2, [32, 32])
    assert all(initial[k] == v for k, v in bc.items() if v is not None)
    # ... and a finished one (eval does not warn of an unfinished run), with its model card
    assert (run / "policy" / "card.json").is_file() and (run / "policy" / "README.md").is_file()


def test_shiftkit_train_bc_on_the_aggregated_dataset_by_id(fire_run, tmp_path, monkeypatch):
    run, ds_root = fire_run
    home = tmp_path / "home"
    (home / "test").mkdir(parents=True)
    (home / "test" / "fire-agg").symlink_to(ds_root)
    monkeypatch.setenv("HF_LEROBOT_HOME", str(home))
    args = ["train", "bc", "--dataset", "test/fire-agg", "--output", str(tmp_path / "bc"), "--regime", "fixed"]
    assert main([*args, "--steps", "3", "--ensemble", "1", "--hidden", "8", "--device", "cpu"]) == 0
    assert (tmp_path / "bc" / "checkpoints" / "last.txt").is_file()


# ------------------------------------------------------------------------------ Algorithm 2, item by item


def _rollout_episodes(run: Path) -> list:
    from shiftkit.datasets.reader import open_lerobot_dataset

    return list(open_lerobot_dataset(run / "rollouts").iter_episodes())


def test_no_intervention_prediction_or_bc_update_before_d_is_ready(fire_run):
    """Warm-up (thesis 5.4.2): until D has trained on `--d-start` policy samples, the BC policy runs
    on its own: no prediction, no stop, no takeover, no BC update; the DAgger recording agrees."""
    run, _ = fire_run
    lines = _episode_lines(run)
    warm = [x for x in lines if not x["d_ready"]]
    assert warm and lines[len(warm)]["d_ready"]  # the warm-up, then Algorithm 2 proper
    for x in warm:
        assert x["predictions"] == 0 and x["feedback"] == [] and x["interventions"] == [] and x["stops"] == []
        assert x["episode_expert_samples"] == 0 and x["bc_loss"] is None and "retrain_epochs" not in x
    assert warm[-1]["policy_samples"] >= 20 and all(x["policy_samples"] < 20 for x in warm[:-1])
    for ep in _rollout_episodes(run)[: len(warm)]:
        assert not ep.frames["intervention"].any()
    assert all(x["bc_loss"] is not None for x in lines[len(warm) :])


def test_the_expert_hands_control_back_once_the_policy_can_finish(fire_run):
    """Algorithm 2, lines 27-28 (Fig. 5.1): a correction ends as soon as the policy can finish from
    the current state; the policy then drives again, and succeeds (the oracle's look-ahead is exact).
    The DAgger recording shows it as `intervention` True, then False, within one episode."""
    run, _ = fire_run
    episodes = _rollout_episodes(run)
    back = [i for i, ep in enumerate(episodes) if (np.diff(ep.frames["intervention"][:, 0].astype(int)) == -1).any()]
    assert back, "no correction was handed back to the policy"
    lines = _episode_lines(run)
    for i in back:
        flags = episodes[i].frames["intervention"][:, 0]
        handed = [x for x in lines[i]["interventions"] if x["end"] < len(flags)]
        assert handed and lines[i]["success"]
        for stretch in handed:
            assert flags[stretch["start"] : stretch["end"]].all() and not flags[stretch["end"] :].any()
    assert lines[-1]["corrections"] < sum(x["length"] - x["intervened_at"] for x in lines if x["intervened_at"])


def test_protocol_check_reads_warm_up_and_hand_backs_from_metrics_and_recording(fire_run):
    """`fire.runs.protocol_check` (the study's acceptance numbers): no intervention before D is ready
    and the hand-backs, counted alike from the episode lines and the DAgger recording."""
    from shiftkit.policies.fire.runs import protocol_check

    run, _ = fire_run
    check = protocol_check(run)
    metrics, recording = check["metrics"], check["recording"]
    lines = _episode_lines(run)
    assert metrics["episodes"] == recording["episodes"] == len(lines)
    assert metrics["warm_up_episodes"] == sum(not x["d_ready"] for x in lines) > 0
    assert metrics["interventions_before_d"] == recording["intervention_frames_before_d"] == 0
    assert recording["first_episode_with_intervention"] >= metrics["warm_up_episodes"]
    assert metrics["hand_backs"] == recording["hand_backs"] >= 1
    assert metrics["interventions"] == sum(len(x["interventions"]) for x in lines)


def test_missed_failures_are_stopped_where_they_show_and_logged(fire_run, demo):
    """An unpredicted failure is stopped once the policy has stood still for 2 s (every simulator
    position within 2 cm or rad, checked here on the recorded sim.qpos), at the latest at the
    episode's end minus the median demonstration's length; each stop is logged with its reason and
    starts an intervention ("fn")."""
    from shiftkit.datasets.reader import open_lerobot_dataset
    from shiftkit.policies.fire.recording import load_npz

    run, _ = fire_run
    env_name, task, root = demo
    demos = open_lerobot_dataset(root)
    lengths = [len(ep) for ep in demos.iter_episodes()]
    horizon = make(env_name, task, control_hz=demos.fps).max_episode_steps
    deadline = horizon - int(np.median(lengths))
    stall = math.ceil(2.0 * demos.fps)
    lines = _episode_lines(run)
    stopped = 0
    for line in lines:
        frames, _ = load_npz(run / "episodes" / f"episode_{line['episode']:06d}.npz")
        first, kinds = line["intervened_at"], [f for f in line["feedback"] if f != "fp"]
        if first is None or kinds[0] != "fn":  # the first intervention was not a stop
            continue
        stopped += 1
        qpos = frames["sim.qpos"][max(0, first - stall + 1) : first + 1]
        still = first + 1 >= stall and (np.abs(qpos - qpos[-1]).max(axis=1) < 0.02).all()
        assert still or first >= deadline, (line["episode"], first, deadline)
    assert stopped
    assert lines[0]["deadline_step"] == deadline
    for line in lines:
        for stop in line["stops"]:
            assert stop["reason"] in ("stalled", "deadline")
            assert {"start": stop["step"], "kind": "fn"}.items() <= next(
                i for i in line["interventions"] if i["start"] == stop["step"]
            ).items()


def test_gda_learns_from_executed_segments(fire_run):
    """GDA's statistics hold executed stretches: a policy stretch that ended in an intervention is a
    failure, expert corrections are success-class data (the reference's `append_traj`)."""
    from shiftkit.policies.run_dir import load_checkpoint

    run, _ = fire_run
    state = load_checkpoint(sorted((run / "checkpoints").glob("step-*.safetensors"))[-1])
    lines = _episode_lines(run)
    ends = {i["start"] for x in lines for i in x["interventions"]} | {x["length"] for x in lines if not x["success"]}
    segments = state["gda"]["segments"]
    assert any(s["expert"] for s in segments) and any(s["failed"] for s in segments)
    for s in segments:
        if s["failed"] and not s["expert"]:  # ended in an intervention or the episode's failure
            assert s["start"] + len(s["d"]) in ends
        assert s["d"] is not None  # re-scored by the trained D


def _demo_frames(root: Path) -> tuple[int, int]:
    from shiftkit.datasets.reader import open_lerobot_dataset

    demos = open_lerobot_dataset(root)
    return sum(len(ep) for ep in demos.iter_episodes()), demos.fps


def test_execution_time_counts_the_demonstrations(fire_run, demo):
    """Execution time = (demonstration frames + every executed step) / fps (thesis 5.5.1: the
    demonstrations are robot time too)."""
    run, _ = fire_run
    frames, fps = _demo_frames(demo[2])
    last = _episode_lines(run)[-1]
    assert last["execution_time_s"] == pytest.approx((frames + last["env_steps"]) / fps)


def test_success_finals_join_the_expert_set_but_are_not_expert_samples(fire_run, demo):
    """A success's final (s_T, a_T) joins D_E (thesis 5.3.4) but no expert gave it: expert samples
    = demonstration frames + corrections."""
    from shiftkit.policies.fire.recording import load_npz
    from shiftkit.policies.run_dir import load_checkpoint

    run, _ = fire_run
    frames, _ = _demo_frames(demo[2])
    lines = _episode_lines(run)
    finals = 0  # successes whose last step the policy took
    for line in lines:
        flags, _ = load_npz(run / "episodes" / f"episode_{line['episode']:06d}.npz")
        finals += line["success"] and not flags["intervention"][-1, 0]
    assert finals > 0
    assert lines[-1]["expert_samples"] == frames + lines[-1]["corrections"]
    state = load_checkpoint(sorted((run / "checkpoints").glob("step-*.safetensors"))[-1])
    assert len(state["expert_set"]["action"]) == frames + lines[-1]["corrections"] + finals


def test_fire_policy_is_the_thesis_network_by_default(fire_run):
    """Thesis 5.4.2: one 2x256 MLP with a tanh output, FIRE's own defaults; the ensemble-doubt
    predictors keep an ensemble."""
    from shiftkit.policies.bc_policy import load_policy
    from shiftkit.policies.fire.config import FireArgs, FireBC

    args = FireArgs(dataset="d", env="panda-play", task="lift", output_dir="o").resolved()
    assert (args.bc.ensemble_size, args.bc.hidden, args.bc.output_activation) == (1, [256, 256], "tanh")
    assert FireArgs("d", "panda-play", "lift", "o", predictor="gda+doubt").resolved().bc.ensemble_size == 5
    with pytest.raises(ConfigError, match="needs an ensemble"):
        FireArgs("d", "panda-play", "lift", "o", predictor="doubt", bc=FireBC(ensemble_size=1)).resolved()
    # FIRE's defaults hold for settings built in code too, beside the ones given
    assert (FireBC(batch_size=8).hidden, FireBC(batch_size=8).output_activation) == ([256, 256], "tanh")
    run, _ = fire_run
    policy = load_policy(run / "policy")
    assert policy.spec.output_activation == "tanh" and len(policy.members) == 2  # the fixture's --ensemble 2
    assert policy.act({k: np.zeros(ft["shape"], np.float32) for k, ft in policy.features.items()}).max() <= 1.0


def test_every_bc_setting_of_fire_reaches_its_initial_bc(monkeypatch, tmp_path):
    """`FireArgs.bc` is BC's settings (`BCSettings`), handed to `shiftkit train bc` whole: each one,
    set to a value no default has, arrives in the initial BC's arguments unchanged."""
    import torch

    from shiftkit.policies.fire import loop
    from shiftkit.policies.fire.config import FireArgs, FireBC
    from shiftkit.policies.trainers.bc.args import BCArgs, BCSettings

    changed = dict(
        regime="fixed", steps=7, max_epochs=3, patience=2, batch_size=5, lr=0.5, weight_decay=0.25,
        val_fraction=0.3, ensemble_size=3, inputs=["observation.state"], encoder="resnet18",
        encoder_weights="w.pt", num_keypoints=6, hidden=[9, 9], output_activation="linear",
        norm_std_floor=0.05, norm_clip=4.0,
    )  # fmt: skip
    assert set(changed) == {f.name for f in dataclasses.fields(BCSettings)}  # a new setting joins this test
    assert all(changed[f.name] != getattr(FireBC(), f.name) for f in dataclasses.fields(FireBC))
    seen = []
    monkeypatch.setattr(loop, "train_bc", seen.append)
    monkeypatch.setattr(loop, "load_policy", lambda *a, **k: None)
    args = FireArgs("d", "panda-play", "lift", str(tmp_path), bc=FireBC(**changed), seed=4).resolved()
    loop._initial_bc(args, tmp_path / "bc-init", torch.device("cpu"))
    (bc,) = seen
    assert isinstance(bc, BCArgs) and {name: getattr(bc, name) for name in changed} == changed
    assert (bc.datasets, bc.output_dir, bc.seed) == (["d"], str(tmp_path / "bc-init"), 4)
    # the retrainings' hold-out share is the nested one; unset, 0.2 in either regime
    assert args.hold_out_share == 0.3 and FireArgs("d", "e", "t", "o", bc=FireBC(regime="fixed")).hold_out_share == 0.2
    with pytest.raises(ConfigError, match=r"bc.val_fraction must be in \(0, 1\), got 0"):
        FireArgs("d", "panda-play", "lift", "o", bc=FireBC(val_fraction=0.0)).resolved()
    with pytest.raises(ConfigError, match="bc.hidden must be a positive integer, got 0"):
        FireArgs("d", "panda-play", "lift", "o", bc=FireBC(hidden=[4, 0])).resolved()


def test_per_episode_updates_never_sample_the_retraining_hold_out():
    """The full retraining early-stops on expert frames the per-episode updates never drew (thesis
    5.3.4), so its validation measures what the retraining adds."""
    import torch

    from shiftkit.policies.bc_policy import BCPolicy, PolicySpec
    from shiftkit.policies.fire.config import FireArgs, FireBC
    from shiftkit.policies.fire.learning import online_update, retrain
    from shiftkit.policies.frame_buffer import FrameBuffer

    spec = PolicySpec(
        features={"observation.state": {"dtype": "float32", "shape": [3], "names": None}},
        action={"dtype": "float32", "shape": [2], "names": None},
        stats={"observation.state": {"mean": [0.0] * 3, "std": [1.0] * 3}, "action": {"mean": [0, 0], "std": [1, 1]}},
        encoder="cnn", num_keypoints=4, hidden=[8], ensemble_size=1, output_activation="tanh",
    )  # fmt: skip
    rng = np.random.default_rng(0)
    expert = FrameBuffer(["observation.state", "action"])
    expert.add({"observation.state": rng.normal(size=(50, 3)).astype(np.float32), "action": np.zeros((50, 2), "f4")})
    held = np.zeros(50, dtype=bool)
    held[rng.choice(50, 10, replace=False)] = True
    drawn = []
    gather = expert.gather
    expert.gather = lambda rows, device="cpu": (drawn.append(np.asarray(rows)), gather(rows, device))[1]
    policy = BCPolicy(spec)
    opts = [torch.optim.Adam(policy.members[0].parameters())]
    args = FireArgs("d", "panda-play", "lift", "o", bc=FireBC(batch_size=8), retrain_max_epochs=3)
    online_update(policy, opts, expert, np.flatnonzero(~held), 20, args, rng, "cpu")
    assert drawn and not held[np.concatenate(drawn)].any()
    drawn.clear()
    out = retrain(policy, opts, expert, held, args, 0, "cpu")
    assert (out["retrain_frames"], out["retrain_val_frames"]) == (40, 10)
    validation, *training = drawn
    np.testing.assert_array_equal(np.sort(validation), np.flatnonzero(held))
    assert not held[np.concatenate(training)].any()


@pytest.mark.slow
def test_lerobot_train_act_on_the_aggregated_dataset(fire_run, tmp_path):
    _, ds_root = fire_run
    lerobot_train_two_steps("test/fire-agg", ds_root, tmp_path / "train")


def _comparable(lines: list[dict]) -> list[dict]:
    timing = ("wall_time_s", "episode_exec_s", "episode_cpu_s")
    return [{k: v for k, v in x.items() if k not in timing} for x in lines]


def test_fire_resumes_after_sigkill_as_if_never_stopped(demo, fire_run, tmp_path):
    env_name, task, root = demo
    reference, _ = fire_run
    out = tmp_path / "run"
    args = _fire_cli(env_name, task, root, out, "--dataset-root", str(tmp_path / "agg"), "--predictor", "gda+doubt")
    code = "import sys; from shiftkit.app.cli import main; sys.exit(main(sys.argv[1:]))"
    proc = subprocess.Popen([sys.executable, "-c", code, *args], start_new_session=True)
    last = out / "checkpoints" / "last.txt"
    deadline = time.time() + 300
    while not last.exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert last.exists() and not (tmp_path / "agg").exists()
    assert main([*args, "--resume"]) == 0
    assert _comparable(_episode_lines(out)) == _comparable(_episode_lines(reference))
    assert main([*args, "--resume"]) == 0  # a finished run resumes to its summary
    assert main([*args, "--resume", "--bc.hidden", "16,16"]) == 2  # only the run that made it


def test_a_run_stored_with_flat_bc_settings_resumes(demo, fire_run, tmp_path, capsys):
    """Before `FireArgs.bc`, a FIRE run stored BC's settings flat (`bc_regime`, `hidden`, ...,
    `val_fraction` 0.2 by default): it resumes with today's options, and only with the same settings
    (a refused resume leaves its config as it was)."""
    import shutil

    env_name, task, root = demo
    reference, ds_root = fire_run
    run = tmp_path / "run"
    shutil.copytree(reference, run)
    for path in (run / "config.json", run / "policy" / "config.json"):
        config = json.loads(path.read_text())
        bc, args = config["args"].pop("bc"), config["args"]
        args.update(bc_regime=bc["regime"], bc_steps=bc["steps"], val_fraction=0.2, output_dir=str(run))
        args.update({k: bc[k] for k in ("ensemble_size", "hidden", "output_activation", "batch_size")})
        path.write_text(json.dumps(config))
    stored = (run / "config.json").read_bytes()
    args = [*_fire_cli(env_name, task, root, run, "--repo-id", "test/fire-agg", "--dataset-root", str(ds_root))]
    args += ["--predictor", "gda+doubt", "--resume"]
    assert main([*args, "--bc.hidden", "16,16"]) == 2 and (run / "config.json").read_bytes() == stored
    assert "--resume with a different 'bc.hidden' ([32, 32] in" in capsys.readouterr().err
    assert main(args) == 0
    assert json.loads((run / "config.json").read_text())["args"]["bc"]["hidden"] == [32, 32]


def test_plots_of_a_fire_run(fire_run, tmp_path, capsys, monkeypatch):
    from matplotlib.figure import Figure

    drawn = []
    save = Figure.savefig
    monkeypatch.setattr(Figure, "savefig", lambda fig, *a, **k: (drawn.append(fig), save(fig, *a, **k))[1])
    run, _ = fire_run
    assert main(["plot", "fire", f"mine={run}", "--out", str(tmp_path / "fire.png"), "--window", "2"]) == 0
    assert (tmp_path / "fire-expert.png").stat().st_size > 0 and (tmp_path / "fire-time.png").stat().st_size > 0
    lines = _episode_lines(run)
    expert, time = (fig.axes[0] for fig in drawn)
    assert [t.get_text() for t in expert.get_legend().get_texts()] == [f"mine ({len(lines)} episodes) (n = 1 run)"]
    assert expert.get_title().startswith("mine (") and time.get_xlabel() == "total execution time (s)"
    # runs under one label are one method's seeds: one line, the IQM of their curves
    drawn.clear()
    assert main(["plot", "fire", f"a={run}", f"a={run}", "--out", str(tmp_path / "two.png"), "--window", "2"]) == 0
    (line,) = drawn[0].axes[0].lines
    from shiftkit.policies.fire.runs import success_curve

    x, rate, _, _ = success_curve(lines, "expert_samples", 2)
    last = [rate[np.flatnonzero(x <= g)[-1]] for g in np.unique(x)]
    np.testing.assert_allclose(line.get_ydata(), last)
    assert drawn[0].axes[0].get_legend().get_texts()[0].get_text() == "a (IQM, 95% bootstrap CI) (n = 2 runs)"
    labels = [not x["policy_success"] for x in lines if x["d_ready"]]
    code = main(["plot", "roc", str(run), "--out", str(tmp_path / "roc.png")])
    if 0 < sum(labels) < len(labels):
        assert code == 0 and (tmp_path / "roc.png").stat().st_size > 0
        assert "gda: AUC" in capsys.readouterr().out
        title = drawn[-1].axes[0].get_title()
        assert (
            f"failure prediction, {run.name}" in title and f"n = {len(labels)} episodes, {sum(labels)} failed" in title
        )
    else:  # too few episodes for both outcomes: a one-line error, no figure
        assert code == 2 and not (tmp_path / "roc.png").exists()


def test_seed_curve_is_the_iqm_of_the_runs_step_functions():
    """`plot fire` draws one line per method: at every x where all its runs have data, the IQM of each
    run's last windowed success at or before x, with a bootstrap band over the runs."""
    from shiftkit.policies.fire.runs import seed_curve

    def lines(xs, ok):
        return [{"expert_samples": x, "policy_success": o} for x, o in zip(xs, ok, strict=True)]

    runs = [lines([10, 20, 30], [0, 1, 1]), lines([10, 25, 40], [1, 1, 0]), lines([15, 30, 35], [0, 0, 1])]
    x, mid, low, high = seed_curve(runs, "expert_samples", window=1, reps=200)
    np.testing.assert_array_equal(x, [15, 20, 25, 30])  # from the latest first x to the earliest last x
    expected = np.array([[0, 1, 1, 1], [1, 1, 1, 1], [0, 0, 0, 0]], dtype=float).mean(axis=0)  # 3 runs: IQM = mean
    np.testing.assert_allclose(mid, expected)
    assert (low <= mid + 1e-12).all() and (high >= mid - 1e-12).all()


def test_plot_fire_draws_bc_at_its_training_frames(demo, fire_run, tmp_path, capsys):
    """`plot fire --bc`: BC is a point at its dataset's frames (and frames / fps on the time panel),
    at its evaluation's success with the Wilson interval; a label's runs pool their episodes."""
    import shutil

    from shiftkit.policies.curves import Point, draw_curves
    from shiftkit.policies.evaluation import EpisodeResult, EvalReport, record_evaluation, wilson_interval
    from shiftkit.policies.fire.runs import bc_reference

    env_name, task, root = demo
    bc = tmp_path / "bc-s0"
    train = ["train", "bc", "--dataset", str(root), "--output", str(bc), "--regime", "fixed", "--steps", "2"]
    assert main([*train, "--ensemble", "1", "--hidden", "8", "--device", "cpu", "--no-progress"]) == 0
    other = tmp_path / "bc-s1"
    shutil.copytree(bc, other)
    for run, wins in ((bc, [True, False, False]), (other, [True, True, False, False])):
        results = [EpisodeResult(i, 100 + i, w, 5, 0.0) for i, w in enumerate(wins)]
        record_evaluation(EvalReport(env_name, task, str(run), 100, results), run)
    info = json.loads((root / "meta" / "info.json").read_text())
    ref = bc_reference([bc, other])
    assert ref["expert_samples"] == info["total_frames"]
    assert ref["execution_time_s"] == pytest.approx(info["total_frames"] / info["fps"])
    assert (ref["successes"], ref["episodes"]) == (3, 7)
    assert ref["ci95"] == list(wilson_interval(3, 7))

    fire, _ = fire_run
    capsys.readouterr()
    args = ["plot", "fire", f"fire={fire}", "--bc", f"BC 3 demos={bc},{other}"]
    assert main([*args, "--out", str(tmp_path / "f.png"), "--window", "2"]) == 0
    out = capsys.readouterr().out
    assert f"BC 3 demos: 2 BC run(s), {info['total_frames']} expert samples" in out and "3/7" in out
    assert (tmp_path / "f-expert.png").stat().st_size > 0 and (tmp_path / "f-time.png").stat().st_size > 0

    point = Point("BC 3 demos", ref["execution_time_s"], ref["success"], *ref["ci95"], ref["episodes"])
    ax = draw_curves([], xlabel="total execution time (s)", points=(point,)).axes[0]
    (bar,) = ax.containers
    line = bar.lines[0]
    assert line.get_xdata()[0] == ref["execution_time_s"] and line.get_ydata()[0] == pytest.approx(3 / 7)
    assert ax.get_legend().get_texts()[0].get_text() == "BC 3 demos (n = 7 episodes)"
    assert "BC 3 demos" in ax.get_title()

    # BC on more data (here the aggregated dataset): a curve over the datasets, each pooled over its runs
    _, agg_root = fire_run
    bigger = tmp_path / "bc-agg"
    train = ["train", "bc", "--dataset", str(agg_root), "--output", str(bigger), "--regime", "fixed", "--steps", "2"]
    assert main([*train, "--ensemble", "1", "--hidden", "8", "--device", "cpu", "--no-progress"]) == 0
    record_evaluation(EvalReport(env_name, task, str(bigger), 100, [EpisodeResult(0, 100, True, 5, 0.0)]), bigger)
    curve_args = ["plot", "fire", f"fire={fire}", "--bc", f"BC={bc},{other},{bigger}", "--window", "2"]
    assert main([*curve_args, "--out", str(tmp_path / "c.png")]) == 0
    agg_frames = json.loads((agg_root / "meta" / "info.json").read_text())["total_frames"]
    assert f"BC: 1 BC run(s), {agg_frames} expert samples" in capsys.readouterr().out

    # one run without its evaluation: a one-line error naming the folder
    shutil.rmtree(other / "eval")
    assert main([*args, "--out", str(tmp_path / "g.png")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bc-s1" in err[0] and "exactly one evaluation" in err[0]
    assert not (tmp_path / "g-expert.png").exists()
    # a label given twice would silently drop a run: refused
    assert main(["plot", "fire", str(fire), "--bc", f"a={bc}", "--bc", f"a={other}", "--out", "h.png"]) == 2
    assert "'a' is given twice" in capsys.readouterr().err


def test_fire_user_errors_are_one_line(demo, tmp_path, capsys):
    env_name, task, root = demo
    cases = [
        (["--predictor", "gda"], "--env", "no-such-env", "unknown env"),
        ([], "--task", "no-such-task", "unknown task"),
        ([], "--dataset", str(tmp_path / "missing"), "dataset not found"),
        (["--budget-expert-samples", "0"], None, None, "--budget-expert-samples: must be a positive integer"),
        (["--repo-id", "noslash"], None, None, "ORG/NAME"),
    ]
    for extra, flag, value, message in cases:
        args = _fire_cli(env_name, task, root, tmp_path / "out", *extra)
        if flag is not None:
            args[args.index(flag) + 1] = value
        capsys.readouterr()
        assert main(args) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], err
        assert not (tmp_path / "out").exists()
    assert main(["plot", "roc", str(tmp_path), "--out", str(tmp_path / "r.png")]) == 2


# ------------------------------------------------------------------------------ offline FIRE (DAgger)


def _frames_of(root: Path):
    import pyarrow.parquet as pq

    return pq.read_table(sorted((root / "data").glob("*/*.parquet"))).to_pydict()


def test_simulated_rollouts_are_what_lerobots_dagger_strategy_writes(fire_run, tmp_path):
    """The run's rollouts/ against a recording made the way lerobot-rollout's DAgger strategy makes
    it (record_autonomous=true): LeRobotDataset.create with lerobot's `intervention` declaration,
    add_frame per step, save_episode per episode, finalize."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from shiftkit.datasets.reader import open_lerobot_dataset

    run, _ = fire_run
    ours = run / "rollouts"
    info = json.loads((ours / "meta" / "info.json").read_text())
    assert info["features"]["intervention"] == {"dtype": "bool", "shape": [1], "names": None}
    recorded = open_lerobot_dataset(ours)
    features = {k: v for k, v in recorded.features.items() if k != "intervention"}
    dataset_features = {**features, "intervention": {"dtype": "bool", "shape": (1,), "names": None}}
    ref = LeRobotDataset.create(
        "local/rollout_ref",
        info["fps"],
        root=tmp_path / "ref",
        robot_type=info["robot_type"],
        features=dataset_features,
        use_videos=False,
    )
    for path in sorted((run / "episodes").glob("episode_*.npz")):
        with np.load(path) as z:
            for t in range(len(z["action"])):
                frame = {k: z[k][t] for k in features}
                ref.add_frame(
                    {**frame, "task": recorded.tasks[0], "intervention": np.array([bool(z["intervention"][t, 0])])}
                )
        ref.save_episode()
    ref.finalize()
    theirs = json.loads((tmp_path / "ref" / "meta" / "info.json").read_text())
    for key in ("codebase_version", "fps", "robot_type", "features", "total_episodes", "total_frames", "total_tasks"):
        assert info[key] == theirs[key], key
    a, b = _frames_of(ours), _frames_of(tmp_path / "ref")
    assert a.keys() == b.keys()
    for key in a:
        np.testing.assert_allclose(np.asarray(a[key], dtype=float), np.asarray(b[key], dtype=float), err_msg=key)


def _aggregate_cli(demo_root: Path, rollouts: list[Path], out: Path, *extra: str) -> list[str]:
    return [
        "fire", "aggregate", "--expert", str(demo_root), "--rollouts", *map(str, rollouts), "--out", str(out),
        "--repo-id", "test/fire-agg", "--d-hidden", "16,16", "--beta", "3", "--device", "cpu", "--no-progress",
        *extra,
    ]  # fmt: skip


def test_fire_aggregate_over_the_simulated_rollouts_equals_the_online_run(demo, fire_run, tmp_path, capsys):
    _, _, demo_root = demo
    run, online = fire_run
    out = tmp_path / "offline"
    assert main(_aggregate_cli(demo_root, [run / "rollouts"], out, "--policy", str(run / "bc-init"))) == 0
    assert "ROC AUC against the recorded interventions: beta" in capsys.readouterr().out
    for rel in ("meta/info.json", "meta/stats.json", "meta/fire_roc.json", "meta/tasks.parquet"):
        assert (out / rel).read_bytes() == (online / rel).read_bytes(), rel
    data = sorted(p.relative_to(online) for p in (online / "data").rglob("*.parquet"))
    assert data and data == sorted(p.relative_to(out) for p in (out / "data").rglob("*.parquet"))
    for rel in data:
        assert (out / rel).read_bytes() == (online / rel).read_bytes(), rel


def test_fire_aggregate_reads_both_dagger_layouts_and_its_predictor_runs_in_a_rollout(demo, fire_run, tmp_path, capsys):
    from lerobot.lerobot_types import TransitionKey
    from lerobot.processor.pipeline import DataProcessorPipeline, ProcessorStepRegistry

    from shiftkit.datasets.reader import open_lerobot_dataset
    from shiftkit.policies.fire.dagger_recording import write_recording
    from shiftkit.policies.fire.predictor import FailurePredictor, FailurePredictorStep
    from shiftkit.policies.fire.recording import recorded_episodes

    _, _, demo_root = demo
    run, _ = fire_run
    continuous = open_lerobot_dataset(run / "rollouts")
    corrections = tmp_path / "rollout_corrections"  # record_autonomous=false: each correction one episode
    features = {k: v for k, v in continuous.features.items() if k != "intervention"}
    episodes = recorded_episodes(run / "episodes", continuous.fps, continuous.tasks[0])
    sources = [{"kind": "fire-run", "path": str(run)}]
    write_recording(
        corrections,
        "local/rollout_corrections",
        continuous.fps,
        features,
        episodes,
        sources=sources,
        record_autonomous=False,
    )
    windows = open_lerobot_dataset(corrections)
    lines = _episode_lines(run)
    assert windows.num_episodes == sum(len(x["interventions"]) for x in lines)
    # both layouts carry the provenance every shiftkit dataset does
    for recording, autonomous in ((run / "rollouts", True), (corrections, False)):
        provenance = json.loads((recording / "meta" / "shiftkit_provenance.json").read_text())
        assert provenance["dagger"] == {"record_autonomous": autonomous}
        assert provenance["output"]["episodes"] == open_lerobot_dataset(recording).num_episodes
    assert provenance["sources"] == sources
    # rollouts without a correction make no corrections-only recording, and leave nothing behind
    calm = (
        Episode({**e.frames, "intervention": np.zeros_like(e.frames["intervention"])})
        for e in recorded_episodes(run / "episodes", continuous.fps, continuous.tasks[0])
    )
    with pytest.raises(DatasetError, match="no corrections"):
        write_recording(
            tmp_path / "calm", "local/rollout_calm", continuous.fps, features, calm, sources=sources,
            record_autonomous=False,
        )  # fmt: skip
    assert not (tmp_path / "calm").exists() and not list(tmp_path.glob(".calm*"))

    out = tmp_path / "agg"
    assert main(_aggregate_cli(demo_root, [run / "rollouts", corrections], out, "--d-steps", "64")) == 0
    printed = capsys.readouterr().out
    assert "gda " in printed and f"dataset {out}" in printed
    agg = list(open_lerobot_dataset(out).iter_episodes())
    assert len(agg) == 3 + continuous.num_episodes + windows.num_episodes
    for ep in agg[3 + continuous.num_episodes :]:
        assert (ep.frames["source"] == 2).all() and ep.frames["intervention"].all()

    # the predictor file, as a Python object: D's scores are the dataset's, requests follow the rule
    predictor = FailurePredictor.load(out / "meta" / "failure_predictor.pt")
    ep = agg[3]
    predictor.reset()
    scores = [predictor.predict({k: ep.frames[k][t] for k in features}, ep.frames["action"][t])[0] for t in range(5)]
    np.testing.assert_allclose(scores, ep.frames["discriminator_score"][:5, 0], rtol=1e-5, atol=1e-6)
    # ... and as a lerobot processor step, rebuilt from its saved config through lerobot's registry
    assert ProcessorStepRegistry.get("shiftkit_failure_predictor") is FailurePredictorStep
    pipeline = DataProcessorPipeline(
        steps=[FailurePredictorStep(path=str(out / "meta" / "failure_predictor.pt"), bell=False)]
    )
    pipeline.save_pretrained(tmp_path / "proc")
    loaded = DataProcessorPipeline.from_pretrained(tmp_path / "proc", config_filename="dataprocessorpipeline.json")
    obs = {k: ep.frames[k][0] for k in features if k != "action"}
    result = loaded._forward({TransitionKey.OBSERVATION: obs, TransitionKey.ACTION: ep.frames["action"][0]})
    assert result[TransitionKey.INFO]["failure_score"] == pytest.approx(scores[0], rel=1e-5, abs=1e-6)
    assert isinstance(result[TransitionKey.INFO]["intervention_request"], bool)

    # ROC of the aggregated dataset's stretches through `shiftkit plot roc`
    roc = json.loads((out / "meta" / "fire_roc.json").read_text())
    code = main(["plot", "roc", str(out), "--out", str(tmp_path / "roc.png")])
    if 0 < sum(roc["failed"]) < len(roc["failed"]):
        assert code == 0 and "gda: AUC" in capsys.readouterr().out
    else:
        assert code == 2


def test_fire_aggregate_refuses_recordings_that_do_not_fit(demo, fire_run, tmp_path, capsys):
    from shiftkit.datasets.reader import open_lerobot_dataset
    from shiftkit.policies.fire.dagger_recording import write_recording
    from shiftkit.policies.fire.recording import recorded_episodes

    _, _, demo_root = demo
    run, _ = fire_run
    rec = open_lerobot_dataset(run / "rollouts")
    features = {k: v for k, v in rec.features.items() if k != "intervention"}
    sources = [{"kind": "fire-run", "path": str(run)}]
    other_fps = tmp_path / "rollout_fps"
    episodes = recorded_episodes(run / "episodes", rec.fps * 2, "t")
    write_recording(other_fps, "local/rollout_fps", rec.fps * 2, features, episodes, sources=sources)
    only_corrections = tmp_path / "rollout_corr"
    write_recording(
        only_corrections,
        "local/rollout_corr",
        rec.fps,
        features,
        recorded_episodes(run / "episodes", rec.fps, "t"),
        sources=sources,
        record_autonomous=False,
    )
    cases = [
        ([demo_root], "is --expert"),  # the demonstrations as rollouts: one input given twice
        ([other_fps], f"at {2 * rec.fps} fps but the demonstrations at {rec.fps} fps"),
        ([only_corrections], "pass --policy RUN"),
        ([tmp_path / "missing"], "missing"),
    ]
    for rollouts, message in cases:
        capsys.readouterr()
        assert main(_aggregate_cli(demo_root, rollouts, tmp_path / "out")) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], err
        assert not (tmp_path / "out").exists()
    # corrections only, with the policy that ran them: D compares the corrections with its own actions
    ok = tmp_path / "ok"
    assert (
        main(_aggregate_cli(demo_root, [only_corrections], ok, "--policy", str(run / "bc-init"), "--d-steps", "16"))
        == 0
    )
    provenance = json.loads((ok / "meta" / "shiftkit_provenance.json").read_text())
    assert provenance["fire"]["d_policy_samples"] == "policy actions at corrected states"
    before = sorted(p.stat().st_mtime_ns for p in (run / "rollouts").rglob("*"))
    assert main(_aggregate_cli(demo_root, [run / "rollouts"], run / "rollouts")) == 2  # destination exists
    assert sorted(p.stat().st_mtime_ns for p in (run / "rollouts").rglob("*")) == before
