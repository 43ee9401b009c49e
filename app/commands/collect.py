"""`shiftkit collect`: record scripted-expert episodes (raw format or LeRobot)."""

from __future__ import annotations

import argparse

from shiftkit.pipelines.dataclass_config import add_env_kwarg, csv_list
from shiftkit.pipelines.option_values import non_negative_int, positive_int

HELP = "record scripted-expert episodes from a simulated env (raw episodes or a LeRobot dataset)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `collect`."""
    parser.add_argument("--env", default="panda-play", help="environment name (default: panda-play)")
    parser.add_argument("--task", required=True, help="task, e.g. lift, stack, insert")
    parser.add_argument("--episodes", type=positive_int, default=10, help="number of episodes (default: 10)")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="episode i uses seed SEED+i (default: 0)")
    parser.add_argument("--out", help="raw-episode output directory (must not exist)")
    parser.add_argument("--lerobot", metavar="REPO_ID", help="write a LeRobot dataset with this repo id")
    parser.add_argument("--root", help="LeRobot dataset root (with --lerobot)")
    parser.add_argument("--play", action="store_true", help="record play episodes with task-segment labels")
    parser.add_argument("--sequence", help="comma-separated play sequence (default: the task's)")
    parser.add_argument(
        "--control-hz", type=positive_int, help="control rate in Hz (default: the env's, panda-play 20)"
    )
    add_env_kwarg(parser, "view=multiview")
    parser.add_argument(
        "--expert", default="scripted", help="how episodes are recorded: scripted (default) or an env's other recorder"
    )
    parser.add_argument("--kinesthetic", action="store_true", help="shorthand for --expert kinesthetic")
    parser.add_argument("--cameras", default="", help="comma-separated cameras to render, e.g. front")
    parser.add_argument("--depth", action="store_true", help="also record depth images")
    parser.add_argument("--video", action="store_true", help="cameras as lerobot videos (with --lerobot)")
    parser.add_argument("--width", type=positive_int, default=64, help="image width (default: 64)")
    parser.add_argument("--height", type=positive_int, default=48, help="image height (default: 48)")
    parser.add_argument("--render-quality", default="fast", choices=("fast", "full"), help="geometry shown")
    parser.add_argument(
        "--extra-steps", type=non_negative_int, default=0, help="frames kept after success (default: 0)"
    )
    parser.add_argument("--only-successful", action="store_true", help="skip failed episodes")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    """Record the episodes and print where they went; return the exit code."""
    from shiftkit.app.collect import CollectConfig, collect
    from shiftkit.app.env_kwargs import check_env_kwargs

    check_env_kwargs(args.env, dict(args.env_kwarg))

    config = CollectConfig(
        env=args.env,
        task=args.task,
        episodes=args.episodes,
        seed=args.seed,
        out=args.out,
        lerobot=args.lerobot,
        root=args.root,
        play=args.play,
        control_hz=args.control_hz,
        cameras=tuple(csv_list(args.cameras)),
        depth=args.depth,
        video=args.video,
        width=args.width,
        height=args.height,
        render_quality=args.render_quality,
        extra_steps=args.extra_steps,
        only_successful=args.only_successful,
        sequence=tuple(csv_list(args.sequence)),
        env_kwargs=dict(args.env_kwarg),
        expert="kinesthetic" if args.kinesthetic else args.expert,
    )
    path, counts = collect(config, progress=not args.no_progress)
    print(f"wrote {counts['episodes']} episodes ({counts['successes']} successful) to {path}")
    return 0
