"""Human-in-the-loop rollouts as lerobot 0.6.1 records them (`lerobot-rollout --strategy.type=dagger`).

lerobot's DAgger strategy writes the robot's observation features, `action` and one more per-frame
feature, `intervention` (bool, shape (1,), no names: True while the operator drives through the
teleoperator). Its two layouts:

* `record_autonomous=true`: continuous recording; the policy's frames (`intervention` False) and the
  operator's corrections (True) in one stream, rotated into episodes by time;
* `record_autonomous=false`: only the corrections; each one (start to stop) is its own episode.

Frames recorded while paused do not exist in either layout. Offline FIRE (`fire.aggregate`) reads
both, and the simulated FIRE loop writes its rollouts in the first so that every path a lab with a
real robot takes can be run here.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from shiftkit.datasets.dataset import Dataset
from shiftkit.datasets.dataset import open as resolve_dataset
from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import DatasetError
from shiftkit.datasets.features import Features, user_features
from shiftkit.datasets.reader import LeRobotDatasetReader, open_lerobot_dataset
from shiftkit.datasets.writer import write_episodes

INTERVENTION = "intervention"
# exactly as lerobot's rollout context declares it (rollout/context.py)
INTERVENTION_FEATURE: dict[str, Any] = {"dtype": "bool", "shape": (1,), "names": None}
# lerobot-rollout refuses dataset names without this prefix
ROLLOUT_PREFIX = "rollout_"


def rollout_repo_id(name: str, org: str = "local") -> str:
    """A repo ID lerobot-rollout would accept for a recording called `name`."""
    name = name if name.startswith(ROLLOUT_PREFIX) else ROLLOUT_PREFIX + name
    return f"{org}/{name}"


def runs(flags: np.ndarray) -> list[tuple[int, int, bool]]:
    """Maximal runs of equal values: `(start, end, value)` with `end` exclusive."""
    flags = np.asarray(flags, dtype=bool).reshape(-1)
    if len(flags) == 0:
        return []
    cuts = np.flatnonzero(np.diff(flags.astype(np.int8))) + 1
    starts, ends = np.r_[0, cuts], np.r_[cuts, len(flags)]
    return [(int(s), int(e), bool(flags[s])) for s, e in zip(starts, ends, strict=True)]


def write_recording(
    root: str | Path,
    repo_id: str,
    fps: int,
    features: Features,
    episodes: Iterable[Episode],
    *,
    sources: list[dict[str, Any]],
    robot_type: str | None = None,
    record_autonomous: bool = True,
) -> Path:
    """Write rollouts in lerobot's DAgger layout. `features`: the robot's observation features and
    `action`; each episode holds them, `intervention` ((n, 1) bool), `timestamp` and `task`. With
    `record_autonomous` False only the corrections are kept, each its own episode (timestamps from 0).
    `sources`: where the rollouts come from, for the provenance every shiftkit dataset carries."""
    schema = {**{k: v for k, v in features.items() if k != INTERVENTION}, INTERVENTION: INTERVENTION_FEATURE}

    def recorded() -> Iterator[Episode]:
        written = 0
        for episode in episodes:
            frames = {k: episode.frames[k] for k in [*schema, "task"]}
            flags = np.asarray(frames[INTERVENTION], dtype=bool).reshape(-1)
            parts = [(0, len(flags))] if record_autonomous else [(s, e) for s, e, on in runs(flags) if on]
            for start, end in parts:
                part = {k: v[start:end] for k, v in frames.items()}
                part[INTERVENTION] = flags[start:end, None]
                part["timestamp"] = (np.arange(end - start) / fps).astype(np.float32)
                written += 1
                yield Episode(part)
        if written == 0:
            raise DatasetError(f"no frames to record in {root}: the rollouts hold no corrections")

    write_episodes(
        repo_id,
        root,
        fps,
        schema,
        recorded(),
        robot_type=robot_type,
        sources=sources,
        dagger={"record_autonomous": record_autonomous},
    )
    return Path(root)


@dataclass
class Recording:
    """One opened DAgger recording (its layout shows in its frames: corrections only, or both)."""

    resolved: Dataset
    reader: LeRobotDatasetReader

    @property
    def name(self) -> str:
        """The recording's repo id."""
        return self.resolved.repo_id


def _differences(expected: dict, got: dict) -> str | None:
    for field in ("dtype", "shape", "names"):
        a, b = expected.get(field), got.get(field)
        if field == "shape":
            a, b = tuple(a), tuple(b)
        if a != b:
            return f"{field} {b!r} instead of {a!r}"
    return None


def open_recordings(refs: list[str], fps: int, features: Features) -> list[Recording]:
    """Open DAgger recordings and check them against the demonstrations' `fps` and `features` (every
    recording feature but `intervention` must be a demonstration feature of the same dtype, shape
    and names, and all recordings must hold the same features). DatasetError (one line) otherwise."""
    if not refs:
        raise DatasetError("no rollout recording given")
    out: list[Recording] = []
    for ref in refs:
        resolved = resolve_dataset(ref)
        reader = open_lerobot_dataset(resolved.root)
        name = resolved.repo_id
        got = user_features(reader.features)
        if INTERVENTION not in got:
            raise DatasetError(f"rollouts {name}: no per-frame 'intervention' feature (not a DAgger recording)")
        if (diff := _differences(INTERVENTION_FEATURE, {**got[INTERVENTION], "names": None})) is not None:
            raise DatasetError(f"rollouts {name}: feature 'intervention' has {diff}")
        if reader.fps != fps:
            raise DatasetError(f"rollouts {name} run at {reader.fps} fps but the demonstrations at {fps} fps")
        for key, ft in got.items():
            if key == INTERVENTION:
                continue
            if key not in features:
                raise DatasetError(f"rollouts {name}: feature {key!r} is not in the demonstrations")
            if (diff := _differences(features[key], ft)) is not None:
                raise DatasetError(f"rollouts {name}: feature {key!r} has {diff} (as in the demonstrations)")
        if out:
            first = set(out[0].reader.features)
            if set(got) != first:
                odd = sorted(set(got) ^ first)[0]
                raise DatasetError(f"rollouts {name} and {out[0].name} differ in feature {odd!r}")
        if reader.num_episodes == 0:
            raise DatasetError(f"rollouts {name} hold no episode")
        out.append(Recording(resolved, reader))
    return out
