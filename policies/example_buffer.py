"""Success examples per task (B*_T), their loaders and training-time augmentation.

Examples are states where a task is complete (VPACE); for LfGP they are full expert trajectories with
actions. Loaders read them from LeRobot datasets (`observation.state` [+ `observation.environment_state`],
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
    """One task's expert data: example states and, for full trajectories, actions."""

    obs: np.ndarray  # (N, obs_dim) float32
    act: np.ndarray | None = None  # (N, act_dim) float32, expert actions (full trajectories only)


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

    With `with_actions` (LfGP), frames keep their actions and every episode's final state is added once
    more with a zero action, the `(s_T, 0)` pair that marks the end of a demonstration. Given the
    env's `observation_names`, state columns are put in that order by their dimension names. With
    `require_example_set`, each dataset must be an example set (`check_example_set`).
    """
    obs_parts: dict[str, list[np.ndarray]] = {t: [] for t in tasks}
    act_parts: dict[str, list[np.ndarray]] = {t: [] for t in tasks}
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
            if task not in obs_parts:
                continue
            mask = task_index == int(row["task_index"])
            obs_parts[task].append(obs[mask])
            if act is not None:
                ends = np.flatnonzero(mask & np.append(episode[1:] != episode[:-1], True))
                obs_parts[task].append(obs[ends])
                act_parts[task] += [act[mask], np.zeros_like(act[ends])]
    examples = {}
    for task in tasks:
        if not obs_parts[task] or sum(len(p) for p in obs_parts[task]) == 0:
            raise DatasetError(f"no examples for task {task!r} in {', '.join(refs)}")
        examples[task] = TaskExamples(
            np.concatenate(obs_parts[task]), np.concatenate(act_parts[task]) if with_actions else None
        )
    return examples, [resolved for resolved, _ in opened]


class ExampleBuffer:
    """Example sets of all tasks of a run, sampled as one (num_tasks, batch, ·) block."""

    def __init__(
        self,
        examples: dict[str, TaskExamples],
        tasks: list[str],
        aug_factor: float = 0.1,
        max_per_task: int | None = None,
    ):
        self.tasks = tasks
        self.aug_factor = aug_factor
        self.obs = [examples[t].obs[:max_per_task] for t in tasks]
        self.act = [None if examples[t].act is None else examples[t].act[:max_per_task] for t in tasks]
        # Exactly 0 where a dimension never varies (float rounding could leave a tiny std otherwise).
        self.std = [np.where(np.ptp(o, axis=0) == 0, 0.0, o.std(axis=0)).astype(np.float32) for o in self.obs]
        dims = {o.shape[1] for o in self.obs}
        if len(dims) != 1:
            raise DatasetError(f"example observation widths differ between tasks: {sorted(dims)}")
        self.obs_dim = dims.pop()

    def sizes(self) -> dict[str, int]:
        """Examples held per task."""
        return {t: len(o) for t, o in zip(self.tasks, self.obs, strict=True)}

    def sample(self, rng: np.random.Generator, batch_size: int) -> tuple[np.ndarray, np.ndarray | None]:
        """Augmented example states (T, B, obs_dim) and, when present, their actions (T, B, act_dim)."""
        obs, act = [], []
        for o, a, std in zip(self.obs, self.act, self.std, strict=True):
            idx = rng.integers(0, len(o), batch_size)
            obs.append(o[idx] + rng.standard_normal((batch_size, o.shape[1]), np.float32) * (self.aug_factor * std))
            if a is not None:
                act.append(a[idx])
        return np.stack(obs).astype(np.float32), (np.stack(act) if act else None)
