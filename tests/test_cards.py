"""Dataset cards cite the method that made the dataset, looked up by its registered name."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from shiftkit.cards.render import render_dataset_card
from shiftkit.pipelines.stage import registered_stages


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
    assert stage in registered_stages()  # the card's key is the name the stage registers under
    provenance = {"stages": [{"name": stage, "version": 1, "params": {}}], "sources": []}
    assert title in render_dataset_card(_root(tmp_path), provenance)


def test_a_fire_dataset_card_cites_fire(tmp_path):
    card = render_dataset_card(_root(tmp_path), {"stages": [], "sources": [], "fire": {"predictor": "gda"}})
    assert "Failure identification to reduce expert burden" in card
