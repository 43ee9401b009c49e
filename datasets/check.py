"""Summaries (`shiftkit info`) and integrity checks (`shiftkit validate`) of LeRobot datasets."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from shiftkit.cards.render import shiftkit_version
from shiftkit.datasets.dataset import Dataset, as_dataset
from shiftkit.datasets.depth import depth_unit, is_depth
from shiftkit.datasets.errors import DatasetError
from shiftkit.datasets.loaders import load_stats
from shiftkit.datasets.provenance import format_report
from shiftkit.datasets.quality import verdict_lines


def summarize(dataset: Dataset | str | Path) -> dict[str, Any]:
    """Features, counts, tasks, stats summary and provenance, as a JSON-able dict."""
    dataset = as_dataset(dataset)
    root, reader = dataset.root, dataset.reader
    stats_path = root / "meta" / "stats.json"
    stats = _read_stats(stats_path) if stats_path.exists() else {}
    return {
        "root": str(root),
        "codebase_version": reader.info.get("codebase_version"),
        "robot_type": reader.robot_type,
        "fps": reader.fps,
        "episodes": reader.num_episodes,
        "frames": int(reader.info.get("total_frames", 0)),
        "tasks": reader.tasks,
        "features": {
            k: {"dtype": ft["dtype"], "shape": list(ft["shape"]), "names": ft.get("names")}
            for k, ft in reader.features.items()
        },
        "stats": {
            k: {s: v[s] for s in ("mean", "std", "min", "max") if s in v}
            for k, v in stats.items()
            if k in reader.features and reader.features[k]["dtype"] not in ("image", "video")
        },
        "cameras": {"cameras": reader.cameras["cameras"], "episodes": reader.cameras["episodes"]},
        "provenance": dataset.provenance or None,
    }


def format_summary(summary: dict[str, Any]) -> str:
    """The `summarize` summary as the text `shiftkit info` prints."""

    def short(v: Any) -> str:
        flat = np.asarray(v, dtype=float).ravel()
        return "[" + ", ".join(f"{x:.3g}" for x in flat[:4]) + (", ..." if flat.size > 4 else "") + "]"

    lines = [
        f"{summary['root']}  ({summary['codebase_version']}, robot {summary['robot_type']})",
        f"episodes {summary['episodes']}, frames {summary['frames']}, fps {summary['fps']}",
        f"tasks ({len(summary['tasks'])}): {', '.join(summary['tasks'])}",
        "features:",
    ]
    width = max(len(k) for k in summary["features"])
    for key, ft in summary["features"].items():
        st = summary["stats"].get(key)
        extra = f"mean {short(st['mean'])} std {short(st['std'])}" if st and "mean" in st else ""
        lines.append(f"  {key:<{width}}  {ft['dtype']:<8} {str(tuple(ft['shape'])):<14} {extra}")
    lines += _camera_lines(summary["cameras"], summary["episodes"])
    prov = summary["provenance"]
    if prov:
        lines.append(
            f"provenance: shiftkit {shiftkit_version(prov['versions'])}, lerobot {prov['versions'].get('lerobot')}, seed {prov.get('seed')}"
        )
        for src in prov.get("sources", []):
            facts = {k: v for k, v in src.items() if v not in (None, "") and k not in ("stages", "episodes")}
            line = "  source: " + ", ".join(f"{k}={v}" for k, v in facts.items())
            if isinstance(src.get("episodes"), list):
                first, end = src["episodes"]
                line += f"; output episodes {first}..{end - 1} ({end - first})"
            lines.append(line)
            for stage in src.get("stages", []):
                lines.append(
                    f"    own stage: {stage['name']} v{stage['version']} {json.dumps(stage['params'], sort_keys=True)}"
                )
        for stage in prov.get("stages", []):
            lines.append(f"  stage: {stage['name']} v{stage['version']} {json.dumps(stage['params'], sort_keys=True)}")
            if stage.get("report"):
                lines.append(f"    report: {format_report(stage['report'])}")
        if prov.get("quality"):  # the writer's verdict on what it wrote (`validate --quality` anew)
            lines += verdict_lines(prov["quality"])
    else:
        lines.append("provenance: none (not made by shiftkit)")
    return "\n".join(lines)


def _camera_lines(cameras: dict[str, Any], num_episodes: int) -> list[str]:
    """One line per camera: intrinsics, extrinsics and which entries vary per episode."""
    per_episode: dict[str, set[str]] = {}
    for cams in cameras["episodes"].values():
        for name, cam in cams.items():
            per_episode.setdefault(name, set()).update(cam)
    names = sorted(set(cameras["cameras"]) | set(per_episode))
    if not names:
        return []
    lines = ["cameras (meta/cameras.json):"]
    for name in names:
        cam, parts = cameras["cameras"].get(name, {}), []
        own = {key: e["intrinsics"] for key, e in (cam.get("features") or {}).items() if e.get("intrinsics")}
        for key, intr in [("", cam.get("intrinsics")), *own.items()]:  # a feature's own, where they differ
            if intr:
                parts.append(
                    f"{f'{key} ' if key else ''}{intr['width']}x{intr['height']} fx {intr['fx']:.1f} "
                    f"fy {intr['fy']:.1f} cx {intr['cx']:.1f} cy {intr['cy']:.1f}"
                )
        if extr := cam.get("extrinsics"):
            parts.append(f"at [{', '.join(f'{x:.3f}' for x in extr['position'])}] in the {extr['frame']} frame")
        if varying := per_episode.get(name):
            counts = sum(name in cams for cams in cameras["episodes"].values())
            parts.append(f"per episode: {', '.join(sorted(varying))} ({counts}/{num_episodes} episodes)")
        lines.append(f"  {name}: " + "; ".join(parts))
    return lines


def validate_dataset(dataset: Dataset | str | Path) -> dict[str, Any]:
    """Read every episode and check it against the metadata; raise DatasetError on the first problem.

    Checks: info/episodes/tasks metadata readable and consistent; every data file readable; each
    episode's rows, indices, frame indices, timestamps and tasks; shapes and dtypes; NaN/inf in
    float features; the statistics a trainer needs (`check_stats`); lerobot itself can open the
    dataset and read its first and last frame (videos through the pyav backend). Returns the
    counts and the `warnings` (problems no trainer fails on).
    """
    from shiftkit.datasets.features import check_episode

    dataset = as_dataset(dataset)
    root, reader = dataset.root, dataset.reader
    warnings = check_stats(root, reader.features)
    frames = 0
    next_index = 0
    for ep in reader.iter_episodes():
        i = ep.meta["source_episode_index"]
        row = reader.episodes.iloc[i]
        if int(row["dataset_from_index"]) != next_index:
            raise DatasetError(
                f"{root}: episode {i} starts at index {int(row['dataset_from_index'])}, expected {next_index}"
            )
        check_episode(ep, reader.features, reader.fps, f"{root} episode {i}")
        next_index = int(row["dataset_to_index"])
        frames += len(ep)
    if frames != int(reader.info.get("total_frames", -1)):
        raise DatasetError(f"{root}: {frames} frames in the data, info.json says {reader.info.get('total_frames')}")
    if reader.num_episodes != int(reader.info.get("total_episodes", -1)):
        raise DatasetError(
            f"{root}: {reader.num_episodes} episodes, info.json says {reader.info.get('total_episodes')}"
        )
    check_lerobot_loads(root)
    dataset.provenance  # noqa: B018 - `info` shows it and trainers read it: its loader checks it here too
    return {"episodes": reader.num_episodes, "frames": frames, "warnings": warnings}


# What lerobot's normalizer reads from a feature's statistics entry (MEAN_STD or MIN_MAX modes).
TRAINING_STATS = ("mean", "std", "min", "max")


def check_stats(root: Path, features: dict[str, Any]) -> list[str]:
    """The statistics trainers read. An entry that exists but lacks mean/std/min/max, or holds
    NaN/inf, is an error (lerobot's normalizer raises on it, or trains on NaN); so is a missing
    `action` entry (every trainer normalises the action). A feature without an entry is a warning:
    lerobot's trainers leave it unnormalised (lerobot's own tools write such datasets, e.g. a video
    feature after `convert_image_to_video_dataset`, a feature from `add_features`), and shiftkit's
    BC cannot take it as an input until `shiftkit run` recomputes the statistics."""
    stats_path = root / "meta" / "stats.json"
    if not stats_path.exists():
        raise DatasetError(f"{stats_path} is missing (trainers read the normalisation statistics from it)")
    stats = _read_stats(stats_path)
    warnings = []
    for key in features:
        entry = stats.get(key)
        if entry is None:
            if key == "action":
                raise DatasetError(f"{stats_path}: no statistics for 'action' (every trainer normalises it)")
            warnings.append(
                f"{stats_path}: no statistics for {key!r} (lerobot trains with it unnormalised; "
                "shiftkit's BC cannot use it as an input)"
            )
            continue
        lacking = [s for s in TRAINING_STATS if s not in entry]
        if lacking:
            raise DatasetError(f"{stats_path}: statistics of {key!r} lack {lacking} (lerobot's normalizer needs them)")
        if not all(np.isfinite(np.asarray(entry[s], dtype=float)).all() for s in TRAINING_STATS):
            raise DatasetError(f"{stats_path}: statistics of {key!r} hold NaN or inf")
    return warnings


def check_lerobot_loads(root: Path) -> None:
    """lerobot opens the dataset and reads its first and last frame (decoding videos with pyav,
    the backend that works where torchcodec cannot load FFmpeg)."""
    try:
        from lerobot.datasets.lerobot_dataset import LeRobotDataset

        dataset = LeRobotDataset(f"local/{root.name}", root=root, video_backend="pyav")
        dataset[0]
        dataset[len(dataset) - 1]
    except Exception as exc:
        raise DatasetError(
            f"{root}: lerobot cannot load it ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
        ) from None


def recompute_stats(dataset: Dataset | str | Path, rtol: float = 1e-3) -> int:
    """Recompute mean/std/min/max of every numeric feature from the data files (streamed per
    episode) and compare with meta/stats.json, and check that depth images hold values possible in
    their declared unit (`check_depth_values`); raise DatasetError naming the first problem.
    Returns how many features' statistics were checked."""
    dataset = as_dataset(dataset)
    root, reader = dataset.root, dataset.reader
    stats = _read_stats(root / "meta" / "stats.json")
    acc: dict[str, list] = {}  # key -> [count, sum, sum of squares, min, max]
    for ep in reader.iter_episodes():
        for key, arr in ep.frames.items():
            ft = reader.features.get(key)
            if ft is not None and ft["dtype"] == "image" and is_depth(ft):
                check_depth_values(arr, depth_unit(ft), f"{root} episode {ep.meta['source_episode_index']} {key!r}")
            if ft is None or ft["dtype"] in ("image", "video", "string") or key not in stats:
                continue
            x = np.asarray(arr, dtype=np.float64).reshape(len(arr), -1)
            a = acc.setdefault(key, [0, 0.0, 0.0, np.inf, -np.inf])
            a[0] += len(x)
            a[1] = a[1] + x.sum(0)
            a[2] = a[2] + (x * x).sum(0)
            a[3], a[4] = np.minimum(a[3], x.min(0)), np.maximum(a[4], x.max(0))
    for key, (n, total, squares, lo, hi) in acc.items():
        mean = total / n
        std = np.sqrt(np.maximum(squares / n - mean * mean, 0.0))
        computed = {"mean": mean, "std": std, "min": lo, "max": hi}
        scale = np.maximum(np.abs(hi - lo), 1e-6)  # tolerance relative to the feature's range
        # a std aggregated in float32 from sums of squares (lerobot's tools) keeps half the digits:
        # about sqrt(eps) x the values' size, even for a constant feature (whose range is 0)
        cancellation = np.sqrt(np.finfo(np.float32).eps) * np.maximum(np.abs(lo), np.abs(hi))
        for name, value in computed.items():
            if name not in stats[key]:
                continue
            try:
                recorded = np.asarray(stats[key][name], dtype=np.float64).reshape(-1)
            except (TypeError, ValueError):
                raise DatasetError(f"{root}/meta/stats.json: {name} of {key!r} is not a list of numbers") from None
            atol = 1e-6 + (cancellation if name == "std" else 0.0)
            if recorded.shape != value.shape or not np.all(np.abs(recorded - value) <= rtol * scale + atol):
                raise DatasetError(
                    f"{root}/meta/stats.json: {name} of {key!r} is {_short(recorded)}, the data gives {_short(value)}"
                )
    return len(acc)


# Farther than any robot depth camera measures (lerobot's depth video range ends at 10 m): a depth
# image in metres beyond it holds another unit's numbers (millimetres stored as metres read 1000x).
MAX_DEPTH_M = 100.0


def check_depth_values(metres: np.ndarray, unit: str, where: str) -> None:
    """A depth image feature's frames (float32 metres, as read) hold values its declared unit can
    hold: none negative; in metres, none beyond `MAX_DEPTH_M`; in millimetres, whole millimetres
    (float metres stored under "mm" read back as fractions of a millimetre)."""
    d = np.asarray(metres, dtype=np.float64)
    if (d < 0).any():
        raise DatasetError(f"{where}: negative depth {d.min():.4g} m")
    if unit == "m" and d.max(initial=0.0) > MAX_DEPTH_M:
        raise DatasetError(
            f"{where}: depth up to {d.max():.6g} m is impossible in metres (more than {MAX_DEPTH_M:g} m); "
            "millimetres stored under depth_unit 'm'?"
        )
    if unit == "mm":
        mm = d * 1000.0
        off = np.abs(mm - np.rint(mm)).max(initial=0.0)
        if off > 0.05:  # float32 metres of whole millimetres are within 0.01 mm of them
            raise DatasetError(
                f"{where}: depth of {off:.3g} mm off whole millimetres is impossible in uint16 millimetres; "
                "metres stored under depth_unit 'mm'?"
            )


def _read_stats(path: Path) -> dict[str, dict[str, Any]]:
    return load_stats(path)


def _short(v: np.ndarray) -> str:
    return "[" + ", ".join(f"{x:.4g}" for x in v[:4]) + (", ..." if v.size > 4 else "") + "]"
