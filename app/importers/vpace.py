"""Import the VPACE / LfGP authors' published expert buffers (utiasSTARS/vpace `expert_data/`) as
LeRobot datasets.

A buffer file is gzip + pickle of a dict of numpy arrays written by their circular replay buffer
(format facts: shared/data/vpace/README.md). Two kinds exist:

* example files (`1200_per_task/<i>_<task>.gz`): independent success states of one task. Each row
  becomes a one-frame episode whose `task` is the file's task (as `success_examples` writes them).
* trajectory files (`full_trajectories/.../<i>_<task>.gz`): expert transitions. Rows are put back in
  insertion order and split into episodes where `next_observations[t] != observations[t + 1]`;
  actions and rewards are kept.

Observations (59 dims + absorbing flag in LfGP-era files, 53 + flag in VPACE-era files) are split
into `observation.state` / `observation.environment_state` with the Panda play env's names, the
always-zero absorbing flag is dropped, and the gripper action is converted to shiftkit's sign.
"""

from __future__ import annotations

import gzip
import hashlib
import io
import pickle
import re
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from shiftkit.datasets.dataclass_config import option
from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import DatasetError
from shiftkit.datasets.features import Features, vector_feature
from shiftkit.datasets.importers import Importer, register_importer
from shiftkit.datasets.sources import groups_by_file

Kind = Literal["auto", "examples", "trajectories"]

# Observation width without the absorbing flag -> control rate of the data: the LfGP-era Panda
# tasks (59 dims, with force-torque) ran at 20 Hz, the VPACE-era ones (53 dims) at 5 Hz (thesis B.2).
ERA_FPS = {59: 20, 53: 5}
_REQUIRED_KEYS = ("observations", "next_observations", "actions", "rewards", "memory_size", "pointer", "count")
# File names in the reference's `expert_data/` (utiasSTARS/vpace env_default_configs.py):
# * Panda play: `<intention index>_[<scene>-]<task>[_<revision>].gz`, e.g. `0_stack-open` (the open
#   task in the stack scene), `5_move_new` (a later recording of move); any prefix before the index
#   is ignored (`examples_1200_3_lift`).
# * every other environment: `<env>.gz` holds its main task, `<env>_[random_]<aux>[_<variant>].gz`
#   an auxiliary task (reach or grasp), e.g. `sawyer_lift_random_reach`, `door-human-v0_reach_mulperep`.
_NUMBERED_NAME = re.compile(r"^(?:.*_)?(\d+)_([A-Za-z][A-Za-z0-9-]*)(?:_([A-Za-z][A-Za-z0-9-]*))?$")
_PANDA_PLAY_SCENES = ("unstack-stack", "stack", "bring", "insert")  # main tasks whose scene a file name may name
_PANDA_PLAY_ALIASES = {"move": "move-object"}  # reference task name -> this env's
_REFERENCE_ENVS = (
    "sawyer_air_reach",
    "sawyer_bin_picking",
    "sawyer_box_close",
    "sawyer_drawer_close",
    "sawyer_drawer_open",
    "sawyer_lift",
    "sawyer_push",
    "sawyer_reach",
    "door-human-v0",
    "hammer-human-v0",
    "relocate-human-v0",
    "relocate-human-v0-najp",
    "PandaReach",
    "SimPandaReach",
    "PandaDoor",
    "PandaDoorAngle",
    "PandaDoorNoJamAngle",
    "PandaDrawer",
    "PandaDrawerLine",
)
_ENV_NAME = re.compile(
    r"(?:^|_)(" + "|".join(re.escape(e) for e in sorted(_REFERENCE_ENVS, key=len, reverse=True)) + r")(?:_(.+))?$"
)
_AUX_TASKS = ("reach", "grasp")


@dataclass
class VpaceBuffer:
    """One published buffer, rows in insertion order, absorbing flag removed."""

    path: Path
    sha256: str
    task: str
    observations: np.ndarray
    """(N, 59 or 53) float32."""
    next_observations: np.ndarray
    actions: np.ndarray
    """(N, 4) float32, gripper dim in shiftkit's sign convention (> 0 opens)."""
    rewards: np.ndarray
    """(N, num_tasks) float32 as stored (the generating env's task order)."""
    overwritten_rows: int
    """Oldest rows the circular buffer dropped (count - memory_size when it wrapped)."""
    reference_name: ReferenceName | None = None
    """What the file name says (None when the task was given instead)."""

    @property
    def obs_dim(self) -> int:
        """Length of one observation row."""
        return int(self.observations.shape[1])

    def kind(self) -> str:
        """ "trajectories" if any row continues into the next one, else "examples"."""
        continues = np.all(self.next_observations[:-1] == self.observations[1:], axis=1)
        return "trajectories" if continues.any() else "examples"

    def episode_bounds(self) -> list[tuple[int, int]]:
        """[start, end) row ranges of the episodes: a new one starts wherever a row's next
        observation is not the following row's observation (the files' `dones` are all False)."""
        breaks = np.flatnonzero(np.any(self.next_observations[:-1] != self.observations[1:], axis=1)) + 1
        edges = [0, *breaks.tolist(), len(self.observations)]
        return list(zip(edges[:-1], edges[1:], strict=True))


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickles numpy arrays, scalars and RandomState only: a buffer file cannot run code."""

    _ALLOWED = {
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy.core.multiarray", "scalar"),
        ("numpy._core.multiarray", "scalar"),
        ("numpy.random._pickle", "__randomstate_ctor"),
        ("numpy.random._pickle", "__bit_generator_ctor"),
    }

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in self._ALLOWED:
            return super().find_class(module, name)
        if module == "numpy" or module.startswith("numpy.dtypes"):
            obj = super().find_class(module, name)
            if isinstance(obj, type) and (issubclass(obj, np.generic) or issubclass(obj, np.dtype)):
                return obj
        raise pickle.UnpicklingError(f"refusing to load {module}.{name} (only numpy arrays are expected)")


@dataclass(frozen=True)
class ReferenceName:
    """What a reference file name says about its contents."""

    task: str
    """The task whose states/transitions the file holds (Panda play files: this env's task name)."""
    scene: str | None = None
    """Panda play: the main task whose scene the file was recorded in (`0_stack-open` -> stack);
    other environments: the reference's environment name."""
    variant: str | None = None
    """The rest of the name: a re-recording (`new`, `fix`) or sampling variant (`mulperep`, `p02z`)."""


def parse_reference_name(path: str | Path) -> ReferenceName:
    """Map a file name of the reference's `expert_data/` folders to the task it holds:
    `5_move_new.gz` -> move-object, `0_stack-open.gz` -> open (stack scene), `sawyer_lift.gz` ->
    sawyer_lift (the environment's main task), `sawyer_lift_random_reach.gz` -> reach."""
    stem = Path(path).name.removesuffix(".gz")
    m = _ENV_NAME.search(stem)
    if m is not None:
        env, rest = m.group(1), m.group(2).split("_") if m.group(2) else []
        if rest[:1] == ["random"] and rest[1:2] and rest[1] in _AUX_TASKS:
            rest = rest[1:]
        if rest and rest[0] in _AUX_TASKS:
            return ReferenceName(rest[0], env, "_".join(rest[1:]) or None)
        return ReferenceName(env, env, "_".join(rest) or None)
    m = _NUMBERED_NAME.match(stem)
    if m is None:
        raise DatasetError(
            f"{path}: cannot tell the task from the file name (expected <index>_<task>.gz or <env>[_<aux>].gz "
            "as in the reference's expert_data/); give --task"
        )
    name, variant = m.group(2), m.group(3)
    scene = next((s for s in _PANDA_PLAY_SCENES if name.startswith(f"{s}-")), None)
    task = name.removeprefix(f"{scene}-") if scene else name
    return ReferenceName(_PANDA_PLAY_ALIASES.get(task, task), scene, variant)


def task_from_filename(path: str | Path) -> str:
    """The task a reference file holds, from its name (see `parse_reference_name`)."""
    return parse_reference_name(path).task


def read_vpace_buffer(path: str | Path, task: str | None = None) -> VpaceBuffer:
    """Load and check one buffer file; rows come back oldest first."""
    vpace_action_to_shiftkit = _panda_play().action_conventions["vpace"]

    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: no such file")
    raw_bytes = path.read_bytes()
    try:
        data = _NumpyOnlyUnpickler(gzip.GzipFile(fileobj=io.BytesIO(raw_bytes))).load()
    except (OSError, EOFError, pickle.UnpicklingError, AttributeError, ImportError, ValueError) as exc:
        raise DatasetError(f"{path}: not a VPACE buffer (gzip + pickle of numpy arrays): {exc}") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a dict of arrays, got {type(data).__name__}")
    missing = [k for k in _REQUIRED_KEYS if k not in data]
    if missing:
        raise DatasetError(f"{path}: missing key(s) {missing}")
    counters = [data[k] for k in ("memory_size", "pointer", "count")]
    if not all(
        isinstance(v, (int, np.integer, np.ndarray)) and np.ndim(v) == 0 and np.asarray(v).dtype.kind in "iu"
        for v in counters
    ):
        raise DatasetError(f"{path}: memory_size, pointer and count must be integers")
    size, pointer, count = (int(v) for v in counters)
    if size < 0 or count < 0 or not 0 <= pointer < max(size, 1):
        raise DatasetError(f"{path}: pointer {pointer} is outside the buffer of {size} rows (count {count})")
    if min(count, size) == 0:
        raise DatasetError(f"{path}: empty buffer (no rows)")
    arrays = {k: _rows(path, k, data[k]) for k in ("observations", "next_observations", "actions", "rewards")}
    if any(len(a) != size for a in arrays.values()):
        raise DatasetError(f"{path}: array lengths {[len(a) for a in arrays.values()]} differ from memory_size {size}")
    # Circular buffer: once it has wrapped, the oldest row is at `pointer`.
    order = np.roll(np.arange(size), -pointer) if count > size else np.arange(min(count, size))
    arrays = {k: a[order] for k, a in arrays.items()}
    obs, next_obs = arrays["observations"], arrays["next_observations"]
    width = obs.shape[1] if obs.ndim == 2 else None
    if width is None or width - 1 not in ERA_FPS or next_obs.shape != obs.shape:
        other = _ENV_NAME.search(path.name.removesuffix(".gz"))
        why = f" ({other.group(1)} data: shiftkit has no environment with its layout)" if other else ""
        raise DatasetError(f"{path}: observation shape {obs.shape} is neither (N, 60) nor (N, 54){why}")
    if np.any(obs[:, -1] != 0) or np.any(next_obs[:, -1] != 0):
        raise DatasetError(f"{path}: rows with the absorbing-state flag set are not supported")
    actions = arrays["actions"]
    if actions.ndim != 2 or actions.shape[1] != 4:
        raise DatasetError(f"{path}: actions have shape {actions.shape}, expected (N, 4)")
    rewards = arrays["rewards"].reshape(len(order), -1)
    for key, a in (("observations", obs), ("actions", actions), ("rewards", rewards)):
        if not np.isfinite(a).all():
            raise DatasetError(f"{path}: {key} contain NaN/inf")
    reference_name = None if task else parse_reference_name(path)
    return VpaceBuffer(
        path=path,
        sha256=hashlib.sha256(raw_bytes).hexdigest(),
        task=task or reference_name.task,
        observations=obs[:, :-1],
        next_observations=next_obs[:, :-1],
        actions=vpace_action_to_shiftkit(actions),
        rewards=rewards,
        overwritten_rows=max(count - size, 0),
        reference_name=reference_name,
    )


def _rows(path: Path, key: str, value: Any) -> np.ndarray:
    """`value` as a float32 array with one row per buffer entry; a one-line error naming the file
    and the key for anything else (ragged rows, text, objects, a scalar)."""
    if isinstance(value, np.ndarray) and value.dtype.kind not in "biuf":
        raise DatasetError(f"{path}: {key} has dtype {value.dtype}, expected numbers")
    try:
        arr = np.asarray(value, dtype=np.float32)
    except (TypeError, ValueError) as exc:
        reason = "rows of different lengths" if "inhomogeneous" in str(exc) else "not numbers"
        raise DatasetError(f"{path}: {key} is not a numeric array ({reason})") from None
    if arr.ndim == 0:
        raise DatasetError(f"{path}: {key} is a scalar, expected one row per buffer entry")
    return arr


def _panda_play():
    """The Panda play family's dataset facts, through the env registry."""
    from shiftkit.envs import env_family

    return env_family("panda-play")


def observation_features(obs_dim: int) -> Features:
    """The env's split of the reference observation (panda-play), trimmed to `obs_dim`."""
    family = _panda_play()
    state = [family.observation_names[i] for i in family.state_indices if i < obs_dim]
    env_state = [family.observation_names[i] for i in family.environment_state_indices]
    info = {"source_layout": f"VPACE/LfGP Panda play, {obs_dim} dims (see docs/panda_play.md)"}
    return {
        "observation.state": vector_feature("float32", state, **info),
        "observation.environment_state": vector_feature("float32", env_state, **info),
    }


def _split_observations(obs: np.ndarray) -> dict[str, np.ndarray]:
    family = _panda_play()
    state_idx = family.state_indices[family.state_indices < obs.shape[1]]
    return {
        "observation.state": np.ascontiguousarray(obs[:, state_idx]),
        "observation.environment_state": np.ascontiguousarray(obs[:, family.environment_state_indices]),
    }


def _reward_names(buffers: list[VpaceBuffer]) -> list[str]:
    """One `next.reward` column when every file's reward columns agree row by row (true for the
    published files: a sparse reward replicated over the generating env's tasks), else one per task."""
    if all(np.all(b.rewards == b.rewards[:, :1]) for b in buffers):
        return ["reward"]
    widths = sorted({b.rewards.shape[1] for b in buffers})
    if len(widths) != 1:
        raise DatasetError(f"reward widths differ between files ({widths}); import them into separate datasets")
    return [f"reward_{i}" for i in range(widths[0])]


@dataclass
class VpaceOptions:
    """Options of the VPACE importer (`shiftkit import vpace FILE...`)."""

    files: list[str]
    """Buffer files (all go into one dataset)."""
    kind: Kind = "auto"
    """Success-example sets or expert trajectories (default: detected)."""
    task: str | None = None
    """Task name for every file (default: from the file name, 3_lift -> lift)."""
    fps: int | None = option(None, rule="positive_int")
    """Frame rate (default: 20 for 60-column files, 5 for 54)."""


class VpaceSource:
    """The buffers of `files` as one pipeline source (one group per file): example rows become one-frame
    episodes, trajectories are split into episodes."""

    def __init__(self, options: VpaceOptions) -> None:
        if not options.files:
            raise DatasetError("no input files given")
        self.inputs = [Path(f) for f in options.files]
        buffers = self.buffers = [read_vpace_buffer(f, options.task) for f in options.files]
        dims = sorted({b.obs_dim for b in buffers})
        if len(dims) != 1:
            raise DatasetError(
                f"files mix observation widths {dims} (LfGP-era and VPACE-era data); import them separately"
            )
        kinds = sorted({b.kind() for b in buffers}) if options.kind == "auto" else [options.kind]
        if len(kinds) != 1:
            raise DatasetError("files mix example sets and trajectories; import them separately or give --kind")
        self.kind, self.obs_dim = kinds[0], dims[0]
        self.fps = options.fps or ERA_FPS[self.obs_dim]
        self.robot_type = _panda_play().robot
        self.features = observation_features(self.obs_dim)
        self.reward_names: list[str] = []
        if self.kind == "trajectories":
            self.reward_names = _reward_names(buffers)
            self.features["action"] = vector_feature("float32", list(_panda_play().action_names))
            self.features["next.reward"] = vector_feature("float32", self.reward_names)
        self.bounds = [
            [(r, r + 1) for r in range(len(b.observations))] if self.kind == "examples" else b.episode_bounds()
            for b in buffers
        ]
        self._episodes = [(f, e) for f, bounds in enumerate(self.bounds) for e in range(len(bounds))]
        self.num_episodes = len(self._episodes)

    def episode_groups(self) -> list[list[int]]:
        """The episodes of each file."""
        return groups_by_file([f for f, _ in self._episodes])

    def iter_episodes(self, indices: list[int]) -> Iterator[Episode]:
        """The episodes at `indices`, in that order."""
        for i in indices:
            f, e = self._episodes[i]
            b = self.buffers[f]
            start, end = self.bounds[f][e]
            n = end - start
            frames = {k: v[start:end] for k, v in _split_observations(b.observations).items()}
            frames["timestamp"] = np.arange(n, dtype=np.float64) / self.fps
            frames["task"] = np.array([b.task] * n)
            source: dict[str, Any] = {"file": b.path.name, "rows": [start, end]}
            if self.kind == "trajectories":
                frames["action"] = b.actions[start:end]
                rewards = b.rewards[start:end]
                frames["next.reward"] = np.ascontiguousarray(rewards[:, :1] if len(self.reward_names) == 1 else rewards)
                # The wrapped buffer dropped the oldest rows: the first episode may lack its start.
                source["start_overwritten"] = bool(e == 0 and b.overwritten_rows > 0)
            yield Episode(frames, {"task": b.task, "source": source, "source_episode_index": i})

    def describe(self) -> dict[str, Any]:
        """The provenance entry: every file (sha256, task, rows, episode lengths) and the import's settings."""
        return {
            "kind": "vpace",
            "files": [
                {
                    "path": str(b.path.resolve()),
                    "sha256": b.sha256,
                    "task": b.task,
                    "rows": len(b.observations),
                    "overwritten_rows": b.overwritten_rows,
                    "lengths": [end - start for start, end in bounds],
                    **({"file_name": asdict(b.reference_name)} if b.reference_name else {}),
                }
                for b, bounds in zip(self.buffers, self.bounds, strict=True)
            ],
            "importer": {
                "name": "vpace",
                "kind": self.kind,
                "fps": self.fps,
                "observation_dims": self.obs_dim,
                "dropped": "absorbing-state flag (last observation column)",
                "gripper": "negated: published > 0 closes, shiftkit > 0 opens",
            },
        }


def _report(source: dict[str, Any]) -> list[str]:
    lines = []
    for f in source["files"]:
        lengths = f["lengths"]
        detail = (
            f"{f['rows']} examples"
            if source["importer"]["kind"] == "examples"
            else f"{f['rows']} transitions in {len(lengths)} episodes (lengths {lengths})"
        )
        lines.append(f"{Path(f['path']).name}: task {f['task']!r}, {detail}")
    return lines


IMPORTER = register_importer(
    Importer(
        name="vpace",
        help="the VPACE/LfGP authors' published expert buffers (gzipped pickles)",
        Options=VpaceOptions,
        inputs=("files",),
        open=VpaceSource,
        report=_report,
    )
)
