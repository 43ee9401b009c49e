"""Roll out a trained policy in a registered environment: success rate with a Wilson 95% interval,
per-episode results (JSON) and optional videos. Shared by every trainer.

A policy is any object with
* `features`: the dataset features it consumes, `{key: {"dtype", "shape", "names"}}`,
* `act(obs: dict[str, np.ndarray]) -> np.ndarray`: one unbatched observation -> one action, and
  optionally `reset()`, called before every episode (for policies with memory), and
  `action_names`, the names of its action's dims (a BC policy's are its dataset's).
The policy's action must be the env's: when both name their dims (`env.action_names`) the names
must be identical, else the dims must at least match in number (a one-line ConfigError, not a shape
error from inside the env).
`ObservationMap` builds that observation from the environment: numeric features by their
per-dimension `names` looked up in `env.observation_names` (so any split of the env's vector into
`observation.state` / `observation.environment_state` works), cameras `observation.images.<cam>`
from `env.render_rgb(cam)` and `observation.depth.<cam>` from `env.render_depth(cam)`.
Episode `i` is reset with seed `seed + i`; it counts as a success once `info["is_success"]` holds.
An env with `episode_extras()` (e.g. door-tactile: the STS modes the policy drove) adds that dict to
each episode's result.
`yaw_sweep` evaluates a multiview policy per base-yaw bin (docs/multiview.md: 12 bins [-0.8, -0.7] ...
[0.3, 0.4] rad) and `write_yaw_sweep` saves its JSON and a PNG of success per bin.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from shiftkit.datasets.depth import clean_metres, is_legacy_depth, legacy_grey
from shiftkit.datasets.errors import ConfigError, DatasetError, ShiftkitError


class Policy(Protocol):
    """What `shiftkit eval` runs: a policy with its input `features` (name -> LeRobot feature) and `act`."""

    features: dict[str, dict]

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """The action (act_dim,) for one observation dict (feature name -> array, no batch dim)."""


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


def dim_names(names: Any) -> list[str] | None:
    """A feature's per-dimension names as a list (lerobot's older `{"motors": [...]}` form unwrapped)."""
    if isinstance(names, dict):
        names = next(iter(names.values()), None)
    return None if names is None else list(names)


def check_action(policy: Policy, env: Any) -> None:
    """The policy's action dims must be the env's, by name when both name them (ConfigError)."""
    ours, theirs = dim_names(getattr(policy, "action_names", None)), getattr(env, "action_names", None)
    if ours is not None and theirs is not None and ours != list(theirs):
        raise ConfigError(
            f"the policy's action {ours} is not the env's action {list(theirs)} "
            "(an --env-kwarg may select another action, e.g. door-tactile sensor_mode=visual for one without sts_mode)"
        )


class ObservationMap:
    """Env observation -> the policy's feature dict (see the module docstring)."""

    def __init__(self, features: dict[str, dict], observation_names: list[str]) -> None:
        self.vectors: dict[str, np.ndarray] = {}
        self.cameras: dict[str, tuple[str, str]] = {}  # feature -> ("rgb" | "depth", camera)
        self.grey_depth = {k for k, ft in features.items() if is_legacy_depth(k, ft) and ft["dtype"] == "image"}
        index = {name: i for i, name in enumerate(observation_names)}
        for key, ft in features.items():
            if key.startswith("observation.images."):
                self.cameras[key] = ("rgb", key.removeprefix("observation.images."))
            elif key.startswith("observation.depth."):
                self.cameras[key] = ("depth", key.removeprefix("observation.depth."))
            else:
                names = dim_names(ft.get("names"))
                missing = [n for n in names or [None] if n not in index]
                if missing:
                    raise ConfigError(
                        f"policy input {key!r} needs observation {missing[0]!r}, which the env does not provide"
                    )
                self.vectors[key] = np.asarray([index[n] for n in names])

    def __call__(self, env: Any, obs: np.ndarray) -> dict[str, np.ndarray]:
        """The policy's observation dict for the env's flat observation `obs`, cameras rendered from `env`."""
        out = {key: np.asarray(obs, dtype=np.float32)[idx] for key, idx in self.vectors.items()}
        for key, (kind, cam) in self.cameras.items():
            if kind == "rgb":
                out[key] = env.render_rgb(cam)
            elif key in self.grey_depth:  # trained on older shiftkit data: its 8-bit grey levels
                out[key] = legacy_grey(env.render_depth(cam))
            else:  # (H, W, 1) metres, as the dataset reader gives depth (datasets.depth)
                out[key] = clean_metres(env.render_depth(cam))
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
    extras: dict[str, Any] | None = None
    """What the env reports about the episode besides success (`env.episode_extras()`), e.g.
    door-tactile's `tactile_steps` and `first_tactile_step`; None for envs without it."""


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
        """Episodes that succeeded."""
        return sum(e.success for e in self.episodes)

    @property
    def success_rate(self) -> float:
        """Fraction of episodes that succeeded (0 with no episodes)."""
        return self.successes / len(self.episodes) if self.episodes else 0.0

    def summary(self) -> dict[str, Any]:
        """Env, task, counts, success rate and its 95% Wilson interval, as a JSON-ready dict."""
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
        """The summary plus every episode's result, as indented JSON."""
        return json.dumps({**self.summary(), "results": [asdict(e) for e in self.episodes]}, indent=2) + "\n"


def load_policy(path: str | Path, device: str = "cpu") -> Policy:
    """A trained policy from a run folder or checkpoint file, whichever trainer made it."""
    from shiftkit.policies.run_dir import RunDir, run_folder, torch_device
    from shiftkit.policies.trainers import TRAINERS

    path = Path(path)
    if not path.exists():
        raise DatasetError(f"policy not found: {path}")
    config = RunDir(run_folder(path), resume=True).read_config()
    if config is None:
        raise DatasetError(f"{path} is not a shiftkit run (no {run_folder(path) / 'config.json'})")
    torch_device(device)  # an unknown or absent device fails here, in one line
    name = config.get("trainer")
    if name not in TRAINERS:  # the trainer that made the run loads its policies
        raise DatasetError(f"{run_folder(path) / 'config.json'}: unknown trainer {name!r}")
    try:
        loader = TRAINERS.get(name).policy_loader()
    except ModuleNotFoundError as exc:
        raise ShiftkitError(f"policies of trainer {name!r} cannot be loaded in this install ({exc})") from exc
    return loader(path, device=device)


def policy_rate(path: str | Path) -> int | None:
    """The control rate (Hz) a trained policy acts at: its datasets' fps (BC, FIRE), or for RL
    trainers the rate of the env it trained in; None when the run does not say."""
    from shiftkit.datasets.dataset import as_dataset
    from shiftkit.envs import env_family
    from shiftkit.policies.run_dir import RunDir, run_folder

    config = RunDir(run_folder(path), resume=True).read_config() or {"datasets": [], "args": {}}
    rates = set()
    for record in config["datasets"]:
        fps = record.get("fps")
        info = Path(record.get("root") or "") / "meta" / "info.json"
        if fps is None and record.get("root") and info.is_file():  # a run recorded before fps was
            fps = as_dataset(record["root"]).info["fps"]
        if fps is not None:
            rates.add(fps)
    if config.get("trainer") in ("vpace", "lfgp"):
        kwargs = config["args"].get("env_kwargs")
        kwargs = kwargs if isinstance(kwargs, dict) else {}
        try:
            rates = {int(kwargs.get("control_hz") or env_family(str(config.get("env"))).control_rates[0])}
        except (ValueError, TypeError):  # trained in an env shiftkit does not register
            return None
    if len(rates) > 1:
        raise DatasetError(f"{path} was trained on datasets of different fps {sorted(rates)}")
    return rates.pop() if rates else None


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
    reset_options: Callable[[int], dict[str, Any]] | None = None,
) -> list[EpisodeResult]:
    """Run `episodes` episodes of `policy` in `env` (reset with seeds `seed`, `seed + 1`, ... and
    `reset_options(i)` if given); each stops at its first success or when the env ends it."""
    obs_map = ObservationMap(policy.features, list(env.observation_names))
    check_action(policy, env)
    videos = Path(video_dir) if video_dir is not None else None
    if videos is not None:
        videos.mkdir(parents=True, exist_ok=True)
    results = []
    for i in range(episodes):
        obs, info = env.reset(seed=seed + i, options=reset_options(i) if reset_options else None)
        if hasattr(policy, "reset"):
            policy.reset()
        frames = [env.render_rgb()] if videos is not None else []
        steps, reward, success = 0, 0.0, bool(info.get("is_success", False))
        done = success
        while not done:
            action = np.asarray(policy.act(obs_map(env, obs)), dtype=np.float32)
            if action.shape != env.action_space.shape:
                raise ConfigError(f"the policy outputs {action.shape} actions, the env takes {env.action_space.shape}")
            if not np.all(np.isfinite(action)):
                raise ShiftkitError(f"policy produced a non-finite action {action} (episode {i}, step {steps})")
            obs, r, terminated, truncated, info = env.step(action)
            steps, reward = steps + 1, reward + float(r)
            success = bool(info.get("is_success", False))
            done = success or terminated or truncated
            if videos is not None:
                frames.append(env.render_rgb())
        result = EpisodeResult(episode=i, seed=seed + i, success=success, steps=steps, reward=reward)
        if hasattr(env, "episode_extras"):
            result.extras = env.episode_extras()
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
    rate: int | None = None,
) -> EvalReport:
    """Build the registered env `env_name`/`task` (rendering at the policy's image size, controlled at
    the policy's `rate` when given: see `_make_env`) and run `run_episodes` in it."""
    if episodes < 1:
        raise ConfigError(f"--episodes must be >= 1, got {episodes}")
    env = _make_env(policy, env_name, task, env_kwargs, rate)
    try:
        report = EvalReport(env=env_name, task=task, policy=policy_name, seed=seed)
        report.episodes = run_episodes(policy, env, episodes, seed, video_dir, on_episode)
        return report
    finally:
        env.close()


def _make_env(
    policy: Policy, env_name: str, task: str, env_kwargs: dict[str, Any] | None, rate: int | None = None
) -> Any:
    """The env, rendering at the policy's image size and, for a policy of known `rate`, stepping at that
    rate: a policy run at another rate than its data's acts on the wrong time scale (ConfigError
    naming both rates when the env cannot run at it)."""
    from shiftkit.envs import env_family, make

    kwargs = dict(env_kwargs or {})
    size = camera_size(policy.features)
    if size is not None:
        kwargs.update(height=size[0], width=size[1])
    try:
        rates = env_family(env_name).control_rates
        if rate is not None and "control_hz" not in kwargs and rate in rates and rate != rates[0]:
            kwargs["control_hz"] = rate
        env = make(env_name, task, **kwargs)
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"{env_name}/{task}: {exc}") from None
    env_rate = round(getattr(env, "control_hz", rates[0]))
    if rate is not None and env_rate != rate:
        env.close()
        offered = ", ".join(str(r) for r in sorted(rates))
        raise ConfigError(
            f"the policy's data is at {rate} fps but {env_name} would run at {env_rate} Hz "
            f"({env_name} offers {offered} Hz): evaluate at the data's rate or retrain at one the env offers"
        )
    return env


YAW_BINS: tuple[tuple[float, float], ...] = tuple(
    (round(-0.8 + 0.1 * k, 1), round(-0.7 + 0.1 * k, 1)) for k in range(12)
)
"""The out-of-distribution sweep (thesis ch. 3, docs/multiview.md) for policies trained on base yaw U[-0.6, 0.2]."""


def yaw_sweep(
    policy: Policy,
    env_name: str,
    task: str,
    episodes_per_bin: int,
    seed: int,
    bins: tuple[tuple[float, float], ...] = YAW_BINS,
    policy_name: str = "",
    env_kwargs: dict[str, Any] | None = None,
    on_bin: Callable[[dict[str, Any]], None] | None = None,
    rate: int | None = None,
) -> dict[str, Any]:
    """Success per base-yaw bin: in every bin, episodes with seeds `seed + i` (the same object resets
    in every bin) at an aimed base pose with yaw uniform in the bin (env reset option `base_yaw`)."""
    if episodes_per_bin < 1:
        raise ConfigError(f"--episodes must be >= 1, got {episodes_per_bin}")
    env = _make_env(policy, env_name, task, env_kwargs, rate)
    try:
        if not hasattr(env, "base_pose"):
            raise ConfigError(f"{env_name} has no mobile base: a yaw sweep needs a multiview env (mv-*)")
        rows = []
        for b, (lo, hi) in enumerate(bins):
            yaws = np.random.default_rng([seed, b]).uniform(lo, hi, episodes_per_bin)
            results = run_episodes(
                policy, env, episodes_per_bin, seed, reset_options=lambda i, yaws=yaws: {"base_yaw": float(yaws[i])}
            )
            successes = sum(r.success for r in results)
            row = {
                "yaw": [lo, hi],
                "episodes": episodes_per_bin,
                "successes": successes,
                "success_rate": successes / episodes_per_bin,
                "ci95": list(wilson_interval(successes, episodes_per_bin)),
            }
            rows.append(row)
            if on_bin is not None:
                on_bin(row)
    finally:
        env.close()
    return {
        "env": env_name,
        "task": task,
        "policy": policy_name,
        "seed": seed,
        "ci_method": "wilson",
        "bins": rows,
        "training_yaw": training_yaw(policy_name) if policy_name else None,
    }


def training_yaw(policy_path: str | Path) -> dict[str, Any] | None:
    """The base yaws a policy was trained at, from its training datasets' camera metadata
    (`meta/cameras.json` base poses): {"episodes", "low", "high"} (low == high: a fixed-view policy),
    or None when the run records no dataset with base poses."""
    from shiftkit.datasets.camera_meta import episode_cameras, read_cameras_file
    from shiftkit.datasets.dataset import as_dataset
    from shiftkit.policies.run_dir import trained_datasets

    yaws = []
    for record in trained_datasets(policy_path):
        root = Path(record.get("root") or "")
        if not record.get("root") or not (root / "meta" / "info.json").is_file():
            continue
        doc = read_cameras_file(root)
        for i in range(as_dataset(root).info.get("total_episodes", 0)):
            poses = [cam["base_pose"] for cam in episode_cameras(doc, i).values() if "base_pose" in cam]
            yaws += [float(pose["yaw"]) for pose in poses[:1]]
    if not yaws:
        return None
    return {"episodes": len(yaws), "low": min(yaws), "high": max(yaws)}


def draw_yaw_sweep(sweep: dict[str, Any]):
    """A matplotlib Figure of the sweep's success per yaw bin (Wilson 95% error bars), its training
    yaws marked (a band, a line for a fixed-view policy, else the envs' range) and named in the title."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = sweep["bins"]
    centres = [(r["yaw"][0] + r["yaw"][1]) / 2 for r in rows]
    rates = np.array([r["success_rate"] for r in rows])
    err = np.array([[r["success_rate"] - r["ci95"][0], r["ci95"][1] - r["success_rate"]] for r in rows]).T
    from shiftkit.envs.base_pose import YAW_RANGE

    fig, ax = plt.subplots(figsize=(6, 3.2))
    trained = sweep.get("training_yaw")
    kind = "policy"
    if trained is None:  # a policy whose run names no dataset with base poses: the envs' sampling range
        label = f"the envs' base-yaw range U[{YAW_RANGE[0]:g}, {YAW_RANGE[1]:g}] (training yaws not recorded)"
        ax.axvspan(*YAW_RANGE, color="0.9", zorder=0, label=label)
    elif trained["low"] == trained["high"]:
        kind = "fixed-view policy"
        label = f"trained at yaw {trained['low']:.3g} only ({trained['episodes']} episodes)"
        ax.axvline(trained["low"], color="0.5", linestyle="--", zorder=0, label=label)
    else:
        kind = "multiview policy"
        label = f"training yaws [{trained['low']:.3g}, {trained['high']:.3g}] ({trained['episodes']} episodes)"
        ax.axvspan(trained["low"], trained["high"], color="0.9", zorder=0, label=label)
    ax.bar(centres, rates, width=0.08, yerr=err, capsize=3, color="tab:blue")
    ax.set_xlabel("base yaw (rad), bin centre")
    ax.set_ylabel("success rate")
    ax.set_ylim(0, 1.05)
    ax.legend(loc="upper right", fontsize=7)
    per_bin = sorted({r["episodes"] for r in rows})
    ax.set_title(
        f"{' '.join(filter(None, (kind, Path(sweep.get('policy') or '').name)))} on {sweep['env']} / {sweep['task']}: success per base-yaw bin\n"
        f"n = {'/'.join(map(str, per_bin))} episodes per bin ({sum(r['episodes'] for r in rows)} in all), "
        f"seeds from {sweep['seed']}, Wilson 95% CI",
        fontsize=8,
    )
    fig.tight_layout()
    return fig


def write_yaw_sweep(sweep: dict[str, Any], path: str | Path) -> tuple[Path, Path]:
    """Write the sweep's JSON at `path` and a PNG of success rate (with 95% intervals) per yaw bin
    beside it; returns both paths."""
    path = Path(path)
    png = path.with_suffix(".png")
    if png == path:
        raise ConfigError(f"{path}: the sweep's JSON and PNG would be one file; give a .json path")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig = draw_yaw_sweep(sweep)
    import matplotlib.pyplot as plt

    fig.savefig(png, dpi=100)  # the figure first: a failure leaves no JSON without its PNG
    plt.close(fig)
    path.write_text(json.dumps(sweep, indent=2) + "\n")
    return path, png


def record_evaluation(report: EvalReport, policy_path: str | Path, out: str | Path | None = None) -> Path:
    """Write the per-episode results JSON (default: `<run>/eval/<env>-<task>-seed<S>.json`, with
    `-<checkpoint name>` added for a checkpoint file such as best.safetensors) and, when it lands in the policy's
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
