"""`shiftkit calibrate`: fit a tactile sensor's force calibration from pushes against a fixed object
(thesis §4.3.6): simulated pushes, or the recording of a push plan a robot executed."""

from __future__ import annotations

import argparse

HELP = (
    "calibrate a tactile sensor: pushes (simulated, or --plan for a robot and --from its recording), "
    "piecewise-linear fit, calibration file + plot"
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `calibrate`."""
    parser.add_argument(
        "--env", default="door-tactile", help="environment with a tactile sensor (default: door-tactile)"
    )
    parser.add_argument(
        "--task", default="knob-open", help="task whose scene holds the object pushed (default: knob-open)"
    )
    parser.add_argument("--out", help="calibration file to write (JSON); not with --plan")
    parser.add_argument("--plot", help="fit-vs-data PNG (default: the --out path with .png)")
    parser.add_argument("--pushes", type=int, default=3, help="pushes of each kind to fit on (default: 3)")
    parser.add_argument("--held-out", type=int, default=2, help="pushes of each kind to test on (default: 2)")
    parser.add_argument("--seed", type=int, default=0, help="push i uses seed SEED+i (default: 0)")
    parser.add_argument(
        "--plan", metavar="DIR", help="write the pushes as a raw-format plan for a robot to execute (no fit)"
    )
    parser.add_argument("--from", dest="recording", metavar="RAW_DIR", help="fit from a robot's recording of a plan")
    parser.add_argument(
        "--sensor-id", help="the sensor's id in the plan / calibration (default: the --env's simulated STS)"
    )


def run(args: argparse.Namespace) -> int:
    """Fit and write the calibration (or write the push plan with `--plan`); return the exit code."""
    from pathlib import Path

    import numpy as np

    from shiftkit.app.commands.plot import check_figure_path
    from shiftkit.pipelines.errors import ConfigError
    from shiftkit.transforms import force_calibration as fc

    if args.pushes < 1 or args.held_out < 0:
        raise ConfigError("--pushes must be >= 1 and --held-out >= 0")
    fit_seeds = list(range(args.seed, args.seed + args.pushes))
    held_seeds = list(range(args.seed + args.pushes, args.seed + args.pushes + args.held_out))
    if args.plan:
        if args.out or args.recording:
            raise ConfigError("--plan writes a plan only: give neither --out nor --from with it")
        plan = Path(args.plan)
        if plan.exists() or not plan.parent.is_dir():
            raise ConfigError(f"--plan {plan}: give a new folder in an existing one")
        sensor = args.sensor_id or _sim_sensor(args.env)
        fc.write_calibration_plan(plan, fit_seeds, held_seeds, sensor)
        print(
            f"wrote {plan}: {len(fit_seeds) + len(held_seeds)} pushes of each kind ({', '.join(fc.PUSH_KINDS)}) "
            f"for sensor {sensor}; execute it and record it, then: shiftkit calibrate --from RECORDING --out FILE"
        )
        return 0
    if not args.out:
        raise ConfigError("give --out (the calibration file to write), or --plan")
    out = Path(args.out)
    if out.is_dir() or not out.parent.is_dir():
        raise ConfigError(f"--out {out}: give a file in an existing folder")
    plot = Path(args.plot) if args.plot else out.with_suffix(".png")
    if plot.resolve() == out.resolve():  # the plot would overwrite the calibration
        raise ConfigError(
            f"--out {out} and the plot {plot} would be one file: give --out a .json path or another --plot"
        )
    check_figure_path(str(plot), "--plot" if args.plot else "the plot of --out")
    if plot.is_dir() or not plot.parent.is_dir():
        raise ConfigError(f"--plot {plot}: give a file in an existing folder")
    if args.recording:
        calibration, fit, held = fc.calibrate_recording(args.recording, args.sensor_id)
    else:
        calibration, fit, held = fc.calibrate_env(args.env, args.task, fit_seeds, held_seeds)
    stack = lambda pushes: [np.concatenate([getattr(p, a) for p in pushes]) for a in ("displacement", "wrench", "mask")]  # noqa: E731
    e, f, m = stack(fit)
    new = [p for p in (out, plot) if not p.exists()]
    try:
        calibration.save(out)
        fc.plot_calibration(calibration, e, f, plot, held_out=tuple(stack(held)) if held else None, mask=m)
    except BaseException:  # no calibration without its plot: remove what this run created
        for path in new:
            path.unlink(missing_ok=True)
        raise
    print(f"wrote {out} (sensor {calibration.sensor_id}) and {plot}")
    split = "held_out" if held else "fit"
    for axis in fc.WRENCH_AXES:
        fit_ = calibration.axes[axis]
        res = calibration.residuals[split][axis]
        rel = res["relative_rmse_displacement"]
        print(
            f"  {axis:6s} slopes {', '.join(f'{s:.4g}' for s in fit_.slopes)}"
            + (f" (break at {fit_.breakpoints[0]:.4g})" if fit_.breakpoints else "")
            + f", offset {fit_.offset:+.3f}; {split} displacement RMSE {res['rmse_displacement']:.3g} {res['unit']}"
            + (f" ({100 * rel:.1f}% of the loaded RMS)" if rel is not None else "")
        )
    return 0


def _sim_sensor(env: str) -> str:
    from shiftkit.envs import env_family
    from shiftkit.pipelines.errors import ConfigError
    from shiftkit.transforms.force_calibration import sensor_id

    try:
        return sensor_id(env_family(env).sim_model_id)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
