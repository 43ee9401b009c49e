"""The demo pipeline on embedded defaults: record episodes, run a multiview pipeline, validate it.

It records scripted-expert lift episodes from one fixed base pose in the multiview simulator
(`mv-lift`: a Panda on a mobile base with a base-mounted 64x48 RGB-D camera, with simulator state)
with `shiftkit collect`, runs a pipeline config (written next to the outputs so it can be edited
and re-run) that keeps successful episodes, trims them, re-renders each from two new sampled base
poses with the `multiview` stage (keeping the recorded view too) and drops the simulator state,
validates the LeRobot dataset it made, and writes `views.png`: the first frame of one episode as
recorded and as re-rendered from the new base poses, RGB over depth (with a colour bar in metres).
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from shiftkit.datasets.errors import ShiftkitError

MARKER = ".shiftkit-demo"
ENV, TASK, CAMERA = "mv-lift", "lift", "base"

PIPELINE = """\
# shiftkit demo pipeline: `shiftkit plan` / `shiftkit run` this file.
seed = 0

[[sources]]
path = "raw"

[[stages]]
name = "filter"
params = {{ outcomes = ["success"] }}

[[stages]]
name = "trim"
params = {{ head = 1 }}

[[stages]]
name = "multiview"
params = {{ num_views = {views}, keep_source = true }}

[[stages]]
name = "drop"
params = {{ features = ["sim.qpos", "sim.qvel"] }}

[destination]
root = "dataset"
repo_id = "shiftkit/demo"
"""


def run_demo(out: Path, episodes: int, seed: int, overwrite: bool, progress: bool = True, views: int = 2) -> dict:
    """Record mv-lift episodes into `out`, run the demo pipeline over them and draw the views figure; return the paths
    written, the dataset's counts and its summary."""
    from shiftkit.datasets.check import summarize, validate_dataset
    from shiftkit.pipelines.config import load_pipeline_config
    from shiftkit.pipelines.runner import run_pipeline

    if out.exists():
        if not overwrite or not (out / MARKER).exists():
            raise ShiftkitError(f"{out} exists; pass --overwrite (only replaces an earlier demo output)")
        shutil.rmtree(out)
    out.mkdir(parents=True)
    (out / MARKER).write_text("made by shiftkit demo\n")
    record(out / "raw", episodes, seed)
    config_path = out / "pipeline.toml"
    config_path.write_text(PIPELINE.format(views=views))
    dataset = run_pipeline(load_pipeline_config(config_path), workers=1, progress=progress)
    counts = validate_dataset(dataset)
    figure = write_views_figure(dataset, out / "views.png", views)
    return {
        "dataset": str(dataset),
        "config": str(config_path),
        "figure": str(figure),
        **counts,
        "summary": summarize(dataset),
    }


def record(raw_dir: Path, episodes: int, seed: int) -> None:
    """Write the demo's raw episodes: fixed-view mv-lift, RGB-D of the base camera, simulator state."""
    from shiftkit.app.collect import CollectConfig, collect

    collect(
        CollectConfig(
            env=ENV,
            task=TASK,
            episodes=episodes,
            seed=seed,
            out=str(raw_dir),
            cameras=(CAMERA,),
            depth=True,
            env_kwargs={"view": "fixed"},
        )
    )


DEPTH_SHOWN_M = (0.3, 1.5)  # the depth range the figure's colours span (the table and the arm)


def views_figure(dataset: Path, views: int) -> Any:
    """The first frame (RGB over depth) of the dataset's first source episode as recorded and as
    re-rendered from each new base pose (the multiview stage writes them in that order); depth in
    metres with a colour bar (nearer and farther values show as the bar's end colours)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from shiftkit.datasets.reader import open_lerobot_dataset

    reader = open_lerobot_dataset(dataset)
    episodes = list(reader.iter_episodes(list(range(min(views + 1, reader.num_episodes)))))
    fig, axes = plt.subplots(
        2, len(episodes), figsize=(2.6 * len(episodes) + 0.9, 4.0), squeeze=False, layout="constrained"
    )
    for k, episode in enumerate(episodes):
        pose = episode.meta["cameras"][CAMERA]["base_pose"]
        title = "recorded" if k == 0 else f"re-rendered {k}"
        axes[0, k].imshow(episode.frames[f"observation.images.{CAMERA}"][0], interpolation="nearest")
        axes[0, k].set_title(f"{title}\nbase yaw {pose['yaw']:+.2f} rad", fontsize=8)
        depth = episode.frames[f"observation.depth.{CAMERA}"][0, ..., 0]  # metres
        shown = axes[1, k].imshow(depth, cmap="viridis_r", vmin=DEPTH_SHOWN_M[0], vmax=DEPTH_SHOWN_M[1])
        for ax in axes[:, k]:
            ax.set_axis_off()
    bar = fig.colorbar(shown, ax=list(axes[1, :]), extend="both", shrink=0.9, pad=0.02)
    bar.set_label("depth (m)", fontsize=8)
    bar.ax.tick_params(labelsize=7)
    return fig


def write_views_figure(dataset: Path, path: Path, views: int) -> Path:
    """`views_figure` as a PNG at `path`."""
    import matplotlib.pyplot as plt

    fig = views_figure(dataset, views)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
