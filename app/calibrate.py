"""`shiftkit calibrate`: fit a tactile sensor's force calibration from pushes against a fixed object
(thesis §4.3.6), simulated in an env or recorded by a robot that executed a push plan; or write
that plan. The fit itself is `transforms.force_calibration`'s; this module checks the paths, picks
the push seeds and writes the calibration file with its plot (both or neither)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from shiftkit.datasets.dataclass_config import check_fields, option
from shiftkit.datasets.errors import ConfigError
from shiftkit.datasets.staging import require_writable


@dataclass(frozen=True)
class CalibrateConfig:
    """What to push (or which recording to fit) and where the calibration goes."""

    env: str = "door-tactile"
    """Environment with a tactile sensor."""
    task: str = "knob-open"
    """Task whose scene holds the object pushed."""
    out: str | None = None
    """Calibration file to write (JSON); not with `plan`."""
    plot: str | None = None
    """Fit-vs-data PNG; default: the `out` path with .png."""
    pushes: int = option(3, rule="positive_int")
    """Pushes of each kind to fit on."""
    held_out: int = option(2, rule="non_negative_int")
    """Pushes of each kind to test on."""
    seed: int = option(0, rule="non_negative_int")
    """Push i uses seed `seed + i` (fit pushes first, then the held-out ones)."""
    plan: str | None = None
    """Write the pushes as a raw-format plan folder for a robot to execute (no fit)."""
    recording: str | None = None
    """Fit from a robot's recording of a plan (a raw-episode folder) instead of simulated pushes."""
    sensor_id: str | None = None
    """The sensor's id in the plan / calibration; default: the env's simulated STS."""

    def seeds(self) -> tuple[list[int], list[int]]:
        """The fit seeds and the held-out seeds."""
        check_fields(self)
        fit = list(range(self.seed, self.seed + self.pushes))
        return fit, list(range(fit[-1] + 1, fit[-1] + 1 + self.held_out))


def write_plan(config: CalibrateConfig) -> str:
    """Write the push plan into the new folder `config.plan`; return the sensor id it names."""
    from shiftkit.transforms.force_calibration import write_calibration_plan

    fit_seeds, held_seeds = config.seeds()
    if config.out or config.recording:
        raise ConfigError("--plan writes a plan only: give neither --out nor --from with it")
    plan = Path(config.plan or "")
    if not config.plan or plan.exists() or not plan.parent.is_dir():
        raise ConfigError(f"--plan {plan}: give a new folder in an existing one")
    sensor = config.sensor_id or _sim_sensor(config.env)
    write_calibration_plan(plan, fit_seeds, held_seeds, sensor)
    return sensor


def calibrate(config: CalibrateConfig):  # noqa: ANN201 - a force_calibration.Calibration, imported lazily
    """Fit the calibration, write it to `config.out` and its plot; return (calibration, plot path,
    the residual split shown: "held_out", or "fit" when there are no held-out pushes)."""
    import numpy as np

    from shiftkit.app.commands.plot import check_figure_path
    from shiftkit.transforms import force_calibration as fc

    fit_seeds, held_seeds = config.seeds()
    if not config.out:
        raise ConfigError("give --out (the calibration file to write), or --plan")
    out = Path(config.out)
    if out.is_dir() or not out.parent.is_dir():
        raise ConfigError(f"--out {out}: give a file in an existing folder")
    plot = Path(config.plot) if config.plot else out.with_suffix(".png")
    if plot.resolve() == out.resolve():  # the plot would overwrite the calibration
        raise ConfigError(
            f"--out {out} and the plot {plot} would be one file: give --out a .json path or another --plot"
        )
    check_figure_path(str(plot), "--plot" if config.plot else "the plot of --out")
    if plot.is_dir() or not plot.parent.is_dir():
        raise ConfigError(f"--plot {plot}: give a file in an existing folder")
    require_writable(out.parent, "--out")
    require_writable(plot.parent, "--plot" if config.plot else "the plot of --out")
    if config.recording:
        calibration, fit, held = fc.calibrate_recording(config.recording, config.sensor_id)
    else:
        calibration, fit, held = fc.calibrate_env(config.env, config.task, fit_seeds, held_seeds)
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
    return calibration, plot, "held_out" if held else "fit"


def _sim_sensor(env: str) -> str:
    from shiftkit.envs import env_family
    from shiftkit.transforms.force_calibration import sensor_id

    try:
        return sensor_id(env_family(env).sim_model_id)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
