"""`shiftkit sim-robot`: a simulated lab robot executes a plan shiftkit wrote for a real one and
records it as the lab's logger would (docs/real_robot.md): a calibration plan (`shiftkit calibrate
--plan`) or a force-matched replay plan (`force_match` with `execute = "plan"`)."""

from __future__ import annotations

import argparse
from dataclasses import dataclass

from shiftkit.app.calibrate import CalibrateConfig
from shiftkit.datasets.dataclass_config import field_help
from shiftkit.datasets.option_values import DataclassOptions

HELP = "execute a calibration or replay plan on a simulated robot and record it in the raw format"


@dataclass(frozen=True)
class SimRobotArgs:
    """Which plan the simulated robot executes and where its recording goes."""

    plan: str
    """Calibration plan (raw format) or replay plan (LeRobot dataset) folder."""
    out: str
    """Raw-format recording to write (must not exist)."""
    env: str = CalibrateConfig.env
    """Environment whose robot executes (calibration plans: the one `calibrate` pushes in)."""
    task: str = CalibrateConfig.task
    """Calibration plans: task whose scene holds the object."""


OPTIONS = DataclassOptions(SimRobotArgs, skip=("plan",), metavars={"out": "DIR"})


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `sim-robot`."""
    parser.add_argument("plan", help=field_help(SimRobotArgs, "plan"))
    OPTIONS.add_to(parser)


def run(args: argparse.Namespace) -> int:
    """Execute the plan on the simulated robot and record it in the raw format; return the exit code."""
    from pathlib import Path

    from shiftkit.datasets.errors import ConfigError
    from shiftkit.datasets.sources.raw import is_raw_dataset
    from shiftkit.datasets.staging import check_inputs_and_outputs

    config = OPTIONS.build(args, plan=args.plan)
    plan, out = Path(config.plan), Path(config.out)
    is_calibration, is_replay = is_raw_dataset(plan), (plan / "meta" / "info.json").is_file()
    if not (is_calibration or is_replay):
        raise ConfigError(f"{plan}: not a plan (neither a raw-format calibration plan nor a LeRobot replay plan)")
    check_inputs_and_outputs([("plan", plan)], [("--out", out)])
    if out.exists() or not out.parent.is_dir():
        raise ConfigError(f"--out {out}: give a new folder in an existing one")
    if is_calibration:
        from shiftkit.transforms.force_calibration import execute_calibration_plan

        execute_calibration_plan(plan, out, config.env, config.task)
        print(f"executed calibration plan {plan} on the simulated {config.env} robot; recorded {out}")
    else:
        from shiftkit.transforms.replay_join import execute_replay_plan

        counts = execute_replay_plan(plan, out)
        print(
            f"executed replay plan {plan} on the simulated robot: {counts['episodes']} episodes "
            f"({counts['successes']} successful); recorded {out}"
        )
    return 0
