"""Dataset cards cite the method that made the dataset, from the citation its stages record in the provenance."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from shiftkit.cards.render import render_dataset_card
from shiftkit.pipelines.stage import STAGES, StageContext, build_stage


def _root(tmp_path: Path) -> Path:
    (tmp_path / "meta").mkdir()
    info = {"total_episodes": 1, "total_frames": 2, "fps": 10, "total_tasks": 1, "features": {}}
    (tmp_path / "meta" / "info.json").write_text(json.dumps(info))
    return tmp_path


@pytest.mark.parametrize(
    ("stage", "title"),
    [
        ("force_match", "force-matched imitation learning"),
        ("mode_label", "force-matched imitation learning"),
        ("replay_join", "force-matched imitation learning"),
        ("multiview", "Seeing all the angles"),
        ("success_examples", "value-penalized auxiliary control"),
    ],
)
def test_a_dataset_card_cites_the_method_of_its_stages(tmp_path, stage, title):
    # the stage's entry as the runner records it in the provenance
    entry = build_stage(stage, STAGES.get(stage).example_params, StageContext(fps=10), stage).describe()
    root = _root(tmp_path)
    assert title in render_dataset_card(root, {"stages": [entry], "sources": []})
    own = {"stages": [], "sources": [{"path": "raw", "stages": [entry]}]}
    assert title in render_dataset_card(root, own), "a source's own stage is cited too"


def test_a_card_cites_each_paper_once(tmp_path):
    stages = dict(STAGES.items())
    entries = [
        build_stage(n, stages[n].example_params, StageContext(fps=10), n).describe()
        for n in ("mode_label", "resample", "mode_label")
    ]
    card = render_dataset_card(_root(tmp_path), {"stages": entries, "sources": []})
    assert card.count("force-matched imitation learning") == 1


def test_a_fire_dataset_card_cites_fire(tmp_path):
    card = render_dataset_card(_root(tmp_path), {"stages": [], "sources": [], "fire": {"predictor": "gda"}})
    assert "Failure identification to reduce expert burden" in card
