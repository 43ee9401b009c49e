"""`shiftkit eval`: roll out a trained policy in a registered env and report its success rate."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from typing import Any, Literal

from shiftkit.datasets.dataclass_config import option
from shiftkit.datasets.option_values import DataclassOptions

HELP = "evaluate a trained policy in a registered environment (success rate with a 95% interval)"


@dataclass(frozen=True)
class EvalArgs:
    """What `shiftkit eval` rolls out and where its results go."""

    policy: str
    """Run folder or checkpoint file of a trained policy."""
    task: str
    """Task, e.g. lift."""
    env: str = "panda-play"
    """Environment name."""
    episodes: int = option(50, rule="positive_int")
    """Number of episodes (with `yaw_sweep`: per yaw bin)."""
    seed: int = option(1000, rule="non_negative_int")
    """Episode i uses seed `seed + i`."""
    out: str | None = None
    """Per-episode results JSON; default: <run>/eval/<env>-<task>-seed<S>.json."""
    videos: str | None = None
    """Folder for one MP4 per episode; default: none."""
    control_hz: Literal[5, 20] | None = None
    """Env control rate; default: the fps of the policy's dataset (it must be that rate)."""
    device: str = "cpu"
    """Torch device for the policy."""
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    """Env constructor argument (JSON value), repeatable, e.g. view=fixed."""
    yaw_sweep: bool = False
    """Multiview envs: `episodes` per base-yaw bin over 12 bins [-0.8,-0.7]..[0.3,0.4] rad; writes JSON
    (`out`, default <run>/eval/<env>-<task>-yawsweep-seed<S>.json) and a PNG beside it."""


OPTIONS = DataclassOptions(
    EvalArgs,
    flags={"env_kwargs": "env-kwarg"},
    metavars={"out": "FILE", "videos": "DIR"},
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `eval`."""
    OPTIONS.add_to(parser)


def run(args: argparse.Namespace) -> int:
    """Roll out the policy (or sweep the camera yaw) and print the success rate; return the exit code."""
    from pathlib import Path

    from shiftkit.datasets.errors import ConfigError
    from shiftkit.policies.evaluation import (
        evaluate,
        load_policy,
        policy_rate,
        record_evaluation,
        write_yaw_sweep,
        yaw_sweep,
    )

    config = OPTIONS.build(args)
    # Output paths are checked before the rollouts, which can take minutes.
    if config.out and Path(config.out).is_dir():
        raise ConfigError(f"--out {config.out} is a folder; give the JSON file to write")
    if config.out and any(p.exists() and not p.is_dir() for p in Path(config.out).parents):
        raise ConfigError(f"--out {config.out}: a parent of it is a file, not a folder")
    if config.videos and Path(config.videos).exists() and not Path(config.videos).is_dir():
        raise ConfigError(f"--videos {config.videos} is a file; give a folder for the MP4s")
    from shiftkit.app.env_kwargs import check_env_kwargs

    check_env_kwargs(config.env, config.env_kwargs)
    if config.yaw_sweep:
        if config.videos:
            raise ConfigError("--videos is not written by --yaw-sweep; evaluate without --yaw-sweep for videos")
        if config.env_kwargs.get("view") == "fixed":
            raise ConfigError("--yaw-sweep sets the base yaw of every episode, which view=fixed would keep fixed")
        if config.out and Path(config.out).suffix.lower() == ".png":
            raise ConfigError(f"--out {config.out}: the sweep's JSON goes there and its PNG beside it; give a .json")
    from shiftkit.datasets.staging import require_writable
    from shiftkit.policies.run_dir import EVAL, run_folder

    require_writable(Path(config.out).parent if config.out else run_folder(config.policy) / EVAL, "--out")
    policy = load_policy(config.policy, device=config.device)
    rate = policy_rate(config.policy)
    _warn_if_unfinished(Path(config.policy))
    env_kwargs = {**config.env_kwargs, **({"control_hz": config.control_hz} if config.control_hz else {})}
    if config.yaw_sweep:
        sweep = yaw_sweep(
            policy,
            config.env,
            config.task,
            config.episodes,
            config.seed,
            policy_name=str(config.policy),
            env_kwargs=env_kwargs,
            rate=rate,
            on_bin=lambda r: print(f"yaw {r['yaw']}: {r['successes']}/{r['episodes']} ({r['success_rate']:.0%})"),
        )
        default = run_folder(config.policy) / EVAL / f"{config.env}-{config.task}-yawsweep-seed{config.seed}.json"
        json_path, png = write_yaw_sweep(sweep, config.out or default)
        print(f"yaw sweep written to {json_path} and {png}")
        return 0
    report = evaluate(
        policy,
        config.env,
        config.task,
        config.episodes,
        config.seed,
        video_dir=config.videos,
        policy_name=str(config.policy),
        env_kwargs=env_kwargs,
        rate=rate,
        on_episode=lambda r: print(
            f"episode {r.episode} (seed {r.seed}): {'success' if r.success else 'failure'} after {r.steps} steps"
            + ("".join(f", {k} {v}" for k, v in r.extras.items()) if r.extras else "")
        ),
    )
    out = record_evaluation(report, config.policy, config.out)
    s = report.summary()
    print(
        f"success rate {s['success_rate']:.1%} ({s['successes']}/{s['episodes']}), "
        f"95% CI [{s['ci95'][0]:.1%}, {s['ci95'][1]:.1%}] (Wilson); results in {out}"
    )
    return 0


def _warn_if_unfinished(policy) -> None:
    """A run folder whose trainer never wrote its final metrics was stopped mid-training."""
    import logging

    from shiftkit.policies.run_dir import CARD_METRICS, RunDir

    if policy.is_dir() and not (policy / CARD_METRICS).exists():
        latest = RunDir(policy, resume=True).latest_checkpoint()
        logging.getLogger("shiftkit").warning(
            "warning: %s has not finished training (stopped or still running): evaluating %s, not the final policy",
            policy,
            latest.name if latest else "its latest checkpoint",
        )
