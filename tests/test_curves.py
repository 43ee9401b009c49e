"""Success-curve figures (`shiftkit plot curves`, `plot fire`): the title names the methods and tasks,
every legend entry its n."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from shiftkit.policies.curves import Point, aggregate, draw_curves


def _run(path: Path, task: str, successes: list[float]) -> Path:
    path.mkdir(parents=True)
    (path / "config.json").write_text(json.dumps({"trainer": "vpace", "args": {"main_task": task}}))
    lines = [{"step": 100 * (i + 1), "split": "eval", "success_rate": s} for i, s in enumerate(successes)]
    (path / "metrics.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))
    return path


def test_curves_figure_names_methods_tasks_and_n(tmp_path):
    runs = [_run(tmp_path / f"s{i}", "lift", [0.1 * i, 0.2 * i]) for i in range(3)]
    curve = aggregate("vpace", runs, reps=50)
    assert curve.runs == 3 and curve.tasks == ("lift",)
    point = Point("BC", 150.0, 0.5, 0.2, 0.8, 10)
    ax = draw_curves([curve], points=(point,)).axes[0]
    assert ax.get_title() == "vpace vs BC on lift: success rate (IQM, 95% CI)"
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert legend == ["vpace (n = 3 runs)", "BC (n = 10 episodes)"]
    (line,) = ax.lines[:1]
    assert list(line.get_xdata()) == [100, 200] and np.allclose(line.get_ydata(), curve.iqm)
    (bar,) = ax.containers
    assert bar.lines[0].get_xdata()[0] == 150.0 and bar.lines[0].get_ydata()[0] == pytest.approx(0.5)
