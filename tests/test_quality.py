"""The quality verdict (`datasets/quality.py`, `shiftkit validate --quality`): datasets written by
lerobot's own writer, a good one with no finding and bad ones whose every planted problem is found
in the episode and dimension it was planted in; the verdict in the provenance and the card of what
`shiftkit run` writes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from shiftkit.app.cli import main

FPS = 10
STATE_NAMES = ["x", "y", "z"]
ACTION_NAMES = ["dx", "dy"]


def smooth_episode(length: int, phase: float) -> dict[str, np.ndarray]:
    t = np.arange(length) / FPS
    state = np.stack([np.sin(t + phase), np.cos(0.7 * t + phase), 0.1 * t + phase], axis=1).astype(np.float32)
    action = np.stack([np.cos(t + phase), -0.7 * np.sin(0.7 * t + phase)], axis=1).astype(np.float32)
    success = np.zeros((length, 1), dtype=bool)
    success[-3:] = True
    return {"observation.state": state, "action": action, "next.success": success, "task": ["reach"] * length}


def write_lerobot(root: Path, episodes: list[dict[str, np.ndarray]]) -> Path:
    """A dataset written frame by frame by lerobot's own writer, the way a recorder writes one."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {
        "observation.state": {"dtype": "float32", "shape": (3,), "names": STATE_NAMES},
        "action": {"dtype": "float32", "shape": (2,), "names": ACTION_NAMES},
        "next.success": {"dtype": "bool", "shape": (1,), "names": None},
    }
    ds = LeRobotDataset.create(
        "test/quality", FPS, features=features, root=root, use_videos=False, video_backend="pyav"
    )
    for ep in episodes:
        for i in range(len(ep["action"])):
            ds.add_frame({k: (v[i] if k != "task" else v[i]) for k, v in ep.items()})
        ds.save_episode()
    ds.finalize()
    return root


def shift_timestamps(root: Path, episode: int, after: int, by: float) -> None:
    """Rewrite the data file with `by` seconds added to the timestamps of `episode` from frame `after`
    on: a recorder that dropped frames and wrote its clock (lerobot's writer computes them)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    (path,) = sorted((root / "data").glob("*/*.parquet"))
    table = pq.read_table(path)
    ts = table.column("timestamp").to_numpy().copy()
    rows = (table.column("episode_index").to_numpy() == episode) & (table.column("frame_index").to_numpy() >= after)
    ts[rows] += np.float32(by)
    table = table.set_column(table.schema.get_field_index("timestamp"), "timestamp", pa.array(ts, pa.float32()))
    pq.write_table(table, path)


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> Path:
    return write_lerobot(tmp_path_factory.mktemp("q") / "good", [smooth_episode(40, 0.3 * k) for k in range(6)])


@pytest.fixture(scope="module")
def bad(tmp_path_factory) -> Path:
    """One problem per episode (and a constant dimension and no success in all of them)."""
    episodes = [smooth_episode(40, 0.3 * k) for k in range(8)]
    episodes[0] = smooth_episode(10, 0.0)  # shorter than the default action chunk (16)
    episodes[3] = {k: v.copy() if k != "task" else list(v) for k, v in episodes[2].items()}  # a duplicate
    episodes[4]["observation.state"][:] = episodes[4]["observation.state"][0]  # the robot never moves
    episodes[5]["action"][::2] += 1.5  # jerky: every other action jumps
    episodes[6]["task"] = ["reach"] * 20 + ["lift"] + ["reach"] * 19  # one frame of another task
    for ep in episodes:
        ep["observation.state"][:, 2] = 0.25  # a constant dimension: z
        ep["next.success"][:] = False  # nothing ever succeeds
    root = write_lerobot(tmp_path_factory.mktemp("q") / "bad", episodes)
    shift_timestamps(root, episode=1, after=20, by=0.5)  # 5 frames missing after frame 19
    return root


def test_good_dataset_has_no_finding(good):
    from shiftkit.datasets.quality import quality_verdict

    verdict = quality_verdict(good)
    assert verdict["verdict"] == "ok", verdict["findings"]
    assert verdict["findings"] == [] and verdict["episodes"] == 6 and verdict["frames"] == 240


def test_every_planted_problem_is_found_where_it_was_planted(bad):
    from shiftkit.datasets.quality import quality_verdict

    verdict = quality_verdict(bad)
    assert verdict["verdict"] == "warn"
    by_check: dict[str, list[str]] = {}
    for f in verdict["findings"]:
        by_check.setdefault(f["check"], []).append(f["message"])
    assert by_check["constant_dims"] == ["observation.state: 1 of 3 dims constant over the whole dataset: z = 0.25"], (
        by_check
    )
    (gap,) = by_check["Temporal Consistency"][:1]
    assert gap.startswith("Episode 1: 1 dropped frame gap(s) at frame indices [19]"), by_check
    assert by_check["duplicate_episodes"] == ["episodes with identical numeric data: 2 = 3"]
    assert by_check["still_episodes"][0].endswith("in episode 4")
    assert by_check["jerky_episodes"][0].endswith("in episode 5")
    assert by_check["segments"] == ["task label holds for a single frame between two others in episode 6"]
    assert by_check["flags"] == ["next.success is never set (no episode succeeds)"]
    assert by_check["episode_length"][0].startswith("1 of 8 episodes are shorter than the action chunk of 16")
    assert by_check["episode_length"][0].endswith(": episode 0")
    assert set(by_check) == {
        "constant_dims",
        "Temporal Consistency",
        "duplicate_episodes",
        "still_episodes",
        "jerky_episodes",
        "segments",
        "flags",
        "episode_length",
    }


def test_nan_fails(tmp_path):
    from shiftkit.datasets.quality import quality_verdict

    episodes = [smooth_episode(40, 0.3 * k) for k in range(3)]
    episodes[1]["action"][7, 1] = np.nan
    verdict = quality_verdict(write_lerobot(tmp_path / "nan", episodes))  # `validate` refuses its stats first
    assert verdict["verdict"] == "fail"
    assert "action: 1 NaN values detected" in [f["message"] for f in verdict["findings"] if f["severity"] == "fail"]


def test_validate_quality_json_and_strict(good, bad, capsys):
    # the timestamp gap is also a form error: the verdict comes first, then the one-line error
    assert main(["validate", str(bad), "--quality", "--json"]) == 2
    captured = capsys.readouterr()
    result = json.loads(captured.out)
    assert result["quality"]["verdict"] == "warn" and "episode 1: timestamps are not sampled" in result["error"]
    assert "episode 1: timestamps are not sampled at 10 fps" in captured.err
    assert main(["validate", str(bad), "--strict"]) == 2
    out = capsys.readouterr().out
    assert "quality: warn (10 findings in 8 episodes, action chunk 16)" in out
    assert "  warn constant_dims: observation.state: 1 of 3 dims constant over the whole dataset: z = 0.25" in out
    assert main(["validate", str(good), "--strict"]) == 0
    assert "quality: ok (6 episodes checked, action chunk 16)" in capsys.readouterr().out


def test_chunk_size_option(good, capsys):
    assert main(["validate", str(good), "--chunk-size", "100", "--strict"]) == 1
    out = capsys.readouterr().out
    assert "6 of 6 episodes are shorter than the action chunk of 100 frames (shortest 40)" in out
    assert main(["validate", str(good), "--chunk-size", "0"]) == 2
    assert "--chunk-size: must be a positive integer" in capsys.readouterr().err


def test_depth_against_its_unit():
    from shiftkit.datasets.depth import depth_feature
    from shiftkit.datasets.quality import _depth_findings

    metres, mm = depth_feature(4, 4, unit="m"), depth_feature(4, 4, unit="mm")
    assert _depth_findings("d", metres, {"min": [[[0.2]]], "max": [[[2.0]]]}) == []
    assert _depth_findings("d", mm, {"min": [[[0]]], "max": [[[2000]]]}) == []
    far = _depth_findings("d", metres, {"min": [[[0.2]]], "max": [[[80.6]]]})
    assert [f.severity for f in far] == ["warn"] and "up to 80.6 m" in far[0].message
    assert _depth_findings("d", metres, {"min": [[[-0.1]]], "max": [[[2.0]]]})[0].severity == "fail"
    assert (
        "millimetres stored as metres" in _depth_findings("d", metres, {"min": [[[0]]], "max": [[[1500.0]]]})[0].message
    )
    assert "metres stored as millimetres" in _depth_findings("d", mm, {"min": [[[0]]], "max": [[[2]]]})[0].message


def test_sts_mode_flicker_and_done_before_the_end():
    from shiftkit.datasets.quality import _Checks

    features = {
        "action": {"dtype": "float32", "shape": (2,), "names": ["dx", "sts_mode"]},
        "next.done": {"dtype": "bool", "shape": (1,), "names": None},
    }
    checks = _Checks(features, chunk_size=4)
    for k, (modes, done_at) in enumerate([([0] * 5 + [1] * 5, 9), ([0, 0, 1, 0, 0, 1, 1, 1, 1, 1], 4)]):
        n = len(modes)
        done = np.zeros((n, 1), bool)
        done[done_at] = True
        checks.add(
            k,
            {
                "timestamp": np.arange(n)[:, None] / FPS,
                "action": np.stack([np.linspace(0, 1, n), modes], axis=1).astype(np.float32),
                "next.done": done,
            },
        )
    messages = [f.message for f in checks.findings([], {})]
    assert "STS mode (action dim sts_mode) holds for a single frame between two others in episode 1" in messages
    assert "next.done is set before the last frame in episode 1" in messages


def test_run_records_the_verdict_in_provenance_and_card(synthetic_raw, tmp_path, capsys):
    config = tmp_path / "p.toml"
    config.write_text(f'seed = 0\n[[sources]]\npath = "{synthetic_raw}"\n[destination]\nroot = "{tmp_path / "out"}"\n')
    assert main(["run", str(config), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    provenance = json.loads((tmp_path / "out" / "meta" / "shiftkit_provenance.json").read_text())
    verdict = provenance["quality"]
    assert verdict["episodes"] == 5 and verdict["lerobot_doctor"]["checks"] == [
        "temporal",
        "actions",
        "statistics",
        "episodes",
    ]
    assert f"quality: {verdict['verdict']}" in printed
    card = (tmp_path / "out" / "README.md").read_text()
    assert "## Quality" in card and f"Verdict: **{verdict['verdict']}**" in card
    # the card lists every finding the provenance holds
    assert all(f["message"] in card for f in verdict["findings"])


def test_validate_help_imports_nothing_heavy():
    code = (
        "import sys; from shiftkit.app.cli import main; main(['validate', '--help']);"
        "print(sorted(m for m in ('torch', 'lerobot', 'lerobot_doctor', 'pandas') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().endswith("[]")
