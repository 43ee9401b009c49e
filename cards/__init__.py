"""shiftkit.cards: dataset and model cards rendered from provenance data only."""

from shiftkit.cards.render import render_dataset_card, render_model_card

__all__ = ["render_dataset_card", "render_model_card"]
