"""`shiftkit demo` shows the multiview product: recorded + re-rendered views, validated, and a PNG."""

from __future__ import annotations

from shiftkit.app.demo import run_demo
from shiftkit.datasets.reader import open_lerobot_dataset


def test_demo_records_rerenders_validates_and_draws_the_views(tmp_path):
    result = run_demo(tmp_path / "demo", episodes=2, seed=0, overwrite=False, progress=False, views=1)
    assert result["episodes"] == 4  # two recorded episodes, each kept and re-rendered once
    figure = tmp_path / "demo" / "views.png"
    assert result["figure"] == str(figure) and figure.read_bytes()[:4] == b"\x89PNG"
    reader = open_lerobot_dataset(result["dataset"])
    recorded, rerendered = reader.iter_episodes([0, 1])
    assert recorded.meta["multiview"]["view"] == "source" and rerendered.meta["multiview"]["view"] == 0
    poses = [e.meta["cameras"]["base"]["base_pose"] for e in (recorded, rerendered)]
    assert poses[0] != poses[1]
    assert "sim.qpos" not in reader.features and "observation.depth.base" in reader.features


def test_views_figure_shows_depth_in_metres_with_a_colour_bar(tmp_path):
    import numpy as np

    from shiftkit.app.demo import DEPTH_SHOWN_M, views_figure

    result = run_demo(tmp_path / "demo", episodes=1, seed=0, overwrite=False, progress=False, views=1)
    fig = views_figure(result["dataset"], views=1)
    (bar,) = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert bar.get_ylabel() == "depth (m)" and tuple(bar.get_ylim()) == DEPTH_SHOWN_M
    recorded = next(open_lerobot_dataset(result["dataset"]).iter_episodes([0]))
    depth_image = fig.axes[2].get_images()[0]  # axes row by row (2 columns): row 2, column 1 is the recorded depth
    np.testing.assert_array_equal(depth_image.get_array(), recorded.frames["observation.depth.base"][0, ..., 0])
    assert depth_image.get_clim() == DEPTH_SHOWN_M
