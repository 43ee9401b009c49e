"""`shiftkit calibrate`: fit a tactile sensor's force calibration from pushes against a fixed object
(thesis §4.3.6): simulated pushes, or the recording of a push plan a robot executed.

The options are generated from `app.calibrate.CalibrateConfig` (`option_values.DataclassOptions`).
"""

from __future__ import annotations

import argparse

from shiftkit.datasets.option_values import DataclassOptions

HELP = (
    "calibrate a tactile sensor: pushes (simulated, or --plan for a robot and --from its recording), "
    "piecewise-linear fit, calibration file + plot"
)


def _options() -> DataclassOptions:
    from shiftkit.app.calibrate import CalibrateConfig

    return DataclassOptions(
        CalibrateConfig,
        flags={"recording": "from"},
        metavars={"plan": "DIR", "recording": "RAW_DIR"},
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `calibrate`."""
    _options().add_to(parser)


def run(args: argparse.Namespace) -> int:
    """Fit and write the calibration (or write the push plan with `--plan`); return the exit code."""
    from shiftkit.app.calibrate import calibrate, write_plan
    from shiftkit.datasets.staging import check_inputs_and_outputs
    from shiftkit.envs.door_tactile.lab import PUSH_KINDS
    from shiftkit.transforms.force_calibration import WRENCH_AXES

    config = _options().build(args)
    outputs = (("--out", config.out), ("--plot", config.plot), ("--plan", config.plan))
    inputs = [("--from", config.recording)] if config.recording else []
    check_inputs_and_outputs(inputs, [(flag, path) for flag, path in outputs if path])
    if config.plan:
        sensor = write_plan(config)
        print(
            f"wrote {config.plan}: {config.pushes + config.held_out} pushes of each kind ({', '.join(PUSH_KINDS)}) "
            f"for sensor {sensor}; execute it and record it, then: shiftkit calibrate --from RECORDING --out FILE"
        )
        return 0
    calibration, plot, split = calibrate(config)
    print(f"wrote {config.out} (sensor {calibration.sensor_id}) and {plot}")
    for axis in WRENCH_AXES:
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
