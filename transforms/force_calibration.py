"""Tactile force calibration (thesis §4.3.6, SPEC §5.2): the map between a tactile sensor's unscaled
wrench F~ = (Fx, Fy, Fz, tau_z) and the impedance controller's pose error e = x_d - x, both in the
sensor frame (e = (ex, ey, ez) in metres, erz in radians).

Each axis is fitted on its own by least squares as an odd, piecewise-linear function around an
offset: F~_k = b_k + sign(e_k) g_k(|e_k|), g_k(0) = 0, continuous, with one slope per segment. The
normal axis gets two slopes and a fitted breakpoint (the thesis' robot: ~5 mm), the others one
slope. Inverting it (force matching needs e from F~) clips |e| to the calibrated range (the
reference robot: ~2.6 cm), since the line is not known beyond the pushes that made it.

A calibration is a versioned JSON file (`FORMAT`, `VERSION`) with the sensor id, the fit, its
residuals and where the pushes came from; reading one of another version or sensor is a one-line
`ConfigError`.
"""

from __future__ import annotations

import os
import uuid
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from shiftkit.pipelines.errors import ConfigError, ShiftkitError
from shiftkit.pipelines.jsonutil import dumps, read_json_file

FORMAT = "shiftkit-force-calibration"
VERSION = 1
WRENCH_AXES = ("Fx", "Fy", "Fz", "tau_z")
DISPLACEMENT_AXES = ("ex", "ey", "ez", "erz")
DISPLACEMENT_UNITS = ("m", "m", "m", "rad")
NORMAL = 2  # index of the normal axis
# one breakpoint on the normal axis (thesis Fig. 4.5), straight lines elsewhere
DEFAULT_BREAKPOINTS = (0, 0, 1, 0)
# largest displacement a force may be mapped to (the reference robot clips at ~2.6 cm)
DEFAULT_MAX_OFFSET = (0.026, 0.026, 0.026, 1.0)
BREAKPOINT_CANDIDATES = 200


@dataclass
class AxisFit:
    """F~ = offset + sign(e) g(|e|) with g piecewise linear: slope `slopes[i]` between consecutive
    `breakpoints` (|e| in the axis' unit), g(0) = 0."""

    offset: float
    slopes: list[float]
    breakpoints: list[float] = field(default_factory=list)
    clip: float = float("inf")
    """Largest |e| `displacement` returns: the calibrated range."""

    def _knots(self) -> tuple[np.ndarray, np.ndarray]:
        """|e| at the segment starts and g there."""
        starts = np.concatenate(([0.0], self.breakpoints))
        values = np.concatenate(([0.0], np.cumsum(np.diff(starts) * np.asarray(self.slopes[:-1]))))
        return starts, values

    def force(self, e: np.ndarray) -> np.ndarray:
        """The reading predicted for displacement `e`."""
        e = np.asarray(e, dtype=np.float64)
        starts, values = self._knots()
        a = np.abs(e)
        seg = np.searchsorted(starts, a, side="right") - 1
        g = values[seg] + np.asarray(self.slopes)[seg] * (a - starts[seg])
        return self.offset + np.sign(e) * g

    def displacement(self, reading: np.ndarray) -> np.ndarray:
        """The displacement that produces `reading` (the fit inverted), clipped to +-`clip`."""
        reading = np.asarray(reading, dtype=np.float64)
        slopes = np.asarray(self.slopes)
        sign = np.sign(slopes[0])
        starts, values = self._knots()
        y = (reading - self.offset) * sign
        a = np.abs(y)
        values = values * sign
        seg = np.searchsorted(values, a, side="right") - 1
        e = starts[seg] + (a - values[seg]) / (slopes[seg] * sign)
        return np.sign(y) * np.minimum(e, self.clip)


@dataclass
class Calibration:
    """A fitted sensor calibration and what it was made from."""

    sensor_id: str
    axes: dict[str, AxisFit]
    """Wrench axis name -> its fit."""
    residuals: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Per data split ("fit", "held_out") and wrench axis: RMSE of the force and of the displacement."""
    provenance: dict[str, Any] = field(default_factory=dict)
    """Where the pushes came from (environment, seeds, push counts, step sizes, ...)."""

    def force(self, displacement: np.ndarray) -> np.ndarray:
        """(..., 4) readings predicted for (..., 4) sensor-frame displacements."""
        d = np.asarray(displacement, dtype=np.float64)
        return np.stack([self.axes[a].force(d[..., k]) for k, a in enumerate(WRENCH_AXES)], axis=-1)

    def displacement(self, wrench: np.ndarray) -> np.ndarray:
        """(..., 4) sensor-frame displacements (ex, ey, ez, erz) that give the (..., 4) readings:
        A^-1 (F~ - b), piecewise and clipped."""
        w = np.asarray(wrench, dtype=np.float64)
        return np.stack([self.axes[a].displacement(w[..., k]) for k, a in enumerate(WRENCH_AXES)], axis=-1)

    def to_json(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "version": VERSION,
            "sensor_id": self.sensor_id,
            "wrench_axes": list(WRENCH_AXES),
            "displacement_axes": list(DISPLACEMENT_AXES),
            "displacement_units": list(DISPLACEMENT_UNITS),
            "model": "F~ = offset + sign(e) * piecewise_linear(|e|; slopes, breakpoints); e clipped to +-clip",
            "axes": {a: asdict(f) for a, f in self.axes.items()},
            "residuals": self.residuals,
            "provenance": self.provenance,
        }

    def save(self, path: str | Path) -> Path:
        """Write the file atomically (a temporary sibling renamed into place)."""
        path = Path(path)
        tmp = path.parent / f".{path.name}.{uuid.uuid4().hex[:8]}.tmp"
        tmp.write_text(dumps(self.to_json(), indent=1))
        os.replace(tmp, path)
        return path


def load_calibration(path: str | Path, sensor_id: str | None = None) -> Calibration:
    """Read a calibration file; a file of another format version, or of another sensor than
    `sensor_id` (when given), is a one-line `ConfigError`."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"calibration file not found: {path}")
    try:
        data = read_json_file(path, "not a shiftkit force calibration")
    except ShiftkitError as exc:
        raise ConfigError(str(exc)) from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise ConfigError(f"{path}: not a shiftkit force calibration (format {FORMAT!r} expected)")
    if data.get("version") != VERSION:
        raise ConfigError(f"{path}: calibration version {data.get('version')!r} is not supported (this is v{VERSION})")
    if sensor_id is not None and data.get("sensor_id") != sensor_id:
        raise ConfigError(f"{path}: calibration is for sensor {data.get('sensor_id')!r}, not {sensor_id!r}")
    axes = {}
    for name in WRENCH_AXES:
        raw = (data.get("axes") or {}).get(name)
        try:
            fit = AxisFit(
                offset=float(raw["offset"]),
                slopes=[float(s) for s in raw["slopes"]],
                breakpoints=[float(b) for b in raw.get("breakpoints", [])],
                clip=float(raw.get("clip", float("inf"))),
            )
        except (KeyError, TypeError, ValueError):
            raise ConfigError(f"{path}: axis {name!r} needs 'offset' and 'slopes' numbers") from None
        _check_fit(fit, f"{path}: axis {name!r}")
        axes[name] = fit
    return Calibration(str(data.get("sensor_id")), axes, data.get("residuals", {}), data.get("provenance", {}))


def _check_fit(fit: AxisFit, where: str) -> None:
    slopes = np.asarray(fit.slopes)
    if len(slopes) != len(fit.breakpoints) + 1:
        raise ConfigError(
            f"{where}: {len(slopes)} slopes need {len(slopes) - 1} breakpoints, got {len(fit.breakpoints)}"
        )
    values = [fit.offset, fit.clip, *slopes, *fit.breakpoints]
    if any(v != v for v in values):
        raise ConfigError(f"{where}: NaN in the fit")
    if not (np.all(slopes > 0) or np.all(slopes < 0)):
        raise ConfigError(f"{where}: slopes {slopes.tolist()} change sign or are zero, so the fit cannot be inverted")
    if np.any(np.diff([0.0, *fit.breakpoints]) <= 0) or fit.clip <= 0:
        raise ConfigError(f"{where}: breakpoints must increase from 0 and the clip must be positive")


def fit_axis(e: np.ndarray, reading: np.ndarray, breakpoints: int, clip: float, where: str = "fit") -> AxisFit:
    """Least-squares fit of one axis with `breakpoints` (0 or 1) slope changes; a breakpoint is
    chosen among candidates spread over the data's |e| range (the one with the smallest squared error).
    The returned clip is `clip` or the largest |e| seen, whichever is smaller."""
    e, reading = np.asarray(e, np.float64), np.asarray(reading, np.float64)
    if breakpoints not in (0, 1):
        raise ConfigError(f"{where}: breakpoints must be 0 or 1, got {breakpoints}")
    if len(e) < 3 or not np.isfinite(e).all() or not np.isfinite(reading).all():
        raise ShiftkitError(f"{where}: need at least 3 finite samples, got {len(e)}")
    a = np.abs(e)
    if a.max() <= 0:
        raise ShiftkitError(f"{where}: no sample has a displacement, nothing to fit")
    basis = [np.ones_like(e), e]
    candidates: list[float | None] = [None]
    if breakpoints:
        moving = a[a > 1e-3 * a.max()]
        lo, hi = np.quantile(moving, [0.05, 0.95])
        candidates = list(np.linspace(lo, hi, BREAKPOINT_CANDIDATES)) if hi > lo else [None]
    best: tuple[float, np.ndarray, float | None] | None = None
    for bp in candidates:
        cols = basis if bp is None else [*basis, np.sign(e) * np.maximum(a - bp, 0.0)]
        x = np.stack(cols, axis=1)
        coef, *_ = np.linalg.lstsq(x, reading, rcond=None)
        sse = float(np.sum((x @ coef - reading) ** 2))
        if best is None or sse < best[0]:
            best = (sse, coef, bp)
    _, coef, bp = best
    slopes = [float(coef[1])] if bp is None else [float(coef[1]), float(coef[1] + coef[2])]
    fit = AxisFit(float(coef[0]), slopes, [] if bp is None else [float(bp)], float(min(clip, a.max())))
    try:
        _check_fit(fit, where)
    except ConfigError as exc:
        raise ShiftkitError(str(exc)) from None
    return fit


def fit_calibration(
    displacement: np.ndarray,
    wrench: np.ndarray,
    sensor_id: str,
    breakpoints: tuple[int, ...] = DEFAULT_BREAKPOINTS,
    max_offset: tuple[float, ...] = DEFAULT_MAX_OFFSET,
    provenance: dict[str, Any] | None = None,
) -> Calibration:
    """Fit every axis from (n, 4) sensor-frame displacements and (n, 4) readings; records the fit's
    own residuals under "fit"."""
    displacement, wrench = np.asarray(displacement, np.float64), np.asarray(wrench, np.float64)
    if displacement.ndim != 2 or displacement.shape[1] != 4 or wrench.shape != displacement.shape:
        raise ShiftkitError(f"calibration data must be two (n, 4) arrays, got {displacement.shape} and {wrench.shape}")
    axes = {
        a: fit_axis(displacement[:, k], wrench[:, k], breakpoints[k], max_offset[k], where=f"calibration axis {a}")
        for k, a in enumerate(WRENCH_AXES)
    }
    calibration = Calibration(sensor_id, axes, provenance=dict(provenance or {}))
    calibration.residuals["fit"] = residuals(calibration, displacement, wrench)
    return calibration


def residuals(calibration: Calibration, displacement: np.ndarray, wrench: np.ndarray) -> dict[str, dict[str, Any]]:
    """Per axis: RMSE of the predicted reading, RMSE of the predicted displacement (the inverse, as
    force matching uses it) and that RMSE relative to the RMS displacement, over samples whose
    displacement lies in the calibrated range (the inverse is clipped beyond it)."""
    displacement, wrench = np.asarray(displacement, np.float64), np.asarray(wrench, np.float64)
    predicted_force = calibration.force(displacement)
    predicted_e = calibration.displacement(wrench)
    out = {}
    for k, a in enumerate(WRENCH_AXES):
        inside = np.abs(displacement[:, k]) <= calibration.axes[a].clip
        e, pe = displacement[inside, k], predicted_e[inside, k]
        rms_e = float(np.sqrt(np.mean(e**2))) if len(e) else 0.0
        rmse_e = float(np.sqrt(np.mean((pe - e) ** 2))) if len(e) else 0.0
        out[a] = {
            "n": int(len(e)),
            "rmse_force": float(np.sqrt(np.mean((predicted_force[:, k] - wrench[:, k]) ** 2))),
            "rmse_displacement": rmse_e,
            "relative_rmse_displacement": rmse_e / rms_e if rms_e > 0 else None,
            "unit": DISPLACEMENT_UNITS[k],
        }
    return out


def plot_calibration(
    calibration: Calibration,
    displacement: np.ndarray,
    wrench: np.ndarray,
    path: str | Path,
    held_out: tuple[np.ndarray, np.ndarray] | None = None,
) -> Path:
    """A PNG with one panel per axis: the pushes' (e, F~) samples and the fitted line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(1, 4, figsize=(16, 3.6), constrained_layout=True)
    for k, (a, ax) in enumerate(zip(WRENCH_AXES, axs, strict=True)):
        ax.scatter(displacement[:, k], wrench[:, k], s=3, c="k", alpha=0.5, label="fit pushes")
        if held_out is not None:
            ax.scatter(held_out[0][:, k], held_out[1][:, k], s=3, c="tab:orange", alpha=0.5, label="held-out pushes")
        fit = calibration.axes[a]
        lo, hi = float(np.min(displacement[:, k])), float(np.max(displacement[:, k]))
        xs = np.linspace(max(lo, -fit.clip), min(hi, fit.clip), 200)
        ax.plot(xs, fit.force(xs), c="tab:blue", lw=2, label="piecewise-linear fit")
        for bp in fit.breakpoints:
            ax.axvline(bp, c="tab:blue", ls=":", lw=1)
        res = calibration.residuals.get("held_out", calibration.residuals.get("fit", {})).get(a, {})
        rel = res.get("relative_rmse_displacement")
        title = f"{a} vs {DISPLACEMENT_AXES[k]}"
        if rel is not None:
            title += f"  (displacement RMSE {100 * rel:.1f}%)"
        ax.set_title(title, fontsize=9)
        ax.set_xlabel(f"{DISPLACEMENT_AXES[k]} = x_d - x ({DISPLACEMENT_UNITS[k]})")
        ax.set_ylabel(f"raw {a}")
    axs[0].legend(fontsize=7)
    fig.suptitle(f"force calibration of sensor {calibration.sensor_id}", fontsize=10)
    path = Path(path)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
