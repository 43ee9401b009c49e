"""Merging sources that differ (fps, state names, an extra feature, camera size) with per-source
stages: the planner's one-line error, the merged dataset in lerobot, and each source's episodes
equal to its chain run alone."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from shiftkit.datasets.errors import DatasetError
from shiftkit.datasets.sources.raw import RawDatasetWriter
from shiftkit.pipelines.config import load_pipeline_config
from shiftkit.pipelines.planner import plan_pipeline
from tests.helpers import lerobot_train_two_steps, write_raw_as_lerobot

TELEOP_STAGES = """stages = [
  {name = "resample", params = {fps = 10}},
  {name = "select", params = {feature = "observation.state", names = ["x", "y", "z", "gripper"]}},
  {name = "drop", params = {features = ["observation.wrench"]}},
  {name = "resize", params = {width = 64, height = 48}},
]"""


def _record(out: Path, fps: int, state_names: list[str], size: tuple[int, int], wrench: bool, seed: int) -> Path:
    """Two episodes of a point robot at `fps` with a camera of `size` (h, w) and its intrinsics."""
    rng = np.random.default_rng(seed)
    names = {"state": state_names, "action": ["dx", "dy", "dz", "gripper"]}
    h, w = size
    cameras = {
        "front": {"intrinsics": {"fx": 50.0, "fy": 50.0, "cx": (w - 1) / 2, "cy": (h - 1) / 2, "width": w, "height": h}}
    }
    with RawDatasetWriter(out, fps=fps, robot="point", env="synthetic", names=names) as writer:
        for e in range(2):
            n = fps + 3 * e  # 1 s and a bit
            arrays = {
                "timestamp": np.arange(n, dtype=np.float64) / fps,
                "state": rng.normal(size=(n, len(state_names))).astype(np.float32),
                "action": rng.normal(size=(n, 4)).astype(np.float32),
            }
            if wrench:
                arrays["wrench_raw"] = rng.normal(size=(n, 4)).astype(np.float32)
            images = {"front": rng.integers(0, 255, size=(n, h, w, 3), dtype=np.uint8)}
            writer.add_episode(arrays, images=images, meta={"task": "reach", "cameras": cameras})
    return out


@pytest.fixture(scope="module")
def two_sources(tmp_path_factory):
    """A 10 fps kinesthetic set (state x, y, z, gripper; 48x64 camera) and a 30 fps teleop set
    (9-dim state, a wrench feature, 96x96 camera), both written by lerobot's writer."""
    tmp = tmp_path_factory.mktemp("merge")
    kin = _record(tmp / "kin_raw", 10, ["x", "y", "z", "gripper"], (48, 64), wrench=False, seed=1)
    teleop = _record(
        tmp / "teleop_raw", 30, ["x", "y", "z", "gripper", "j0", "j1", "j2", "j3", "j4"], (96, 96), wrench=True, seed=2
    )
    return (
        write_raw_as_lerobot(kin, "test/kin", tmp / "kin"),
        write_raw_as_lerobot(teleop, "test/teleop", tmp / "teleop"),
    )


def _pipeline(path: Path, sources: list[tuple[Path, str]], dest: Path, repo_id: str) -> Path:
    text = "".join(f'[[sources]]\npath = "{src}"\n{stages}\n\n' for src, stages in sources)
    path.write_text(text + f'[destination]\nroot = "{dest}"\nrepo_id = "{repo_id}"\n')
    return path


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "shiftkit.app.cli", *args], capture_output=True, text=True)


def _episodes(root: Path) -> list[dict[str, list]]:
    """Each episode's rows, without the columns that depend on its place in the dataset."""
    table = pq.read_table(sorted((root / "data").rglob("*.parquet"))).to_pydict()
    tasks = pq.read_table(root / "meta" / "tasks.parquet").to_pandas().index.tolist()
    out: dict[int, dict[str, list]] = {}
    for r, e in enumerate(table["episode_index"]):
        ep = out.setdefault(e, {})
        for key, col in table.items():
            if key not in ("index", "episode_index", "task_index"):
                ep.setdefault(key, []).append(col[r])
        ep.setdefault("task", []).append(tasks[table["task_index"][r]])
    return [out[e] for e in sorted(out)]


def test_plan_names_the_source_feature_difference_and_fix(two_sources, tmp_path):
    kin, teleop = two_sources
    config = _pipeline(tmp_path / "p.toml", [(kin, ""), (teleop, "")], tmp_path / "out", "test/m")
    with pytest.raises(DatasetError) as info:
        plan_pipeline(load_pipeline_config(config))
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("sources[1] (teleop) does not match sources[0] after its stages: has fps 30")
    assert 'add {name = "resample", params = {fps = 10}} to its stages' in message
    assert "(and 3 more differences)" in message
    # with the fps fixed, the next difference is named with its fix
    resample = 'stages = [{name = "resample", params = {fps = 10}}]'
    config = _pipeline(tmp_path / "p2.toml", [(kin, ""), (teleop, resample)], tmp_path / "out", "test/m")
    with pytest.raises(
        DatasetError, match=r"has feature 'observation.wrench' that sources\[0\] lacks; add \{name = \"drop\""
    ):
        plan_pipeline(load_pipeline_config(config))
    out = _cli("plan", str(config))
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1 and "Traceback" not in out.stderr


def test_merged_dataset_equals_each_chain_alone(two_sources, tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    kin, teleop = two_sources
    merged = tmp_path / "merged"
    config = _pipeline(tmp_path / "merge.toml", [(kin, ""), (teleop, TELEOP_STAGES)], merged, "test/merged")
    out = _cli("run", str(config), "--workers", "2", "--no-progress")
    assert out.returncode == 0, out.stderr[-2000:]

    ds = LeRobotDataset("test/merged", root=merged)
    assert ds.fps == 10 and ds.meta.total_episodes == 4
    assert tuple(ds.meta.features["observation.images.front"]["shape"]) == (48, 64, 3)
    assert ds.meta.features["observation.state"]["names"] == ["x", "y", "z", "gripper"]
    assert "observation.wrench" not in ds.meta.features
    # the kinesthetic episodes keep their 10 and 13 frames; 1 s and 1.1 s of teleop at 10 fps
    assert [int(n) for n in ds.meta.episodes["length"]] == [10, 13, 10, 11]

    provenance = json.loads((merged / "meta" / "shiftkit_provenance.json").read_text())
    sources = provenance["sources"]
    assert [s["episodes"] for s in sources] == [[0, 2], [2, 4]] and [s["fps"] for s in sources] == [10, 30]
    assert [st["name"] for st in sources[1]["stages"]] == ["resample", "select", "drop", "resize"]
    card = (merged / "README.md").read_text()
    assert "2 episode(s) in this dataset (episodes 2 to 3) at 30 fps" in card
    # the teleop camera's intrinsics are scaled from 96x96 to 64x48 (pixel centres kept)
    cameras = json.loads((merged / "meta" / "cameras.json").read_text())
    teleop_front = cameras["episodes"]["2"]["front"]["intrinsics"]
    assert teleop_front["width"] == 64 and teleop_front["height"] == 48
    assert teleop_front["cx"] == pytest.approx(31.5) and teleop_front["fy"] == pytest.approx(25.0)

    alone = []
    for name, (src, stages) in {"kin": (kin, ""), "teleop": (teleop, TELEOP_STAGES)}.items():
        dest = tmp_path / f"alone_{name}"
        out = _cli(
            "run", str(_pipeline(tmp_path / f"{name}.toml", [(src, stages)], dest, f"test/{name}")), "--no-progress"
        )
        assert out.returncode == 0, out.stderr[-2000:]
        alone += _episodes(dest)
    assert _episodes(merged) == alone

    info = _cli("info", str(merged))
    assert "output episodes 2..3 (2)" in info.stdout and "own stage: resize v3" in info.stdout
    lerobot_train_two_steps("test/merged", merged, tmp_path / "train")


def test_resize_matches_lerobot_image_resize():
    """The RGB resize is lerobot's `ImageCropResizeProcessorStep` (float in [0, 1]) rounded to uint8;
    depth takes the nearest pixel."""
    import torch
    from lerobot.processor import ImageCropResizeProcessorStep

    from shiftkit.transforms.resize import bilinear, nearest

    frames = np.random.default_rng(0).integers(0, 256, size=(2, 96, 96, 3), dtype=np.uint8)
    step = ImageCropResizeProcessorStep(resize_size=(48, 64))
    theirs = step.observation({"observation.images.front": torch.from_numpy(frames).permute(0, 3, 1, 2) / 255.0})
    expected = theirs["observation.images.front"].permute(0, 2, 3, 1).numpy() * 255.0
    ours = bilinear(frames, (48, 64))
    assert ours.shape == (2, 48, 64, 3) and np.abs(ours - expected).max() <= 0.5 + 1e-3
    depth = np.arange(16, dtype=np.float32).reshape(1, 4, 4, 1)
    assert nearest(depth, (2, 2))[0, :, :, 0].tolist() == [[5.0, 7.0], [13.0, 15.0]]


def test_merge_chooses_the_per_source_stages(two_sources, tmp_path):
    import tomllib

    kin, teleop = two_sources
    out = _cli(
        "merge", str(kin), str(teleop), "--fps", "10", "--out", str(tmp_path / "m"), "--repo-id", "test/m", "--dry-run"
    )
    assert out.returncode == 0, out.stderr[-2000:]
    pipeline = tomllib.loads(out.stdout)
    assert "stages" not in pipeline["sources"][0]
    assert pipeline["sources"][1]["stages"] == [
        {"name": "resample", "params": {"fps": 10}},
        {"name": "drop", "params": {"features": ["observation.wrench"]}},
        {"name": "select", "params": {"feature": "observation.state", "names": ["x", "y", "z", "gripper"]}},
        {"name": "resize", "params": {"width": 64, "height": 48, "features": ["observation.images.front"]}},
    ]
    assert not (tmp_path / "m").exists()
    bad = _cli(
        "merge",
        str(kin),
        str(teleop),
        "--fps",
        "10",
        "--out",
        str(tmp_path / "m"),
        "--repo-id",
        "test/m",
        "--size",
        "64",
    )
    assert bad.returncode == 2 and bad.stderr.strip().splitlines() == [
        "shiftkit merge: error: --size: expected WIDTHxHEIGHT, e.g. 64x48, got '64'"
    ]


def test_merge_takes_paths_outside_the_basic_multilingual_plane(tmp_path):
    """A source folder named with an emoji: `merge` builds its pipeline as config objects, so the
    path is not squeezed through JSON escapes (a surrogate pair TOML refused, a traceback); the
    printed pipeline is a valid file that `shiftkit run` reads back to the same pipeline."""
    import shutil
    import tomllib

    from shiftkit.pipelines.config import parse_pipeline_config
    from tests.lerobot_recordings import Recording, recording

    robot = shutil.copytree(recording(Recording(fps=10, language=False)), tmp_path / "🤖 demos")
    other = shutil.copytree(recording(Recording(fps=20, depth_unit="mm", language=False)), tmp_path / 'teleop "\\ 2')
    out = tmp_path / "merged 🦾"
    merged = _cli(
        "merge", str(robot), str(other), "--fps", "10", "--out", str(out), "--repo-id", "test/m", "--no-progress"
    )
    assert merged.returncode == 0, merged.stderr[-2000:]
    text = merged.stdout.rsplit("wrote ", 1)[0]
    pipeline = parse_pipeline_config(tomllib.loads(text), tmp_path, "printed")
    assert [s.path for s in pipeline.sources] == [str(robot), str(other)]
    assert pipeline.sources[1].stages[0].name == "resample" and pipeline.destination.root == str(out)
    assert json.loads((out / "meta" / "info.json").read_text())["total_episodes"] == 4


def test_pipeline_toml_reads_back_to_the_same_config():
    import tomllib

    from shiftkit.pipelines.config import (
        DestinationConfig,
        PipelineConfig,
        PipelineSource,
        StageSpec,
        parse_pipeline_config,
        pipeline_toml,
    )

    odd = 'a "quoted" \\ back\tslash\n😀 \x01 end'
    config = PipelineConfig(
        sources=[
            PipelineSource(path=f"/data/{odd}", stages=[StageSpec("map_tasks", {"mapping": {odd: "t"}}, version=1)]),
            PipelineSource(repo_id="lab/x", revision="v1"),
        ],
        destination=DestinationConfig(root="/out/🦾", repo_id="lab/y", video=False),
        stages=[StageSpec("filter", {"keep_fraction": 0.5, "tasks": [odd], "min_length": 2})],
        seed=3,
    )
    assert parse_pipeline_config(tomllib.loads(pipeline_toml(config)), Path("/"), "toml") == config
