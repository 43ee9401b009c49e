"""Evaluation in the multiview envs: env kwargs (view) and the base-yaw sweep (JSON + PNG)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from shiftkit.datasets.errors import ConfigError
from shiftkit.envs import env_family
from shiftkit.envs.multiview.experts import ExpertPolicy
from shiftkit.policies.evaluation import YAW_BINS, draw_yaw_sweep, write_yaw_sweep, yaw_sweep


class ExpertWithFeatures(ExpertPolicy):
    """The scripted expert (of the env the sweep builds), recording the base yaw of each episode."""

    features = {
        "observation.state": {"shape": [13], "names": list(env_family("mv-lift").observation_names[:13])},
    }
    envs: list = []

    def __init__(self) -> None:
        self.yaws: list[float] = []

    def reset(self) -> None:
        env = ExpertWithFeatures.envs[-1]
        super().__init__(env)
        self.yaws.append(env.base_pose.yaw)


def test_yaw_bins_are_the_spec_sweep():
    assert len(YAW_BINS) == 12 and YAW_BINS[0] == (-0.8, -0.7) and YAW_BINS[-1] == (0.3, 0.4)


def test_yaw_sweep_runs_each_bin_at_its_yaws_and_writes_json_and_png(tmp_path, monkeypatch):
    import shiftkit.policies.evaluation as evaluation

    real_make = evaluation._make_env

    def make_and_remember(*args, **kwargs):
        env = real_make(*args, **kwargs)
        ExpertWithFeatures.envs.append(env)
        return env

    monkeypatch.setattr(evaluation, "_make_env", make_and_remember)
    policy = ExpertWithFeatures()
    bins = ((-0.8, -0.7), (0.3, 0.4))
    sweep = yaw_sweep(policy, "mv-lift", "lift", 2, seed=5, bins=bins, env_kwargs={"view": "fixed"})
    assert [r["yaw"] for r in sweep["bins"]] == [[-0.8, -0.7], [0.3, 0.4]]
    assert all(r["success_rate"] == 1.0 for r in sweep["bins"])  # the expert works out of distribution too
    yaws = np.array(policy.yaws)
    assert np.all((yaws[:2] >= -0.8) & (yaws[:2] <= -0.7)) and np.all((yaws[2:] >= 0.3) & (yaws[2:] <= 0.4))
    json_path, png = write_yaw_sweep(sweep, tmp_path / "sweep.json")
    assert json.loads(json_path.read_text())["bins"][1]["successes"] == 2
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_yaw_sweep_figure_marks_the_training_yaws():
    bins = [{"yaw": [-0.8, -0.7], "episodes": 4, "successes": 1, "success_rate": 0.25, "ci95": [0.05, 0.7]}]
    sweep = {"env": "mv-lift", "task": "lift", "policy": "runs/bc", "seed": 0, "bins": bins}
    fixed = draw_yaw_sweep({**sweep, "training_yaw": {"episodes": 5, "low": -0.2, "high": -0.2}}).axes[0]
    assert fixed.get_title().startswith("fixed-view policy bc on mv-lift / lift") and "n = 4" in fixed.get_title()
    line = fixed.lines[0]  # drawn first, under the bars
    assert list(line.get_xdata()) == [-0.2, -0.2]
    assert fixed.get_legend().get_texts()[0].get_text() == "trained at yaw -0.2 only (5 episodes)"
    multi = draw_yaw_sweep({**sweep, "training_yaw": {"episodes": 9, "low": -0.6, "high": 0.2}}).axes[0]
    assert multi.get_title().startswith("multiview policy bc")
    band = multi.patches[0]  # drawn first, under the bars
    assert band.get_x() == pytest.approx(-0.6) and band.get_width() == pytest.approx(0.8)
    unknown = draw_yaw_sweep({**sweep, "training_yaw": None}).axes[0]
    assert "training yaws not recorded" in unknown.get_legend().get_texts()[0].get_text()


def test_yaw_sweep_needs_a_mobile_base():
    policy = ExpertWithFeatures()
    with pytest.raises(ConfigError, match="mobile base"):
        yaw_sweep(policy, "panda-play", "lift", 1, seed=0, bins=((0.0, 0.1),))


def test_eval_cli_env_kwarg_and_yaw_sweep(tmp_path, capsys):
    from shiftkit.app.cli import main
    from shiftkit.app.collect import CollectConfig, collect

    collect(CollectConfig(env="mv-lift", task="lift", episodes=2, lerobot="local/mv2", root=str(tmp_path / "mv2")))
    run = tmp_path / "run"
    args = ["train", "bc", "--dataset", str(tmp_path / "mv2"), "--output", str(run), "--regime", "fixed"]
    args += ["--steps", "5", "--ensemble", "1", "--hidden", "16", "--checkpoint-every", "5", "--threads", "1"]
    assert main(args) == 0
    base = ["eval", "--policy", str(run), "--env", "mv-lift", "--task", "lift", "--episodes", "1"]
    assert main([*base, "--env-kwarg", "view=fixed"]) == 0
    assert main([*base, "--env-kwarg", "view=multiview", "--yaw-sweep", "--out", str(tmp_path / "s.json")]) == 0
    sweep = json.loads((tmp_path / "s.json").read_text())
    assert len(sweep["bins"]) == 12 and (tmp_path / "s.png").exists()
    # the figure marks the base yaws of the training episodes (from the dataset's camera metadata)
    trained = sweep["training_yaw"]
    assert trained["episodes"] == 2 and -0.7 <= trained["low"] <= trained["high"] <= 0.3
    ax = draw_yaw_sweep(sweep).axes[0]
    assert ax.get_title().startswith(f"{'fixed-view' if trained['low'] == trained['high'] else 'multiview'} policy run")
    assert "(2 episodes)" in ax.get_legend().get_texts()[0].get_text() and "n = 1 episodes per bin" in ax.get_title()
    assert main([*base, "--env-kwarg", "view=sideways"]) == 2
    assert "yaw sweep written" in capsys.readouterr().out
