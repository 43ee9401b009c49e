"""FIRE end to end: the oracle's forks, `shiftkit fire` on a tiny dataset, the aggregated dataset in
LeRobotDataset / lerobot-train / `shiftkit train bc`, kill + resume, plots and one-line errors.

Environments come from the registry: every family whose scripted expert acts from any state."""

from __future__ import annotations

import copy
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from shiftkit.app.cli import main
from shiftkit.datasets.errors import ConfigError
from shiftkit.envs import families, make
from shiftkit.policies.oracle import SimulatedOracle, fork_env, scripted_expert, sim_state
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


def _reference_look_ahead(env, obs, agent_step) -> tuple[bool, list, list]:
    """The look-ahead as a plain deep copy of the env runs it (nothing shared with the original):
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
        if terminated or truncated:
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
    assert oracle.stops_unpredicted(env, obs, 2) and not oracle.stops_unpredicted(env, obs, 3)
    expert = oracle.take_over(env)
    info = {"is_success": False}
    truncated = False
    while not info["is_success"] and not truncated:
        obs, _, _, truncated, info = env.step(expert.act(obs))
    assert info["is_success"]
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
        "3",
        "--budget-expert-samples",
        "100000",
        "--bc-regime",
        "fixed",
        "--bc-steps",
        "150",
        "--ensemble",
        "2",
        "--hidden",
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
    assert len(lines) == 3
    ds = LeRobotDataset("test/fire-agg", root=ds_root)
    assert ds.meta.total_episodes == 3 + 3
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
        start = line["intervened_at"]
        if start is None:
            assert (source == 1).all()
        else:  # the expert keeps control from its takeover to the end of the episode
            assert (source[:start] == 1).all() and (source[start:] == 2).all()
            assert line["feedback"][-1] in ("tp", "fn")
        assert line["length"] == len(ep)
    # lerobot's own declaration of the DAgger flag, kept as it is
    assert ds.meta.features["intervention"]["names"] is None
    assert (ds_root / "meta" / "failure_predictor.pt").is_file() and (ds_root / "meta" / "fire_roc.json").is_file()
    assert sum(line["episode_expert_samples"] for line in lines) == lines[-1]["corrections"]
    assert lines[-1]["env_steps"] == sum(len(ep) for ep in episodes[3:])
    assert main(["info", str(ds_root)]) == 0 and main(["validate", str(ds_root)]) == 0
    # the current policy is a BC run folder that `shiftkit eval` understands
    assert (run / "policy" / "config.json").is_file() and (run / "policy" / "checkpoints" / "last.txt").is_file()
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
    assert [t.get_text() for t in expert.get_legend().get_texts()] == [f"mine, {len(lines)} episodes (n = 1 run)"]
    assert expert.get_title().startswith("mine, ") and time.get_xlabel() == "total execution time (s)"
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


def test_plot_fire_draws_bc_at_its_training_frames(demo, fire_run, tmp_path, capsys):
    """`plot fire --bc`: BC is a point at its dataset's frames (and frames / fps on the time panel),
    at its evaluation's success with the Wilson interval; a label's runs pool their episodes."""
    import shutil

    from shiftkit.policies.curves import Point, draw_curves
    from shiftkit.policies.evaluation import EpisodeResult, EvalReport, record_evaluation, wilson_interval
    from shiftkit.policies.fire_runs import bc_reference

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
    from shiftkit.policies.dagger_recording import write_recording
    from shiftkit.policies.fire_predictor import FailurePredictor, FailurePredictorStep
    from shiftkit.policies.fire_recording import recorded_episodes

    _, _, demo_root = demo
    run, _ = fire_run
    continuous = open_lerobot_dataset(run / "rollouts")
    corrections = tmp_path / "rollout_corrections"  # record_autonomous=false: each correction one episode
    features = {k: v for k, v in continuous.features.items() if k != "intervention"}
    episodes = recorded_episodes(run / "episodes", continuous.fps, continuous.tasks[0])
    write_recording(
        corrections, "local/rollout_corrections", continuous.fps, features, episodes, record_autonomous=False
    )
    windows = open_lerobot_dataset(corrections)
    lines = _episode_lines(run)
    assert windows.num_episodes == sum(x["intervened_at"] is not None for x in lines)

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
    from shiftkit.policies.dagger_recording import write_recording
    from shiftkit.policies.fire_recording import recorded_episodes

    _, _, demo_root = demo
    run, _ = fire_run
    rec = open_lerobot_dataset(run / "rollouts")
    features = {k: v for k, v in rec.features.items() if k != "intervention"}
    other_fps = tmp_path / "rollout_fps"
    write_recording(
        other_fps, "local/rollout_fps", rec.fps * 2, features, recorded_episodes(run / "episodes", rec.fps * 2, "t")
    )
    only_corrections = tmp_path / "rollout_corr"
    write_recording(
        only_corrections,
        "local/rollout_corr",
        rec.fps,
        features,
        recorded_episodes(run / "episodes", rec.fps, "t"),
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
