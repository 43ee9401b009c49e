"""Success examples per task (B*_T), their loaders and training-time augmentation.

Examples are states where a task is complete (VPACE); for LfGP they are full expert trajectories with
actions (and each segment's next states, for the expert transitions LfGP mixes into its batches). Loaders read them from LeRobot datasets (`observation.state` [+ `observation.environment_state`],
`task` naming the task of each frame); the thesis authors' published expert buffers become such
datasets with `shiftkit import vpace`.

Augmentation (thesis B.2.6): Gaussian noise per observation dimension, scaled by that dimension's
standard deviation within the task's example set times `aug_factor` (0.1), so dimensions that never
vary (std 0) stay exact.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shiftkit.datasets.dataset import Dataset
from shiftkit.datasets.errors import DatasetError
from shiftkit.policies.data import example_set_origin, numeric_column, open_datasets, refuse_example_sets

STATE_KEYS = ("observation.state", "observation.environment_state")


@dataclass
class TaskExamples:
    """One task's expert data: example states and, for full trajectories, actions, next states and which
    rows end a demonstration."""

    obs: np.ndarray  # (N, obs_dim) float32
    act: np.ndarray | None = None  # (N, act_dim) float32, expert actions (full trajectories only)
    next_obs: np.ndarray | None = None  # (N, obs_dim) the next state (a segment's last row: itself); None: obs
    final: np.ndarray | None = None  # (N,) bool, a segment's last row or its (s_T, 0) pair; None: no row is


@dataclass
class ExampleRows:
    """Each task's own example rows of one update (numpy, float32)."""

    obs: np.ndarray  # (T, n, obs_dim)
    act: np.ndarray | None  # (T, n, act_dim), full trajectories only
    weight: np.ndarray  # (T, n) 1 for the rows a task counts, 0 for padding (tasks get unequal shares)


def _column_order(dataset, keys: list[str], observation_names: list[str] | None, ref: str) -> np.ndarray | None:
    """Columns of the concatenated state features in the env's observation order (by dimension
    name): datasets split the observation into robot and object state, the env observes one vector."""
    if observation_names is None:
        return None
    names = [n for k in keys for n in (dataset.features[k].get("names") or [])]
    if sorted(names) != sorted(observation_names):
        missing = sorted(set(observation_names) - set(names))[:3]
        raise DatasetError(
            f"example dataset {ref!r}: state dimensions do not match the env observation (e.g. missing {missing})"
        )
    index = {n: i for i, n in enumerate(names)}
    return np.asarray([index[n] for n in observation_names])


def check_example_set(ref: str, root: Path, dataset) -> None:
    """Refuse to take every frame of a trajectory dataset as a success example: an example set is
    made by the `success_examples` stage, imported as one (`import vpace`, kind examples), or holds
    states only (no `action`)."""
    if "action" not in dataset.features or example_set_origin(root) is not None:
        return
    raise DatasetError(
        f"{ref} holds trajectories ({dataset.meta.total_episodes} episodes with actions), not a success-example set: "
        "make one with the success_examples stage, or pass --frames-as-examples to use all its frames"
    )


def load_dataset_examples(
    refs: list[str],
    tasks: list[str],
    with_actions: bool = False,
    observation_names: list[str] | None = None,
    require_example_set: bool = False,
) -> tuple[dict[str, TaskExamples], list[Dataset]]:
    """Collect each task's frames from LeRobot datasets, keyed by the frame's `task` string.

    With `with_actions` (LfGP), frames keep their actions and next states, and every task segment's
    (each run of consecutive frames of the task in an episode) final state is added once more with a
    zero action, the `(s_T, 0)` pair that marks the end of a demonstration; a segment's last frame and
    that pair transition to themselves and are marked `final`. Given the env's `observation_names`,
    state columns are put in that order by their dimension names. With `require_example_set`, each
    dataset must be an example set (`check_example_set`).
    """
    parts: dict[str, list[TaskExamples]] = {t: [] for t in tasks}
    opened = open_datasets(refs)
    for ref, (resolved, dataset) in zip(refs, opened, strict=True):
        if require_example_set:
            check_example_set(ref, resolved.root, dataset)
        keys = [k for k in STATE_KEYS if k in dataset.features]
        if "observation.state" not in keys:
            raise DatasetError(f"example dataset {ref!r} has no 'observation.state' feature")
        if with_actions:
            refuse_example_sets([(resolved, dataset)], "LfGP")
        if with_actions and "action" not in dataset.features:
            raise DatasetError(f"example dataset {ref!r} has no 'action' feature (LfGP needs full trajectories)")
        obs = np.concatenate([numeric_column(dataset, k).reshape(len(dataset), -1) for k in keys], axis=1)
        order = _column_order(dataset, keys, observation_names, ref)
        if order is not None:
            obs = obs[:, order]
        table = dataset.hf_dataset.with_format("numpy", columns=["task_index", "episode_index"])[:]
        task_index, episode = table["task_index"].reshape(-1), table["episode_index"].reshape(-1)
        act = numeric_column(dataset, "action") if with_actions else None
        for task, row in dataset.meta.tasks.iterrows():
            if task not in parts:
                continue
            mask = task_index == int(row["task_index"])
            if act is None:
                parts[task].append(TaskExamples(obs[mask]))
                continue
            # A frame continues its segment when the next frame is of the same task and episode.
            continues = np.append(mask[1:] & (episode[1:] == episode[:-1]), False)
            rows, ends = np.flatnonzero(mask), np.flatnonzero(mask & ~continues)
            nxt = np.where(continues[rows], rows + 1, rows)
            parts[task].append(TaskExamples(obs[rows], act[rows], obs[nxt], ~continues[rows]))
            parts[task].append(TaskExamples(obs[ends], np.zeros_like(act[ends]), obs[ends], np.ones(len(ends), bool)))
    examples = {}
    for task in tasks:
        got = parts[task]
        if sum(len(p.obs) for p in got) == 0:
            raise DatasetError(f"no examples for task {task!r} in {', '.join(refs)}")
        fields = [
            np.concatenate([getattr(p, f) for p in got]) if with_actions else None for f in ("act", "next_obs", "final")
        ]
        examples[task] = TaskExamples(np.concatenate([p.obs for p in got]), *fields)
    return examples, [resolved for resolved, _ in opened]


class ExampleBuffer:
    """Example sets of all tasks of a run, sampled as (num_tasks, rows, ·) blocks or as transitions."""

    def __init__(
        self,
        examples: dict[str, TaskExamples],
        tasks: list[str],
        aug_factor: float = 0.1,
        max_per_task: int | None = None,
    ):
        self.tasks = tasks
        self.aug_factor = aug_factor
        sets = [examples[t] for t in tasks]
        self.obs = [e.obs[:max_per_task] for e in sets]
        self.act = [None if e.act is None else e.act[:max_per_task] for e in sets]
        self.next_obs = [
            o if e.next_obs is None else e.next_obs[:max_per_task] for o, e in zip(self.obs, sets, strict=True)
        ]
        self.final = [
            np.zeros(len(o), bool) if e.final is None else e.final[:max_per_task]
            for o, e in zip(self.obs, sets, strict=True)
        ]
        # Exactly 0 where a dimension never varies (float rounding could leave a tiny std otherwise).
        self.std = [np.where(np.ptp(o, axis=0) == 0, 0.0, o.std(axis=0)).astype(np.float32) for o in self.obs]
        dims = {o.shape[1] for o in self.obs}
        if len(dims) != 1:
            raise DatasetError(f"example observation widths differ between tasks: {sorted(dims)}")
        self.obs_dim = dims.pop()

    def sizes(self) -> dict[str, int]:
        """Examples held per task."""
        return {t: len(o) for t, o in zip(self.tasks, self.obs, strict=True)}

    def split(self, rows: int) -> np.ndarray:
        """How `rows` expert rows of one batch divide among the tasks, as the reference code's
        `fraction` mode does: rows // T each, the main task (index 0) the remainder."""
        counts = np.full(len(self.tasks), rows // len(self.tasks))
        counts[0] = rows - counts[1:].sum()
        return counts

    def _augmented(self, rng: np.random.Generator, task: int, idx: np.ndarray) -> np.ndarray:
        o = self.obs[task]
        noise = rng.standard_normal((len(idx), o.shape[1]), np.float32) * (self.aug_factor * self.std[task])
        return (o[idx] + noise).astype(np.float32)

    def sample(self, rng: np.random.Generator, rows: int) -> ExampleRows:
        """`rows` augmented example rows divided among the tasks (`split`), each task's block padded to
        the largest share (padding weighs 0)."""
        counts = self.split(rows)
        width = int(counts.max())
        obs, act = [], []
        for t, (o, a) in enumerate(zip(self.obs, self.act, strict=True)):
            idx = rng.integers(0, len(o), width)
            obs.append(self._augmented(rng, t, idx))
            if a is not None:
                act.append(a[idx])
        weight = (np.arange(width) < counts[:, None]).astype(np.float32)
        return ExampleRows(np.stack(obs), np.stack(act) if act else None, weight)

    def sample_discriminator(self, rng: np.random.Generator, rows: int, final_bias: float = 0.0) -> ExampleRows:
        """`rows` augmented rows per task for a discriminator; a `final_bias` share of them (rounded down)
        from the rows that end a demonstration (thesis Table A.2's (s_T, 0) sampling bias), where a
        task has any."""
        obs, act = [], []
        for t, (o, a, final) in enumerate(zip(self.obs, self.act, self.final, strict=True)):
            ends, others = np.flatnonzero(final), np.flatnonzero(~final)
            n_ends = int(final_bias * rows) if len(ends) and len(others) else 0
            idx = (
                np.concatenate(
                    [others[rng.integers(0, len(others), rows - n_ends)], ends[rng.integers(0, len(ends), n_ends)]]
                )
                if n_ends
                else rng.integers(0, len(o), rows)
            )
            obs.append(self._augmented(rng, t, idx))
            if a is not None:
                act.append(a[idx])
        return ExampleRows(np.stack(obs), np.stack(act) if act else None, np.ones((len(obs), rows), np.float32))

    def sample_transitions(self, rng: np.random.Generator, rows: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`rows` expert transitions (obs, act, next_obs), each (rows, ·), divided among the tasks
        (`split`), for batches that mix expert data into replay rows (LfGP; not augmented)."""
        picks = [(t, rng.integers(0, len(self.obs[t]), n)) for t, n in enumerate(self.split(rows))]
        return tuple(
            np.concatenate([arrays[t][idx] for t, idx in picks]).astype(np.float32)
            for arrays in (self.obs, self.act, self.next_obs)
        )  # type: ignore[return-value]
