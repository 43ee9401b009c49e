"""Policy evaluation: Wilson interval, observation mapping, rollouts with results and videos, CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from shiftkit.datasets.errors import ConfigError, DatasetError
from shiftkit.envs.panda_play.experts import ExpertPolicy
from shiftkit.policies.evaluation import EvalReport, ObservationMap, load_policy, run_episodes, wilson_interval


def test_wilson_interval_known_values():
    assert wilson_interval(0, 10) == pytest.approx((0.0, 0.2775), abs=1e-4)
    assert wilson_interval(5, 10) == pytest.approx((0.2366, 0.7634), abs=1e-4)
    assert wilson_interval(45, 50) == pytest.approx((0.7864, 0.9565), abs=1e-4)
    assert wilson_interval(0, 0) == (0.0, 1.0)


def test_observation_map_picks_dims_by_name():
    names = ["ee_x", "ee_y", "blue_x", "blue_y", "grip"]
    features = {
        "observation.state": {"dtype": "float32", "shape": [3], "names": ["ee_x", "ee_y", "grip"]},
        "observation.environment_state": {"dtype": "float32", "shape": [2], "names": ["blue_y", "blue_x"]},
    }
    out = ObservationMap(features, names)(None, np.arange(5, dtype=np.float32))
    np.testing.assert_array_equal(out["observation.state"], [0, 1, 4])
    np.testing.assert_array_equal(out["observation.environment_state"], [3, 2])
    with pytest.raises(ConfigError, match="'force_z'"):
        ObservationMap({"observation.state": {"shape": [1], "names": ["force_z"]}}, names)


class RecordingExpert(ExpertPolicy):
    """The scripted expert asking for the split state features, recording what it is given."""

    def __init__(self, env) -> None:
        from shiftkit.envs.panda_play.physics import ENVIRONMENT_STATE_INDICES, OBSERVATION_NAMES, STATE_INDICES

        super().__init__(env)
        self.features = {
            key: {"shape": [len(idx)], "names": [OBSERVATION_NAMES[i] for i in idx]}
            for key, idx in (
                ("observation.state", STATE_INDICES),
                ("observation.environment_state", ENVIRONMENT_STATE_INDICES),
            )
        }
        self.seen: list[dict] = []

    def act(self, obs):
        self.seen.append(obs)
        return super().act(obs)


def test_run_episodes_with_results_and_videos(tmp_path):
    import av

    from shiftkit.envs import make

    env = make("panda-play", "lift")
    policy = RecordingExpert(env)
    results = run_episodes(policy, env, episodes=2, seed=100, video_dir=tmp_path / "videos")
    assert [e.seed for e in results] == [100, 101]
    # an episode stops at its first success, else at the env's time limit
    assert all(e.success or e.steps == env.max_episode_steps for e in results)
    first = policy.seen[0]
    assert first["observation.state"].shape == (18,) and first["observation.environment_state"].shape == (41,)
    report = EvalReport(env="panda-play", task="lift", policy="expert", seed=100, episodes=results)
    summary = json.loads(report.to_json())
    wins = sum(e.success for e in results)
    assert summary["success_rate"] == wins / 2 and summary["ci95"] == pytest.approx(list(wilson_interval(wins, 2)))
    assert len(summary["results"]) == 2
    with av.open(results[0].video) as container:
        frames = sum(1 for _ in container.decode(video=0))
    assert frames == results[0].steps + 1


def test_eval_cli_runs_a_trained_bc_policy(tmp_path, capsys):
    from shiftkit.app.cli import main
    from shiftkit.app.collect import CollectConfig, collect

    collect(CollectConfig(task="lift", episodes=3, seed=0, lerobot="local/lift3", root=str(tmp_path / "lift3")))
    run = tmp_path / "run"
    assert (
        main(
            [
                "train",
                "bc",
                "--dataset",
                str(tmp_path / "lift3"),
                "--output",
                str(run),
                "--regime",
                "fixed",
                "--steps",
                "40",
                "--ensemble",
                "2",
                "--hidden",
                "32,32",
                "--checkpoint-every",
                "40",
                "--threads",
                "1",
            ]
        )
        == 0
    )
    assert main(["eval", "--policy", str(run), "--task", "lift", "--episodes", "1", "--seed", "500"]) == 0
    printed = capsys.readouterr().out
    assert "success rate" in printed and "95% CI" in printed
    result = json.loads((run / "eval" / "panda-play-lift-seed500.json").read_text())
    assert result["episodes"] == 1 and result["results"][0]["seed"] == 500
    assert result["results"][0]["steps"] > 0
    card = (run / "README.md").read_text()
    assert "success panda-play/lift (1 episodes from seed 500)" in card and "panda-play / lift" in card
    # A checkpoint file's result is kept beside the run's, named for the checkpoint.
    checkpoint = run / "checkpoints" / (run / "checkpoints" / "last.txt").read_text().strip()
    assert main(["eval", "--policy", str(checkpoint), "--task", "lift", "--episodes", "1", "--seed", "500"]) == 0
    assert json.loads((run / "eval" / f"panda-play-lift-seed500-{checkpoint.stem}.json").read_text())["episodes"] == 1
    card = (run / "README.md").read_text()
    assert f"success panda-play/lift ({checkpoint.name}, 1 episodes from seed 500)" in card
    assert "success panda-play/lift (1 episodes from seed 500)" in card

    assert main(["eval", "--policy", str(tmp_path / "missing"), "--task", "lift"]) == 2
    assert main(["eval", "--policy", str(run), "--task", "fly"]) == 2


def test_load_policy_errors(tmp_path):
    with pytest.raises(DatasetError, match="not found"):
        load_policy(tmp_path / "missing")
    (tmp_path / "plain").mkdir()
    with pytest.raises(DatasetError, match="not a shiftkit run"):
        load_policy(tmp_path / "plain")
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "config.json").write_text("{bad")
    with pytest.raises(DatasetError, match="invalid JSON"):
        load_policy(tmp_path / "broken")
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "config.json").write_text(json.dumps({"trainer": "bc", "args": {}}))
    (run / "checkpoints" / "step-00000001.pt").write_text("not a checkpoint")
    with pytest.raises(DatasetError, match="not a readable checkpoint"):
        load_policy(run / "checkpoints" / "step-00000001.pt")
    with pytest.raises(ConfigError, match="unknown device 'gpu0'"):
        load_policy(run, device="gpu0")


class ConstantDoorPolicy:
    """A policy that holds still and asks for one STS mode (the Policy protocol, no training)."""

    def __init__(self, sts_mode: float | None, names: bool = True) -> None:
        from shiftkit.envs.door_tactile.env import ACTION_NAMES, OBSERVATION_NAMES

        self.features = {"observation.state": {"shape": [19], "names": list(OBSERVATION_NAMES[:19])}}
        self.action = np.zeros(6 if sts_mode is None else 7, np.float32)
        if sts_mode is not None:
            self.action[6] = sts_mode
        if names:
            self.action_names = list(ACTION_NAMES[: len(self.action)])

    def act(self, obs):
        return self.action


@pytest.mark.parametrize(("sts_mode", "tactile_steps", "first"), [(1.0, 5, 0), (0.0, 0, None)])
def test_policy_driven_sts_mode_is_in_the_episode_results(sts_mode, tactile_steps, first):
    from shiftkit.envs import make

    env = make("door-tactile", "flat-handle-open", max_episode_seconds=0.5)
    results = run_episodes(ConstantDoorPolicy(sts_mode), env, episodes=1, seed=0)
    assert results[0].steps == 5
    extras = {
        "sensor_mode": "policy",
        "tactile_steps": tactile_steps,
        "first_tactile_step": first,
        "first_contact_step": None,
    }
    assert results[0].extras == extras
    report = EvalReport(env="door-tactile", task="flat-handle-open", policy="constant", seed=0, episodes=results)
    assert json.loads(report.to_json())["results"][0]["extras"] == extras
    env.close()


def test_policy_action_must_be_the_envs():
    """Named dims are matched by name, unnamed ones by count: a one-line ConfigError either way."""
    from shiftkit.envs import make

    env = make("door-tactile", "flat-handle-open", sensor_mode="visual", max_episode_seconds=0.3)
    with pytest.raises(ConfigError, match=r"'drz', 'sts_mode'\] is not the env's action \[.*'drz'\]") as info:
        run_episodes(ConstantDoorPolicy(1.0), env, episodes=1, seed=0)
    assert "\n" not in str(info.value)
    with pytest.raises(ConfigError, match=r"outputs \(7,\) actions, the env takes \(6,\)"):
        run_episodes(ConstantDoorPolicy(1.0, names=False), env, episodes=1, seed=0)
    # with a fixed mode, a policy without the mode dim drives the env, which never switches
    assert run_episodes(ConstantDoorPolicy(None), env, episodes=1, seed=0)[0].extras == {
        "sensor_mode": "visual",
        "tactile_steps": 0,
        "first_tactile_step": None,
        "first_contact_step": None,
    }
    env.close()


def test_eval_cli_fixed_mode_baseline_from_a_mode_label_dataset(tmp_path, capsys):
    """A BC policy trained on a `mode_label` source="visual" dataset (6-dim action) evaluates with
    `--env-kwarg sensor_mode=visual`; on the mode-switching env (7 dims) it is a one-line error."""
    from shiftkit.app.cli import main
    from shiftkit.datasets.sources import SourceConfig
    from shiftkit.datasets.sources.raw import RawDatasetWriter
    from shiftkit.envs.door_tactile.env import ACTION_NAMES, OBSERVATION_NAMES
    from shiftkit.pipelines.config import DestinationConfig, PipelineConfig, StageSpec
    from shiftkit.pipelines.runner import run_pipeline

    rng = np.random.default_rng(0)
    names = {"state": list(OBSERVATION_NAMES[:19]), "action": list(ACTION_NAMES)}
    with RawDatasetWriter(tmp_path / "raw", fps=10, robot="franka_panda", env="door-tactile", names=names) as w:
        for _ in range(2):
            w.add_episode(
                arrays={
                    "timestamp": np.arange(12) / 10.0,
                    "state": rng.normal(0, 0.1, (12, 19)).astype(np.float32),
                    "action": rng.uniform(-0.5, 0.5, (12, 7)).astype(np.float32),
                },
                meta={"task": "flat-handle-open"},
            )
    config = PipelineConfig(
        sources=[SourceConfig(path=str(tmp_path / "raw"))],
        destination=DestinationConfig(root=str(tmp_path / "visual")),
        stages=[StageSpec(name="mode_label", params={"source": "visual"})],
    )
    run_pipeline(config, progress=False)
    run = tmp_path / "run"
    train = ["train", "bc", "--dataset", str(tmp_path / "visual"), "--output", str(run), "--regime", "fixed"]
    assert main([*train, "--steps", "10", "--hidden", "16", "--checkpoint-every", "10", "--threads", "1"]) == 0
    capsys.readouterr()
    short = ["--env-kwarg", "max_episode_seconds=0.3", "--episodes", "1", "--seed", "7"]
    evaluate = ["eval", "--policy", str(run), "--env", "door-tactile", "--task", "flat-handle-open", *short]
    assert main(evaluate) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "'drz'] is not the env's action [" in err and "'sts_mode']" in err
    assert main([*evaluate, "--env-kwarg", "sensor_mode=visual"]) == 0
    assert "tactile_steps 0" in capsys.readouterr().out
    result = json.loads((run / "eval" / "door-tactile-flat-handle-open-seed7.json").read_text())
    assert result["results"][0]["steps"] == 3
    assert result["results"][0]["extras"] == {
        "sensor_mode": "visual",
        "tactile_steps": 0,
        "first_tactile_step": None,
        "first_contact_step": None,
    }
