"""The quality verdict of a LeRobot dataset's content: `ok`, `warn` or `fail`, with its findings.

`shiftkit validate` checks a dataset's form (it loads, its files agree with its metadata); this
module says whether its *content* is fit to learn from. The checks read only the numeric columns
(states, actions, flags, timestamps, indices: no image or video is decoded), one data file at a
time, episode by episode, and run after every `run`, `merge` and import (the verdict goes into the
provenance and the dataset card) and on any dataset with `shiftkit validate --quality`.

Two sources of checks:
* lerobot-doctor (a maintained package of dataset diagnostics; no lerobot import), called as a
  library on the numeric columns (`DOCTOR_CHECKS`): its temporal check (timestamp gaps, non-monotonic time, irregular
  intervals, frame indices) counts as a warning, and whatever it marks FAIL (NaN/inf, values
  clipped at a bound in >99% of frames, empty or one-frame episodes) as a failure. Its other
  warnings are heuristics tuned for teleoperated arms that fire on every scripted or
  binary-gripper dataset (a gripper dimension "stuck" at open, "outliers" in every velocity):
  they are listed as notes and do not change the verdict.
* shiftkit's own, which lerobot-doctor lacks or cannot name: constant and near-constant dimensions
  by their names; still episodes (the robot state hardly moves) and jerky ones (action second
  differences far above the dataset's usual); exactly duplicated episodes; episodes shorter than
  a policy's action chunk; depth outside its unit's range (from the dataset's statistics); flags
  (`next.success`, `next.done`, `intervention`, ...) never or always set, and `next.done` away from
  an episode's end; segments: task and STS-mode labels that flicker for a single frame, and tasks
  no frame uses.

Memory: shiftkit's checks keep a few numbers per episode and dimension; lerobot-doctor's keep the
numeric columns of the episodes they see, at most `DOCTOR_MAX_FRAMES` frames (beyond that they
see the first episodes, and the verdict says how many).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from shiftkit.datasets.depth import depth_unit, is_depth
from shiftkit.datasets.errors import DatasetError
from shiftkit.datasets.features import CAMERA_DTYPES, NUMERIC_DTYPES

QUALITY_VERSION = 1
CHUNK_SIZE = 16
"""Default action chunk an episode should cover: lerobot's diffusion policy horizon (ACT's is 100)."""
NEAR_CONSTANT = 1e-5
"""A dimension whose std is at most this share of its magnitude (`max(|mean|, 1)`) is near-constant."""
STILL = 0.01
"""An episode is still when no state dimension moves more than this share of its dataset-wide std."""
JERK_FACTOR, JERK_FLOOR = 5.0, 0.25
"""An episode is jerky when its action jerk (mean |second difference| in dataset stds) exceeds both
this many times the median episode's and this floor."""
DEPTH_RANGE_M = (0.01, 10.0)
"""lerobot 0.6's depth-video range (`DEFAULT_DEPTH_MIN/MAX`): depth encoded as video is clipped to it."""
DOCTOR_CHECKS = ("temporal", "actions", "statistics", "episodes")
"""lerobot-doctor's checks that run. Not its `anomalies`: of its four parts, "stuck actuators" and
"distribution shift" flag every gripper and every scripted dataset, "near-duplicate episodes"
compares every pair of episodes (quadratic: minutes at a thousand episodes; the exact duplicates
here are linear), and "constant observations" is the constant-dims check here, without names."""
DOCTOR_MAX_FRAMES = 2_000_000
LISTED = 8  # episodes named per finding
_INDEX_KEYS = ("frame_index", "episode_index", "index")


@dataclass
class Finding:
    """One thing the checks found."""

    check: str
    """What was checked, e.g. `constant_dims`, `timestamps`, `flags`."""
    severity: str
    """`fail` (the data is broken) or `warn` (suspicious: worth a look before training)."""
    message: str
    """One line that names the feature, dimensions or episodes."""
    by: str = "shiftkit"
    """`shiftkit` or `lerobot-doctor`."""

    def as_dict(self) -> dict[str, str]:
        """The finding as JSON-able values."""
        return {"check": self.check, "severity": self.severity, "message": self.message, "by": self.by}


@dataclass
class _Moments:
    """Per-dimension count, mean, M2 (Chan et al.'s parallel update), min, max and non-finite count."""

    n: int = 0
    mean: np.ndarray | None = None
    m2: np.ndarray | None = None
    lo: np.ndarray | None = None
    hi: np.ndarray | None = None
    nonfinite: int = 0

    def add(self, x: np.ndarray) -> None:
        finite = np.isfinite(x)
        self.nonfinite += int(x.size - finite.sum())
        x = x[finite.all(axis=1)]
        if not len(x):
            return
        mean, m2 = x.mean(axis=0), ((x - x.mean(axis=0)) ** 2).sum(axis=0)
        if self.mean is None:
            self.n, self.mean, self.m2, self.lo, self.hi = len(x), mean, m2, x.min(axis=0), x.max(axis=0)
            return
        n = self.n + len(x)
        delta = mean - self.mean
        self.m2 = self.m2 + m2 + delta**2 * self.n * len(x) / n
        self.mean = self.mean + delta * len(x) / n
        self.lo, self.hi, self.n = np.minimum(self.lo, x.min(axis=0)), np.maximum(self.hi, x.max(axis=0)), n

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(self.m2 / max(self.n, 1))


@dataclass
class _Checks:
    """shiftkit's own checks, fed one episode at a time."""

    features: dict[str, dict[str, Any]]
    chunk_size: int
    moments: dict[str, _Moments] = field(default_factory=dict)
    lengths: list[int] = field(default_factory=list)
    hashes: dict[str, list[int]] = field(default_factory=dict)
    state_ranges: list[np.ndarray] = field(default_factory=list)
    jerk: list[np.ndarray | None] = field(default_factory=list)  # per episode: mean |second difference| per dim
    action_diff: _Moments = field(default_factory=_Moments)  # second differences of the action, all episodes
    flag_frames: dict[str, int] = field(default_factory=dict)
    done_early: list[int] = field(default_factory=list)
    flicker: dict[str, list[int]] = field(default_factory=dict)
    tasks_used: set[int] = field(default_factory=set)
    frames: int = 0

    def add(self, index: int, columns: dict[str, np.ndarray]) -> None:
        n = len(columns["timestamp"])
        self.lengths.append(n)
        self.frames += n
        digest = hashlib.sha1()
        for key, arr in columns.items():
            ft = self.features.get(key, {})
            if key in _INDEX_KEYS or key == "timestamp":
                continue
            if key != "task_index":
                digest.update(key.encode() + np.ascontiguousarray(arr).tobytes())
            if ft.get("dtype") == "bool":
                self._flag(index, key, arr)
            elif key != "task_index":
                self.moments.setdefault(key, _Moments()).add(arr.astype(np.float64))
        self.hashes.setdefault(digest.hexdigest(), []).append(index)
        if "task_index" in columns:
            task = columns["task_index"].reshape(-1)
            self.tasks_used.update(np.unique(task).tolist())
            self._segments(index, "task", task)
        if "observation.state" in columns:
            state = columns["observation.state"].astype(np.float64)
            self.state_ranges.append(np.ptp(state, axis=0) if n else np.zeros(state.shape[1]))
        if "action" in columns:
            action = columns["action"].astype(np.float64)
            names = dimension_names(self.features.get("action", {}), action.shape[1])
            if "sts_mode" in names:
                self._segments(index, "action.sts_mode", action[:, names.index("sts_mode")])
            second = np.diff(action, n=2, axis=0) if n >= 3 else None
            self.jerk.append(None if second is None else np.abs(second).mean(axis=0))
            if second is not None:
                self.action_diff.add(second)

    def _flag(self, index: int, key: str, arr: np.ndarray) -> None:
        flags = arr.reshape(len(arr), -1).any(axis=1)
        self.flag_frames[key] = self.flag_frames.get(key, 0) + int(flags.sum())
        if key == "next.done" and flags[:-1].any():
            self.done_early.append(index)

    def _segments(self, index: int, key: str, labels: np.ndarray) -> None:
        """A label that holds for one frame between two others (a task or STS mode flickering)."""
        if len(labels) >= 3:
            inner = (labels[1:-1] != labels[:-2]) & (labels[1:-1] != labels[2:])
            if inner.any():
                self.flicker.setdefault(key, []).append(index)

    def findings(self, tasks: list[str], stats: dict[str, Any]) -> list[Finding]:
        out: list[Finding] = []
        for key, m in self.moments.items():
            out += _dimension_findings(key, self.features.get(key, {}), m)
        out += self._episode_findings()
        out += self._flag_findings()
        for key, episodes in self.flicker.items():
            what = "task label" if key == "task" else "STS mode (action dim sts_mode)"
            out.append(
                Finding("segments", "warn", f"{what} holds for a single frame between two others in {_eps(episodes)}")
            )
        unused = [t for i, t in enumerate(tasks) if i not in self.tasks_used]
        if unused:
            out.append(Finding("segments", "warn", f"tasks no frame uses: {', '.join(map(repr, unused[:LISTED]))}"))
        for key, ft in self.features.items():
            if ft.get("dtype") in CAMERA_DTYPES and is_depth(ft):
                out += _depth_findings(key, ft, stats.get(key))
        return out

    def _jerks(self) -> list[tuple[int, float]]:
        """(episode, mean |second difference| of the action in units of the dataset's std of that
        difference, over the dims that vary) of every episode with three frames or more."""
        if self.action_diff.mean is None:
            return []
        std = self.action_diff.std
        varies = std > 0
        if not varies.any():
            return []
        return [(i, float(np.mean(j[varies] / std[varies]))) for i, j in enumerate(self.jerk) if j is not None]

    def _episode_findings(self) -> list[Finding]:
        out = []
        example_set = all(n == 1 for n in self.lengths)  # success-example sets: one frame per episode
        short = [i for i, n in enumerate(self.lengths) if n < self.chunk_size]
        if short and not example_set:
            out.append(
                Finding(
                    "episode_length",
                    "warn",
                    f"{len(short)} of {len(self.lengths)} episodes are shorter than the action chunk of "
                    f"{self.chunk_size} frames (shortest {min(self.lengths)}): {_eps(short)}",
                )
            )
        if self.state_ranges and "observation.state" in self.moments and not example_set:
            std = self.moments["observation.state"].std
            moving = std > 0
            still = [
                i
                for i, r in enumerate(self.state_ranges)
                if self.lengths[i] > 1 and moving.any() and (r[moving] <= STILL * std[moving]).all()
            ]
            if still:
                out.append(
                    Finding(
                        "still_episodes",
                        "warn",
                        f"observation.state hardly moves (every dim within {STILL:g} of its std) in {_eps(still)}",
                    )
                )
        scored = self._jerks()
        if scored:
            median = float(np.median([j for _, j in scored]))
            jerky = [(i, j) for i, j in scored if j > JERK_FACTOR * median and j > JERK_FLOOR]
            if jerky:
                worst = max(j for _, j in jerky)
                out.append(
                    Finding(
                        "jerky_episodes",
                        "warn",
                        f"action jerk (mean |second difference| in action stds) above {JERK_FACTOR:g}x the median "
                        f"episode's {median:.3g} (up to {worst:.3g}) in {_eps([i for i, _ in jerky])}",
                    )
                )
        dup = [ids for ids in self.hashes.values() if len(ids) > 1]
        if dup:
            pairs = "; ".join(" = ".join(map(str, ids)) for ids in dup[:LISTED])
            out.append(Finding("duplicate_episodes", "warn", f"episodes with identical numeric data: {pairs}"))
        return out

    def _flag_findings(self) -> list[Finding]:
        out = []
        for key, frames in self.flag_frames.items():
            if frames == 0:
                what = " (no episode succeeds)" if key == "next.success" else ""
                out.append(Finding("flags", "warn", f"{key} is never set{what}"))
            elif frames == self.frames and self.frames > len(self.lengths):
                out.append(Finding("flags", "warn", f"{key} is set in every frame"))
        if self.done_early:
            out.append(Finding("flags", "warn", f"next.done is set before the last frame in {_eps(self.done_early)}"))
        return out


def dimension_names(feature: dict[str, Any], dims: int) -> list[str]:
    """A vector feature's dimension names (lerobot's list, or its `{"motors": [...]}` form), else
    the dimension indices as text."""
    names = feature.get("names")
    if isinstance(names, dict):
        names = next(iter(names.values()), None)
    if isinstance(names, list) and len(names) == dims:
        return [str(n) for n in names]
    return [str(d) for d in range(dims)]


def _eps(indices: list[int]) -> str:
    shown = ", ".join(map(str, indices[:LISTED]))
    return f"episode{'s' if len(indices) > 1 else ''} {shown}{', ...' if len(indices) > LISTED else ''}"


def _dimension_findings(key: str, feature: dict[str, Any], m: _Moments) -> list[Finding]:
    if m.mean is None:
        return []
    names = dimension_names(feature, len(m.mean))
    std, scale = m.std, np.maximum(np.abs(m.mean), 1.0)
    constant = np.flatnonzero(m.hi == m.lo)
    near = np.flatnonzero((m.hi != m.lo) & (std <= NEAR_CONSTANT * scale))
    out = []
    for dims, what in ((constant, "constant"), (near, f"near-constant (std <= {NEAR_CONSTANT:g} of magnitude)")):
        if len(dims):
            shown = ", ".join(f"{names[d]} = {m.mean[d]:.4g}" for d in dims[:LISTED])
            more = ", ..." if len(dims) > LISTED else ""
            out.append(
                Finding(
                    "constant_dims",
                    "warn",
                    f"{key}: {len(dims)} of {len(names)} dims {what} over the whole dataset: {shown}{more}",
                )
            )
    return out


def _depth_findings(key: str, feature: dict[str, Any], stats: dict[str, Any] | None) -> list[Finding]:
    """Depth against its unit's range, from the dataset's statistics (stored unit; sampled frames)."""
    if not stats or "min" not in stats or "max" not in stats:
        return []
    unit = depth_unit(feature)
    lo, hi = float(np.min(stats["min"])), float(np.max(stats["max"]))
    metres = (lo, hi) if unit == "m" else (lo / 1000.0, hi / 1000.0)
    out = []
    if lo < 0:
        out.append(Finding("depth_range", "fail", f"{key}: negative depth ({lo:.4g} {unit})"))
    if unit == "m" and hi > 1000:
        out.append(Finding("depth_range", "warn", f"{key}: up to {hi:.4g} 'm': millimetres stored as metres?"))
    elif unit == "mm" and 0 < hi < 20:
        out.append(Finding("depth_range", "warn", f"{key}: at most {hi:.4g} 'mm': metres stored as millimetres?"))
    elif metres[1] > DEPTH_RANGE_M[1]:
        out.append(
            Finding(
                "depth_range",
                "warn",
                f"{key}: depth up to {metres[1]:.3g} m, beyond lerobot's depth-video range "
                f"({DEPTH_RANGE_M[0]:g}-{DEPTH_RANGE_M[1]:g} m; stored as video it is clipped there): "
                "a simulator's far plane or a sensor's no-return value (lerobot's convention is 0)?",
            )
        )
    return out


# ------------------------------------------------------------------------------ lerobot-doctor


def _doctor_findings(report: Any) -> tuple[list[Finding], list[Finding]]:
    """(counted findings, notes) of a lerobot-doctor report (see the module docstring)."""
    from lerobot_doctor.runner import Severity

    counted, notes = [], []
    for result in report.results:
        for msg in result.messages:
            if msg.severity == Severity.PASS:
                continue
            finding = Finding(
                result.name, "fail" if msg.severity == Severity.FAIL else "warn", msg.message, "lerobot-doctor"
            )
            if msg.severity == Severity.FAIL or result.name == "Temporal Consistency":
                counted.append(finding)
            else:
                notes.append(finding)
    return counted, notes


# ------------------------------------------------------------------------------ reading


def _numeric_keys(info: dict[str, Any]) -> list[str]:
    return [k for k, ft in info["features"].items() if ft.get("dtype") in NUMERIC_DTYPES]


def _episode_columns(root: Path, info: dict[str, Any]):
    """(episode index, {key: (n, dims) array}) of every episode, one data file read at a time."""
    import pyarrow.parquet as pq

    from shiftkit.datasets.arrow_columns import column_to_numpy

    keys = _numeric_keys(info)
    files = sorted((root / "data").glob("*/*.parquet"))
    if not files:
        raise DatasetError(f"{root}/data: no data files")
    for path in files:
        try:
            table = pq.read_table(path, columns=keys)
        except Exception as exc:  # pyarrow raises several types for corrupt files
            raise DatasetError(f"{path}: unreadable parquet file ({type(exc).__name__})") from None
        columns = {}
        for key in keys:
            ft = info["features"][key]
            arr = column_to_numpy(table.column(key), np.dtype(ft["dtype"]))
            columns[key] = arr.reshape(table.num_rows, -1)
        episode = columns["episode_index"].reshape(-1)
        bounds = [0, *(np.flatnonzero(np.diff(episode)) + 1).tolist(), len(episode)]
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            if b > a:
                yield int(episode[a]), {k: v[a:b] for k, v in columns.items()}


def quality_verdict(root: str | Path, chunk_size: int = CHUNK_SIZE) -> dict[str, Any]:
    """The verdict on the dataset at `root`: `{"verdict": "ok"|"warn"|"fail", "findings": [...],
    "notes": [...], ...}` (JSON-able; the same data gives the same verdict)."""
    from importlib import metadata

    from lerobot_doctor.dataset_loader import EpisodeData, LoadedDataset, load_info
    from lerobot_doctor.runner import run_checks

    from shiftkit.datasets.jsonutil import read_json_file

    root = Path(root)
    info = read_json_file(root / "meta" / "info.json", "dataset info")
    stats_path = root / "meta" / "stats.json"
    stats = read_json_file(stats_path, "dataset statistics") if stats_path.is_file() else {}
    tasks = _task_names(root)
    checks = _Checks(info["features"], chunk_size)
    doctor_episodes: list[Any] = []
    doctor_frames = 0
    for index, columns in _episode_columns(root, info):
        checks.add(index, columns)
        n = len(columns["timestamp"])
        if doctor_frames + n <= DOCTOR_MAX_FRAMES:
            doctor_frames += n
            # lerobot-doctor's loader gives one-dimensional features as (n,) arrays
            doctor_episodes.append(
                EpisodeData(index, {k: v if v.shape[1] > 1 else v[:, 0] for k, v in columns.items()}, n)
            )
    findings = checks.findings(tasks, stats)

    doctor_info = load_info(root)
    loaded = LoadedDataset(root=root, display_path=str(root), info=doctor_info, episodes_data=doctor_episodes)
    counted, notes = _doctor_findings(run_checks(loaded, checks=list(DOCTOR_CHECKS)))
    findings += counted
    severities = {f.severity for f in findings}
    verdict = "fail" if "fail" in severities else "warn" if severities else "ok"
    out = {
        "quality_version": QUALITY_VERSION,
        "verdict": verdict,
        "chunk_size": chunk_size,
        "episodes": len(checks.lengths),
        "frames": checks.frames,
        "findings": [f.as_dict() for f in findings],
        "notes": [f.as_dict() for f in notes],
        "lerobot_doctor": {
            "version": metadata.version("lerobot-doctor"),
            "checks": list(DOCTOR_CHECKS),
            "episodes": len(doctor_episodes),
        },
    }
    return json.loads(json.dumps(out))


def _task_names(root: Path) -> list[str]:
    import pandas as pd

    try:
        df = pd.read_parquet(root / "meta" / "tasks.parquet")
    except Exception:  # validate reports a broken tasks table; the verdict just has no names
        return []
    names = [""] * len(df)
    for task, idx in zip(df.index, df["task_index"], strict=True):
        names[int(idx)] = str(task)
    return names


def verdict_lines(verdict: dict[str, Any], limit: int | None = 10) -> list[str]:
    """The verdict as the lines `validate --quality`, `run`, `merge` and `import` print."""
    findings = verdict["findings"]
    head = f"quality: {verdict['verdict']}"
    if not findings:
        head += f" ({verdict['episodes']} episodes checked"
    else:
        head += f" ({len(findings)} finding{'s' if len(findings) > 1 else ''} in {verdict['episodes']} episodes"
    head += f", action chunk {verdict['chunk_size']})"
    lines = [head]
    shown = findings if limit is None else findings[:limit]
    for f in shown:
        by = " [lerobot-doctor]" if f["by"] == "lerobot-doctor" else ""
        lines.append(f"  {f['severity']} {f['check']}{by}: {f['message']}")
    if len(shown) < len(findings):
        lines.append(f"  ... {len(findings) - len(shown)} more (shiftkit validate DATASET --quality --json)")
    if verdict["notes"]:
        lines.append(
            f"  lerobot-doctor also noted {len(verdict['notes'])} heuristic warning(s) that do not count "
            "(listed by --quality --json)"
        )
    return lines
