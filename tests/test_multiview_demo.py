"""`shiftkit demo` shows the multiview product: recorded + re-rendered views, validated, and a PNG."""

from __future__ import annotations

from shiftkit.app.demo import run_demo
from shiftkit.pipelines.lerobot_io import open_lerobot_dataset


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
