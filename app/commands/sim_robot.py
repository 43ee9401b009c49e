"""`shiftkit sim-robot`: a simulated lab robot executes a plan shiftkit wrote for a real one and
records it as the lab's logger would (docs/real_robot.md): a calibration plan (`shiftkit calibrate
--plan`) or a force-matched replay plan (`force_match` with `execute = "plan"`)."""

from __future__ import annotations

import argparse

HELP = "execute a calibration or replay plan on a simulated robot and record it in the raw format"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `sim-robot`."""
    parser.add_argument("plan", help="calibration plan (raw format) or replay plan (LeRobot dataset) folder")
    parser.add_argument("--out", required=True, help="raw-format recording to write (must not exist)")
    parser.add_argument(
        "--env", default="door-tactile", help="environment whose robot executes (default: door-tactile)"
    )
    parser.add_argument(
        "--task", default="knob-open", help="calibration plans: task whose scene holds the object (default: knob-open)"
    )


def run(args: argparse.Namespace) -> int:
    """Execute the plan on the simulated robot and record it in the raw format; return the exit code."""
    from pathlib import Path

    from shiftkit.pipelines.errors import ConfigError
    from shiftkit.pipelines.sources.raw import is_raw_dataset

    plan, out = Path(args.plan), Path(args.out)
    if out.exists() or not out.parent.is_dir():
        raise ConfigError(f"--out {out}: give a new folder in an existing one")
    if is_raw_dataset(plan):
        from shiftkit.transforms.force_calibration import execute_calibration_plan

        execute_calibration_plan(plan, out, args.env, args.task)
        print(f"executed calibration plan {plan} on the simulated {args.env} robot; recorded {out}")
    elif (plan / "meta" / "info.json").is_file():
        from shiftkit.transforms.replay_join import execute_replay_plan

        counts = execute_replay_plan(plan, out)
        print(
            f"executed replay plan {plan} on the simulated robot: {counts['episodes']} episodes "
            f"({counts['successes']} successful); recorded {out}"
        )
    else:
        raise ConfigError(f"{plan}: not a plan (neither a raw-format calibration plan nor a LeRobot replay plan)")
    return 0
