"""Tactile force calibration (thesis §4.3.6; docs/force_matching.md): the map between a tactile sensor's unscaled
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
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from shiftkit.datasets.errors import ConfigError, ShiftkitError
from shiftkit.datasets.jsonutil import dumps, read_json_file
from shiftkit.datasets.staging import staging_path

if TYPE_CHECKING:
    from shiftkit.envs.door_tactile.lab import PushConfig

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
LOADED = 0.1  # residuals relative to the displacement count samples above this share of the largest


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
        """The calibration as the JSON document it is saved as."""
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
        tmp = staging_path(path, "tmp")  # within the name limit whatever the length of the name
        try:
            tmp.write_text(dumps(self.to_json(), indent=1))
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
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
    Inverting clips at `clip`: beyond the pushes' range the line is extrapolated up to it (a person
    drags a handle harder than a calibration shear move that slips)."""
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
    fit = AxisFit(float(coef[0]), slopes, [] if bp is None else [float(bp)], float(clip))
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
    mask: np.ndarray | None = None,
) -> Calibration:
    """Fit every axis from (n, 4) sensor-frame displacements and (n, 4) readings; `mask` (n, 4)
    says which samples inform which axis (default: all). Records the fit's own residuals under "fit"."""
    displacement, wrench = np.asarray(displacement, np.float64), np.asarray(wrench, np.float64)
    if displacement.ndim != 2 or displacement.shape[1] != 4 or wrench.shape != displacement.shape:
        raise ShiftkitError(f"calibration data must be two (n, 4) arrays, got {displacement.shape} and {wrench.shape}")
    mask = np.ones(displacement.shape, bool) if mask is None else np.asarray(mask, bool)
    axes = {
        a: fit_axis(
            displacement[mask[:, k], k], wrench[mask[:, k], k], breakpoints[k], max_offset[k], f"calibration axis {a}"
        )
        for k, a in enumerate(WRENCH_AXES)
    }
    calibration = Calibration(sensor_id, axes, provenance=dict(provenance or {}))
    calibration.residuals["fit"] = residuals(calibration, displacement, wrench, mask)
    return calibration


def residuals(
    calibration: Calibration, displacement: np.ndarray, wrench: np.ndarray, mask: np.ndarray | None = None
) -> dict[str, dict[str, Any]]:
    """Per axis, over the samples `mask` (n, 4) assigns to it whose displacement lies within the
    clip: RMSE of the predicted reading, RMSE of the predicted displacement (the inverse, as force
    matching uses it), and that RMSE over the loaded samples (|e| above `LOADED` of the largest)
    relative to their RMS displacement (unloaded samples only measure the reading's noise)."""
    displacement, wrench = np.asarray(displacement, np.float64), np.asarray(wrench, np.float64)
    mask = np.ones(displacement.shape, bool) if mask is None else np.asarray(mask, bool)
    predicted_force = calibration.force(displacement)
    predicted_e = calibration.displacement(wrench)
    out = {}
    for k, a in enumerate(WRENCH_AXES):
        inside = mask[:, k] & (np.abs(displacement[:, k]) <= calibration.axes[a].clip)
        e, pe = displacement[inside, k], predicted_e[inside, k]
        rmse = lambda x: float(np.sqrt(np.mean(x**2))) if len(x) else 0.0  # noqa: E731
        loaded = np.abs(e) > LOADED * np.abs(e).max() if len(e) else np.zeros(0, bool)
        rms_loaded = rmse(e[loaded])
        out[a] = {
            "n": int(len(e)),
            "n_loaded": int(loaded.sum()),
            "max_abs_displacement": float(np.abs(e).max()) if len(e) else 0.0,
            "rmse_force": rmse(predicted_force[inside, k] - wrench[inside, k]),
            "rmse_displacement": rmse(pe - e),
            "relative_rmse_displacement": rmse(pe[loaded] - e[loaded]) / rms_loaded if rms_loaded > 0 else None,
            "unit": DISPLACEMENT_UNITS[k],
        }
    return out


def plot_calibration(
    calibration: Calibration,
    displacement: np.ndarray,
    wrench: np.ndarray,
    path: str | Path,
    held_out: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    mask: np.ndarray | None = None,
) -> Path:
    """A PNG with one panel per axis: the pushes' (e, F~) samples that inform the axis (`mask`;
    held-out: (displacement, wrench, mask)) and the fitted line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(1, 4, figsize=(16, 3.6), constrained_layout=True)
    for k, (a, ax) in enumerate(zip(WRENCH_AXES, axs, strict=True)):
        m = np.ones(len(displacement), bool) if mask is None else np.asarray(mask, bool)[:, k]
        ax.scatter(displacement[m, k], wrench[m, k], s=3, c="k", alpha=0.5, label="fit pushes")
        if held_out is not None:
            hm = np.asarray(held_out[2], bool)[:, k]
            ax.scatter(held_out[0][hm, k], held_out[1][hm, k], s=3, c="tab:orange", alpha=0.5, label="held-out pushes")
        fit = calibration.axes[a]
        lo, hi = float(np.min(displacement[m, k])), float(np.max(displacement[m, k]))
        xs = np.linspace(max(lo, -fit.clip), min(hi, fit.clip), 200)
        ax.plot(xs, fit.force(xs), c="tab:blue", lw=2, label="piecewise-linear fit")
        for bp in fit.breakpoints:
            ax.axvline(bp, c="tab:blue", ls=":", lw=1)
        res = calibration.residuals.get("held_out", calibration.residuals.get("fit", {})).get(a, {})
        rel = res.get("relative_rmse_displacement")
        title = f"{a} vs {DISPLACEMENT_AXES[k]}: n = {int(m.sum())} fit"
        if held_out is not None:
            title += f", {int(hm.sum())} held-out"
        if rel is not None:
            title += f"  (displacement RMSE {100 * rel:.1f}%)"
        ax.set_title(title, fontsize=9)
        ax.set_xlabel(f"{DISPLACEMENT_AXES[k]} = x_d - x ({DISPLACEMENT_UNITS[k]})")
        ax.set_ylabel(f"raw {a}")
    axs[0].legend(fontsize=7)
    fig.suptitle(
        f"force calibration of sensor {calibration.sensor_id}: raw wrench vs displacement, "
        f"{len(displacement)} fit samples{f', {len(held_out[0])} held-out' if held_out is not None else ''}",
        fontsize=10,
    )
    path = Path(path)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


# ----------------------------------------------------------------------------- autonomous pushes
# the procedure (`PushConfig`, `PUSH_KINDS`) and the simulated pushes live with the simulated lab
# (envs.door_tactile.lab), imported where used so that the force_match stage loads without the env
@dataclass
class Push:
    """One recorded calibration push: its kind, seed and what was measured."""

    kind: str
    seed: int
    displacement: np.ndarray
    """(n, 4) sensor-frame e = x_d - x: ex, ey, ez (m), erz (rad)."""
    wrench: np.ndarray
    """(n, 4) raw readings F~."""
    mask: np.ndarray
    """(n, 4) which samples inform which axis: every axis during the normal approach (its lateral
    and rotational errors stay near zero), the moved axis and the normal one during a shear or
    torque move while the pad still touches (a lost contact says nothing about the gain)."""


def sensor_id(sim_model_id: str) -> str:
    """The id of a simulated scene's STS (calibrations name the sensor they belong to)."""
    return f"{sim_model_id}:sts"


MOVED_AXIS = {"shear_x": 0, "shear_y": 1, "torque": 3}


def push_mask(kind: str, moving: np.ndarray, wrench: np.ndarray, config: PushConfig) -> np.ndarray:
    """(n, 4) which of a push's samples inform which axis (see `Push.mask`): the samples of a
    shear or torque move (`moving`) inform only the moved and the normal axis, and only while the
    raw normal reading stays `contact_reading` above the push's first (resting) sample."""
    mask = np.ones(wrench.shape, bool)
    if kind in MOVED_AXIS:
        moving = np.asarray(moving, bool)
        touching = wrench[:, NORMAL] - wrench[0, NORMAL] > config.contact_reading
        mask[moving] = False
        for axis in (MOVED_AXIS[kind], NORMAL):
            mask[moving, axis] = touching[moving]
    return mask


def simulate_push(env: Any, kind: str, seed: int, config: PushConfig) -> Push:
    """One simulated push (`envs.door_tactile.lab.simulate_push`) with the samples each axis is
    fitted on (`push_mask`)."""
    from shiftkit.envs.door_tactile.lab import PUSH_KINDS
    from shiftkit.envs.door_tactile.lab import simulate_push as lab_push

    if kind not in PUSH_KINDS:
        raise ConfigError(f"unknown push kind {kind!r}; known: {', '.join(PUSH_KINDS)}")
    displacement, wrench, moving = lab_push(env, kind, seed, config)
    return Push(kind, seed, displacement, wrench, push_mask(kind, moving, wrench, config))


def fit_pushes(
    fit: list[Push],
    held: list[Push],
    sensor: str,
    provenance: dict[str, Any],
    breakpoints: tuple[int, ...] = DEFAULT_BREAKPOINTS,
    max_offset: tuple[float, ...] = DEFAULT_MAX_OFFSET,
) -> Calibration:
    """The calibration fitted on the `fit` pushes, with the residuals on the `held` ones."""
    stack = lambda pushes, attr: np.concatenate([getattr(q, attr) for q in pushes])  # noqa: E731
    provenance = {
        **provenance,
        "samples": {"fit": int(sum(len(q.wrench) for q in fit)), "held_out": int(sum(len(q.wrench) for q in held))},
    }
    calibration = fit_calibration(
        stack(fit, "displacement"),
        stack(fit, "wrench"),
        sensor,
        breakpoints=breakpoints,
        max_offset=max_offset,
        provenance=provenance,
        mask=stack(fit, "mask"),
    )
    if held:
        calibration.residuals["held_out"] = residuals(
            calibration, stack(held, "displacement"), stack(held, "wrench"), stack(held, "mask")
        )
    return calibration


def _tactile_env(env_name: str, task: str) -> tuple[Any, Any]:
    """The family and an env of a tactile env's task (one-line errors for any other)."""
    from shiftkit.envs import env_family, make

    try:
        family = env_family(env_name)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    if task not in family.tasks:
        raise ConfigError(
            f"env {env_name!r} has no task {task!r}: calibration pushes against the object of a tactile env's "
            "task (e.g. --env door-tactile --task knob-open)"
        )
    env = make(env_name, task)
    if not hasattr(env, "sensor") or not hasattr(env.physics, "grasp_pose"):
        env.close()
        raise ConfigError(f"env {env_name!r} has no tactile sensor and calibration object to push against")
    return family, env


def calibrate_env(
    env_name: str,
    task: str,
    fit_seeds: list[int],
    held_out_seeds: list[int],
    push: PushConfig | None = None,
    kinds: tuple[str, ...] | None = None,
    breakpoints: tuple[int, ...] = DEFAULT_BREAKPOINTS,
    max_offset: tuple[float, ...] = DEFAULT_MAX_OFFSET,
) -> tuple[Calibration, list[Push], list[Push]]:
    """Push (every kind, once per seed), fit on the `fit_seeds` pushes and report the residuals on
    the `held_out_seeds` pushes (`kinds`: default every kind of `PUSH_KINDS`). Returns the
    calibration and both push lists."""
    from shiftkit.envs.door_tactile.lab import PUSH_KINDS, PushConfig

    push = push or PushConfig()
    kinds = PUSH_KINDS if kinds is None else kinds
    family, env = _tactile_env(env_name, task)
    try:
        fit = [simulate_push(env, k, s, push) for s in fit_seeds for k in kinds]
        held = [simulate_push(env, k, s, push) for s in held_out_seeds for k in kinds]
    finally:
        env.close()
    provenance = {
        "procedure": "simulated autonomous pushes (shiftkit.transforms.force_calibration.simulate_push)",
        "env": env_name,
        "task": task,
        "sim_model": family.sim_model_id,
        "push_kinds": list(kinds),
        "fit_seeds": list(fit_seeds),
        "held_out_seeds": list(held_out_seeds),
        "push_config": asdict(push),
    }
    calibration = fit_pushes(fit, held, sensor_id(family.sim_model_id), provenance, breakpoints, max_offset)
    return calibration, fit, held


# ----------------------------------------------------------------------------- pushes on a real robot
PLAN_POSE_NAMES = ["x", "y", "z", "qx", "qy", "qz", "qw"]
PLAN_KIND = "shiftkit-calibration-plan"


def plan_push(kind: str, seed: int, config: PushConfig) -> dict[str, np.ndarray]:
    """The open-loop commanded poses of one push, one per control period, in the sensor frame of
    the contact pose (the pad just touching the object, normal +z into it): the push draws what
    `simulate_push` draws for the same seed (start gap, lateral jitter, press depth, direction),
    starts at the gap before the object, moves `travel` in `step`s along the normal (shear /
    torque pushes stop `press` past the step where contact shows, expected `contact_depth` into
    the object: a plan cannot watch the reading), then shears or rotates. Every step is held
    `settle_periods` periods; `sample` marks each step's last period (its reading joins the
    fit), `move` the periods of the shear / torque move."""
    from shiftkit.envs.door_tactile.lab import PUSH_KINDS

    if kind not in PUSH_KINDS:
        raise ConfigError(f"unknown push kind {kind!r}; known: {', '.join(PUSH_KINDS)}")
    rng = np.random.default_rng([seed, PUSH_KINDS.index(kind)])
    rng.integers(2**31)  # the simulated push's noise seed: the draws below stay those of simulate_push
    gap = rng.uniform(*config.start_gap)
    lateral = rng.uniform(-1, 1, 2) * config.jitter
    steps = int(round(config.travel / config.step))
    if kind != "normal":
        contact = int(np.floor((gap + config.contact_depth) / config.step)) + 1
        steps = min(steps, contact + int(round(rng.uniform(*config.press) / config.step)) - 1)
    moves = [(np.array([*lateral, k * config.step - gap]), 0.0, False) for k in range(steps + 1)]
    pressed = moves[-1][0]
    if kind in ("shear_x", "shear_y"):
        direction = np.eye(3)[MOVED_AXIS[kind]] * rng.choice([-1.0, 1.0])
        for k in range(1, int(round(config.shear / config.step)) + 1):
            moves.append((pressed + direction * config.step * k, 0.0, True))
    elif kind == "torque":
        sign = rng.choice([-1.0, 1.0])
        for k in range(1, int(round(config.rotation / config.rotation_step)) + 1):
            moves.append((pressed, sign * config.rotation_step * k, True))
    hold = config.settle_periods
    pose = np.array(
        [[*pos, 0.0, 0.0, np.sin(turn / 2), np.cos(turn / 2)] for pos, turn, _ in moves for _ in range(hold)]
    )
    sample = np.tile(np.arange(hold) == hold - 1, len(moves))
    move = np.repeat([m for _, _, m in moves], hold)
    return {"action": pose, "sample": sample, "move": move}


def write_calibration_plan(
    out: str | Path,
    fit_seeds: list[int],
    held_out_seeds: list[int],
    sensor: str,
    control_hz: int = 10,
    push: PushConfig | None = None,
    kinds: tuple[str, ...] | None = None,
) -> Path:
    """The push sequence for a robot to execute, in the raw episode format (docs/raw_format.md):
    one episode per push, `action` the commanded pose per control period (start-pose frame),
    `sample` / `move` flags, metadata with the push kind, seed and split (fit / held_out); `kinds`:
    default every kind of `PUSH_KINDS`."""
    from shiftkit.datasets.sources.raw import RawDatasetWriter
    from shiftkit.envs.door_tactile.lab import PUSH_KINDS, PushConfig

    push = push or PushConfig()
    kinds = PUSH_KINDS if kinds is None else kinds
    info = {
        "kind": PLAN_KIND,
        "sensor_id": sensor,
        "frame": "contact pose: the sensor frame with the pad just touching the object, normal +z into it",
        "push_config": asdict(push),
    }
    names = {"action": PLAN_POSE_NAMES}
    with RawDatasetWriter(out, fps=control_hz, robot="", env="", names=names, info=info) as writer:
        for split, seeds in (("fit", fit_seeds), ("held_out", held_out_seeds)):
            for seed in seeds:
                for kind in kinds:
                    arrays = plan_push(kind, seed, push)
                    writer.add_episode(
                        arrays={"timestamp": np.arange(len(arrays["action"])) / control_hz, **arrays},
                        meta={"task": f"calibration push: {kind}", "push_kind": kind, "seed": seed, "split": split},
                    )
    return Path(out)


RECORDED = {"action": "commanded pose", "observation.ee_pose": "measured pose", "observation.wrench": "raw wrench"}


def recorded_pushes(root: str | Path, push: PushConfig | None = None) -> tuple[list[Push], list[Push], dict]:
    """The fit and held-out pushes of a recorded calibration plan: per settled sample, e from the
    commanded pose (`action`) and the measured pose (`ee_pose`, the same frame) and the raw reading
    (`wrench_raw`). Returns them and the recording's `info`."""
    from shiftkit.datasets.errors import DatasetError
    from shiftkit.datasets.sources.raw import open_raw_dataset
    from shiftkit.envs.door_tactile.lab import PUSH_KINDS, PushConfig, pose_error
    from shiftkit.envs.geometry import quat_xyzw_to_matrix

    raw = open_raw_dataset(root)
    info = raw.index.get("info", {})
    if info.get("kind") != PLAN_KIND:
        raise DatasetError(f"{root}: not a recorded calibration plan (dataset.json info.kind {PLAN_KIND!r} expected)")
    push = push or PushConfig(**{**asdict(PushConfig()), **info.get("push_config", {})})
    pushes: dict[str, list[Push]] = {"fit": [], "held_out": []}
    for i in range(raw.num_episodes):
        ep = raw.read_episode(i)
        where = f"{raw.episode_dir(i)}"
        for key, what in (*RECORDED.items(), ("sample", "settled-sample flags"), ("move", "move flags")):
            if key not in ep.frames:
                raise DatasetError(f"{where}: no {key!r} array ({what}); record every array of the plan and these")
        kind, split = ep.meta.get("push_kind"), ep.meta.get("split")
        if kind not in PUSH_KINDS or split not in pushes:
            raise DatasetError(f"{where}/meta.json: needs the plan's 'push_kind' and 'split'")
        shapes = {k: ep.frames[k].shape[1] for k in RECORDED}
        if shapes != {"action": 7, "observation.ee_pose": 7, "observation.wrench": 4}:
            raise DatasetError(f"{where}: poses need 7 values (x, y, z, qx, qy, qz, qw), the wrench 4, got {shapes}")
        take = ep.frames["sample"][:, 0].astype(bool)
        commanded, measured = ep.frames["action"][take], ep.frames["observation.ee_pose"][take]
        wrench = ep.frames["observation.wrench"][take].astype(np.float64)
        c_rot, m_rot = quat_xyzw_to_matrix(commanded[:, 3:]), quat_xyzw_to_matrix(measured[:, 3:])
        e = np.array(
            [pose_error(c[:3], cr, m[:3], mr) for c, cr, m, mr in zip(commanded, c_rot, measured, m_rot, strict=True)]
        )
        mask = push_mask(kind, ep.frames["move"][take, 0].astype(bool), wrench, push)
        pushes[split].append(Push(kind, int(ep.meta.get("seed", i)), e, wrench, mask))
    if not pushes["fit"]:
        raise DatasetError(f"{root}: no push of the 'fit' split was recorded")
    return pushes["fit"], pushes["held_out"], info


def calibrate_recording(
    root: str | Path,
    sensor: str | None = None,
    breakpoints: tuple[int, ...] = DEFAULT_BREAKPOINTS,
    max_offset: tuple[float, ...] = DEFAULT_MAX_OFFSET,
) -> tuple[Calibration, list[Push], list[Push]]:
    """`calibrate_env`'s fit, file and residuals from a robot's recording of a calibration plan."""
    fit, held, info = recorded_pushes(root)
    sensor = sensor or info.get("sensor_id")
    if not sensor:
        raise ConfigError(f"{root}: the recording names no sensor; give --sensor-id")
    provenance = {
        "procedure": "recorded pushes of a calibration plan (shiftkit calibrate --plan, --from)",
        "recording": str(root),
        "push_kinds": sorted({q.kind for q in fit}),
        "fit_seeds": sorted({q.seed for q in fit}),
        "held_out_seeds": sorted({q.seed for q in held}),
        "push_config": info.get("push_config"),
    }
    return fit_pushes(fit, held, str(sensor), provenance, breakpoints, max_offset), fit, held


def execute_calibration_plan(plan: str | Path, out: str | Path, env_name: str, task: str) -> Path:
    """The simulated lab: the env's arm executes a calibration plan and its logger records the
    plan's arrays plus `ee_pose` (measured, start frame), `wrench_raw` and the simulator state."""
    from shiftkit.datasets.errors import DatasetError
    from shiftkit.datasets.loaders import load_array
    from shiftkit.datasets.sources.raw import RawDatasetWriter, open_raw_dataset
    from shiftkit.envs.door_tactile.lab import PUSH_KINDS, execute_pushes

    raw = open_raw_dataset(plan)
    info = raw.index.get("info", {})
    if info.get("kind") != PLAN_KIND:
        raise DatasetError(f"{plan}: not a calibration plan (dataset.json info.kind {PLAN_KIND!r} expected)")
    family, env = _tactile_env(env_name, task)
    names = {**raw.index.get("names", {}), "ee_pose": PLAN_POSE_NAMES}
    try:
        with RawDatasetWriter(out, fps=raw.fps, robot=family.robot, env=env_name, names=names, info=info) as writer:
            for i in range(raw.num_episodes):
                ep_dir = raw.episode_dir(i)
                arrays = {p.stem: load_array(p, "plan array") for p in sorted((ep_dir / "arrays").glob("*.npy"))}
                meta = raw.read_episode(i).meta
                # the sensor noise of the simulated push with this seed
                rng = np.random.default_rng([int(meta.get("seed", i)), PUSH_KINDS.index(meta.get("push_kind"))])
                rec = execute_pushes(env, int(rng.integers(2**31)), arrays["action"])
                writer.add_episode(
                    arrays={**arrays, **rec},
                    meta={k: v for k, v in meta.items() if k != "source_episode_index"}
                    | {"sim_model": family.sim_model_id},
                )
    finally:
        env.close()
    return Path(out)
