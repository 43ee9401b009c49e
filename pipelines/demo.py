"""The demo pipeline on embedded defaults: record episodes, run a pipeline, validate the result.

It records scripted-expert lift episodes (state + a 64x48 camera, with simulator state) in the
Panda play simulator with `shiftkit collect`, runs a pipeline config (written next to the
outputs so it can be edited and re-run) that keeps successful episodes, trims them and drops the
simulator state, and validates the LeRobot dataset it made.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from shiftkit.pipelines.errors import ShiftkitError

MARKER = ".shiftkit-demo"

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
name = "drop"
params = {{ features = {drop} }}

[destination]
root = "dataset"
repo_id = "shiftkit/demo"
"""


def run_demo(out: Path, episodes: int, seed: int, overwrite: bool, progress: bool = True) -> dict:
    from shiftkit.pipelines.config import load_pipeline_config
    from shiftkit.pipelines.dataset_check import summarize, validate_dataset
    from shiftkit.pipelines.runner import run_pipeline

    if out.exists():
        if not overwrite or not (out / MARKER).exists():
            raise ShiftkitError(f"{out} exists; pass --overwrite (only replaces an earlier demo output)")
        shutil.rmtree(out)
    out.mkdir(parents=True)
    (out / MARKER).write_text("made by shiftkit demo\n")
    drop = record(out / "raw", episodes, seed)
    config_path = out / "pipeline.toml"
    config_path.write_text(PIPELINE.format(drop=drop))
    dataset = run_pipeline(load_pipeline_config(config_path), workers=1, progress=progress)
    counts = validate_dataset(dataset)
    return {"dataset": str(dataset), "config": str(config_path), **counts, "summary": summarize(dataset)}


def record(raw_dir: Path, episodes: int, seed: int) -> str:
    """Write the demo's raw episodes; returns the TOML list of features the pipeline drops."""
    from shiftkit.pipelines.sources.simulator import CollectConfig, collect

    collect(
        CollectConfig(env="panda-play", task="lift", episodes=episodes, seed=seed, out=str(raw_dir), cameras=("front",))
    )
    return '["sim.qpos", "sim.qvel"]'
