"""`shiftkit eval`: roll out a trained policy in a registered env and report its success rate."""

from __future__ import annotations

import argparse

from shiftkit.pipelines.dataclass_config import add_env_kwarg
from shiftkit.pipelines.option_values import non_negative_int, positive_int

HELP = "evaluate a trained policy in a registered environment (success rate with a 95% interval)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `eval`."""
    parser.add_argument("--policy", required=True, help="run folder or checkpoint file of a trained policy")
    parser.add_argument("--env", default="panda-play", help="environment name (default: panda-play)")
    parser.add_argument("--task", required=True, help="task, e.g. lift")
    parser.add_argument("--episodes", type=positive_int, default=50, help="number of episodes (default: 50)")
    parser.add_argument(
        "--seed", type=non_negative_int, default=1000, help="episode i uses seed SEED+i (default: 1000)"
    )
    parser.add_argument("--out", help="per-episode results JSON (default: <run>/eval/<env>-<task>-seed<S>.json)")
    parser.add_argument("--videos", help="folder for one MP4 per episode (default: none)")
    parser.add_argument(
        "--control-hz",
        type=int,
        choices=(5, 20),
        help="env control rate (default: the fps of the policy's dataset; it must be that rate)",
    )
    parser.add_argument("--device", default="cpu", help="torch device for the policy (default: cpu)")
    add_env_kwarg(parser, "view=fixed")
    parser.add_argument(
        "--yaw-sweep",
        action="store_true",
        help="multiview envs: --episodes per base-yaw bin over 12 bins [-0.8,-0.7]..[0.3,0.4] rad; "
        "writes JSON (--out, default <run>/eval/<env>-<task>-yawsweep-seed<S>.json) and a PNG beside it",
    )


def run(args: argparse.Namespace) -> int:
    """Roll out the policy (or sweep the camera yaw) and print the success rate; return the exit code."""
    from pathlib import Path

    from shiftkit.pipelines.errors import ConfigError
    from shiftkit.policies.evaluation import (
        evaluate,
        load_policy,
        policy_rate,
        record_evaluation,
        write_yaw_sweep,
        yaw_sweep,
    )

    # Output paths are checked before the rollouts, which can take minutes.
    if args.out and Path(args.out).is_dir():
        raise ConfigError(f"--out {args.out} is a folder; give the JSON file to write")
    if args.out and any(p.exists() and not p.is_dir() for p in Path(args.out).parents):
        raise ConfigError(f"--out {args.out}: a parent of it is a file, not a folder")
    if args.videos and Path(args.videos).exists() and not Path(args.videos).is_dir():
        raise ConfigError(f"--videos {args.videos} is a file; give a folder for the MP4s")
    from shiftkit.app.env_kwargs import check_env_kwargs

    check_env_kwargs(args.env, dict(args.env_kwarg))
    if args.yaw_sweep:
        if args.videos:
            raise ConfigError("--videos is not written by --yaw-sweep; evaluate without --yaw-sweep for videos")
        if dict(args.env_kwarg).get("view") == "fixed":
            raise ConfigError("--yaw-sweep sets the base yaw of every episode, which view=fixed would keep fixed")
        if args.out and Path(args.out).suffix.lower() == ".png":
            raise ConfigError(f"--out {args.out}: the sweep's JSON goes there and its PNG beside it; give a .json")
    if args.seed < 0 or args.episodes < 1:
        raise ConfigError(f"need --seed >= 0 and --episodes >= 1, got {args.seed} and {args.episodes}")
    from shiftkit.policies.run_dir import EVAL, run_folder

    _check_writable(Path(args.out).parent if args.out else run_folder(args.policy) / EVAL, "--out")
    policy = load_policy(args.policy, device=args.device)
    rate = policy_rate(args.policy)
    _warn_if_unfinished(Path(args.policy))
    env_kwargs = {**dict(args.env_kwarg), **({"control_hz": args.control_hz} if args.control_hz else {})}
    if args.yaw_sweep:
        from shiftkit.policies.run_dir import EVAL, run_folder

        sweep = yaw_sweep(
            policy,
            args.env,
            args.task,
            args.episodes,
            args.seed,
            policy_name=str(args.policy),
            env_kwargs=env_kwargs,
            rate=rate,
            on_bin=lambda r: print(f"yaw {r['yaw']}: {r['successes']}/{r['episodes']} ({r['success_rate']:.0%})"),
        )
        default = run_folder(args.policy) / EVAL / f"{args.env}-{args.task}-yawsweep-seed{args.seed}.json"
        json_path, png = write_yaw_sweep(sweep, args.out or default)
        print(f"yaw sweep written to {json_path} and {png}")
        return 0
    report = evaluate(
        policy,
        args.env,
        args.task,
        args.episodes,
        args.seed,
        video_dir=args.videos,
        policy_name=str(args.policy),
        env_kwargs=env_kwargs,
        rate=rate,
        on_episode=lambda r: print(
            f"episode {r.episode} (seed {r.seed}): {'success' if r.success else 'failure'} after {r.steps} steps"
            + ("".join(f", {k} {v}" for k, v in r.extras.items()) if r.extras else "")
        ),
    )
    out = record_evaluation(report, args.policy, args.out)
    s = report.summary()
    print(
        f"success rate {s['success_rate']:.1%} ({s['successes']}/{s['episodes']}), "
        f"95% CI [{s['ci95'][0]:.1%}, {s['ci95'][1]:.1%}] (Wilson); results in {out}"
    )
    return 0


def _check_writable(folder, flag: str) -> None:
    """The nearest existing folder on the way to `folder` must take new files (tried, not guessed)."""
    import tempfile

    from shiftkit.pipelines.errors import ConfigError

    existing = next(p for p in [folder, *folder.parents] if p.exists())
    try:
        with tempfile.TemporaryFile(dir=existing):
            pass
    except OSError as exc:
        raise ConfigError(f"{flag}: cannot write into {existing} ({exc.strerror})") from None


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
