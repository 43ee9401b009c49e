"""Roll out a trained policy in a registered environment: success rate with a Wilson 95% interval,
per-episode results (JSON) and optional videos. Shared by every trainer.

A policy is any object with
* `features`: the dataset features it consumes, `{key: {"dtype", "shape", "names"}}`,
* `act(obs: dict[str, np.ndarray]) -> np.ndarray`: one unbatched observation -> one action, and
  optionally `reset()`, called before every episode (for policies with memory).
`ObservationMap` builds that observation from the environment: numeric features by their
per-dimension `names` looked up in `env.observation_names` (so any split of the env's vector into
`observation.state` / `observation.environment_state` works), cameras `observation.images.<cam>`
from `env.render_rgb(cam)` and `observation.depth.<cam>` from `env.render_depth(cam)`.
Episode `i` is reset with seed `seed + i`; it counts as a success once `info["is_success"]` holds.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from importlib import import_module
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from shiftkit.pipelines.depth import DEPTH_PREFIX, encode_depth
from shiftkit.pipelines.errors import ConfigError, DatasetError, ShiftkitError

# trainer name (config.json / checkpoint) -> module with `load_policy(path, device)`
POLICY_LOADERS = {"bc": "shiftkit.policies.bc", "vpace": "shiftkit.policies.vpace", "lfgp": "shiftkit.policies.vpace"}


class Policy(Protocol):
    features: dict[str, dict]

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray: ...


def wilson_interval(successes: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (95% for the default z)."""
    if n == 0:
        return (0.0, 1.0)
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return (max(0.0, centre - half), min(1.0, centre + half))


def camera_size(features: dict[str, dict]) -> tuple[int, int] | None:
    """(height, width) the env must render the policy's cameras at, or None without cameras."""
    sizes = {
        tuple(ft["shape"][:2])
        for k, ft in features.items()
        if k.startswith(("observation.images.", "observation.depth."))
    }
    if len(sizes) > 1:
        raise ConfigError(f"policy cameras have different sizes {sorted(sizes)}; one env renders one size")
    return sizes.pop() if sizes else None


class ObservationMap:
    """Env observation -> the policy's feature dict (see the module docstring)."""

    def __init__(self, features: dict[str, dict], observation_names: list[str]) -> None:
        self.vectors: dict[str, np.ndarray] = {}
        self.cameras: dict[str, tuple[str, str]] = {}  # feature -> ("rgb" | "depth", camera)
        self.depth_images = {k for k, ft in features.items() if k.startswith(DEPTH_PREFIX) and ft["dtype"] == "image"}
        index = {name: i for i, name in enumerate(observation_names)}
        for key, ft in features.items():
            if key.startswith("observation.images."):
                self.cameras[key] = ("rgb", key.removeprefix("observation.images."))
            elif key.startswith("observation.depth."):
                self.cameras[key] = ("depth", key.removeprefix("observation.depth."))
            else:
                names = ft.get("names")
                if isinstance(names, dict):  # lerobot's older {"motors": [...]} form
                    names = next(iter(names.values()))
                missing = [n for n in names or [None] if n not in index]
                if missing:
                    raise ConfigError(
                        f"policy input {key!r} needs observation {missing[0]!r}, which the env does not provide"
                    )
                self.vectors[key] = np.asarray([index[n] for n in names])

    def __call__(self, env: Any, obs: np.ndarray) -> dict[str, np.ndarray]:
        out = {key: np.asarray(obs, dtype=np.float32)[idx] for key, idx in self.vectors.items()}
        for key, (kind, cam) in self.cameras.items():
            if kind == "rgb":
                out[key] = env.render_rgb(cam)
            elif key in self.depth_images:  # the dataset's grey-level encoding (pipelines.depth)
                out[key] = encode_depth(env.render_depth(cam))
            else:  # float (H, W, 1) metres: datasets written before the encoding
                out[key] = env.render_depth(cam)[..., None].astype(np.float32)
        return out


@dataclass
class EpisodeResult:
    """One evaluation episode."""

    episode: int
    seed: int
    success: bool
    steps: int
    """Steps run (the episode stops at the first success)."""
    reward: float
    video: str | None = None


@dataclass
class EvalReport:
    """All episodes of one evaluation and their summary."""

    env: str
    task: str
    policy: str
    seed: int
    episodes: list[EpisodeResult] = field(default_factory=list)

    @property
    def successes(self) -> int:
        return sum(e.success for e in self.episodes)

    @property
    def success_rate(self) -> float:
        return self.successes / len(self.episodes) if self.episodes else 0.0

    def summary(self) -> dict[str, Any]:
        lo, hi = wilson_interval(self.successes, len(self.episodes))
        return {
            "env": self.env,
            "task": self.task,
            "policy": self.policy,
            "seed": self.seed,
            "episodes": len(self.episodes),
            "successes": self.successes,
            "success_rate": self.success_rate,
            "ci95": [lo, hi],
            "ci_method": "wilson",
        }

    def to_json(self) -> str:
        return json.dumps({**self.summary(), "results": [asdict(e) for e in self.episodes]}, indent=2) + "\n"


def load_policy(path: str | Path, device: str = "cpu") -> Policy:
    """A trained policy from a run folder or checkpoint file, whichever trainer made it."""
    from shiftkit.policies.run_dir import RunDir, run_folder, torch_device

    path = Path(path)
    if not path.exists():
        raise DatasetError(f"policy not found: {path}")
    config = RunDir(run_folder(path), resume=True).read_config()
    if config is None:
        raise DatasetError(f"{path} is not a shiftkit run (no {run_folder(path) / 'config.json'})")
    torch_device(device)  # an unknown or absent device fails here, in one line
    trainer = config.get("trainer")
    if trainer not in POLICY_LOADERS:
        raise DatasetError(f"{run_folder(path) / 'config.json'}: unknown trainer {trainer!r}")
    try:
        module = import_module(POLICY_LOADERS[trainer])
    except ModuleNotFoundError as exc:
        raise ShiftkitError(f"policies of trainer {trainer!r} cannot be loaded in this install ({exc})") from exc
    return module.load_policy(path, device=device)


def _write_video(path: Path, frames: list[np.ndarray], fps: int) -> None:
    import av

    h, w = frames[0].shape[:2]
    with av.open(str(path), mode="w") as container:
        stream = container.add_stream("libx264", rate=fps)
        stream.width, stream.height = w - w % 2, h - h % 2  # yuv420p needs even sizes
        stream.pix_fmt = "yuv420p"
        for frame in frames:
            image = av.VideoFrame.from_ndarray(np.ascontiguousarray(frame[: stream.height, : stream.width]), "rgb24")
            container.mux(stream.encode(image))
        container.mux(stream.encode())


def run_episodes(
    policy: Policy,
    env: Any,
    episodes: int,
    seed: int,
    video_dir: str | Path | None = None,
    on_episode: Callable[[EpisodeResult], None] | None = None,
) -> list[EpisodeResult]:
    """Run `episodes` episodes of `policy` in `env` (reset with seeds `seed`, `seed + 1`, ...); each
    stops at its first success or when the env ends it."""
    obs_map = ObservationMap(policy.features, list(env.observation_names))
    videos = Path(video_dir) if video_dir is not None else None
    if videos is not None:
        videos.mkdir(parents=True, exist_ok=True)
    results = []
    for i in range(episodes):
        obs, info = env.reset(seed=seed + i)
        if hasattr(policy, "reset"):
            policy.reset()
        frames = [env.render_rgb()] if videos is not None else []
        steps, reward, success = 0, 0.0, bool(info.get("is_success", False))
        done = success
        while not done:
            action = np.asarray(policy.act(obs_map(env, obs)), dtype=np.float32)
            if not np.all(np.isfinite(action)):
                raise ShiftkitError(f"policy produced a non-finite action {action} (episode {i}, step {steps})")
            obs, r, terminated, truncated, info = env.step(action)
            steps, reward = steps + 1, reward + float(r)
            success = bool(info.get("is_success", False))
            done = success or terminated or truncated
            if videos is not None:
                frames.append(env.render_rgb())
        result = EpisodeResult(episode=i, seed=seed + i, success=success, steps=steps, reward=reward)
        if videos is not None:
            result.video = str(videos / f"episode_{i:04d}.mp4")
            _write_video(Path(result.video), frames, int(env.metadata.get("render_fps", 20)))
        results.append(result)
        if on_episode is not None:
            on_episode(result)
    return results


def evaluate(
    policy: Policy,
    env_name: str,
    task: str,
    episodes: int,
    seed: int,
    video_dir: str | Path | None = None,
    policy_name: str = "",
    env_kwargs: dict[str, Any] | None = None,
    on_episode: Callable[[EpisodeResult], None] | None = None,
) -> EvalReport:
    """Build the registered env `env_name`/`task` (rendering at the policy's image size) and run
    `run_episodes` in it."""
    from shiftkit.envs import make

    if episodes < 1:
        raise ConfigError(f"--episodes must be >= 1, got {episodes}")
    kwargs = dict(env_kwargs or {})
    size = camera_size(policy.features)
    if size is not None:
        kwargs.update(height=size[0], width=size[1])
    try:
        env = make(env_name, task, **kwargs)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    try:
        report = EvalReport(env=env_name, task=task, policy=policy_name, seed=seed)
        report.episodes = run_episodes(policy, env, episodes, seed, video_dir, on_episode)
        return report
    finally:
        env.close()


def record_evaluation(report: EvalReport, policy_path: str | Path, out: str | Path | None = None) -> Path:
    """Write the per-episode results JSON (default: `<run>/eval/<env>-<task>-seed<S>.json`, with
    `-<checkpoint name>` added for a checkpoint file such as best.pt) and, when it lands in the policy's
    run folder, add the result to the run's model card."""
    from shiftkit.policies.run_dir import EVAL, RunDir, checkpoint_name, run_folder

    run_dir = run_folder(policy_path)
    checkpoint = checkpoint_name(policy_path)
    name = f"{report.env}-{report.task}-seed{report.seed}{f'-{Path(checkpoint).stem}' if checkpoint else ''}.json"
    target = Path(out) if out else run_dir / EVAL / name
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_text(report.to_json())
    if target.parent.resolve() == (run_dir / EVAL).resolve():
        RunDir(run_dir, resume=True).refresh_model_card()
    return target
