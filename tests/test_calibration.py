"""Force calibration: the piecewise-linear fit recovers known gains, inverts them, and its file
format refuses other versions and sensors with one-line errors."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from shiftkit.datasets.errors import ConfigError
from shiftkit.transforms.force_calibration import (
    WRENCH_AXES,
    AxisFit,
    fit_calibration,
    load_calibration,
    plot_calibration,
)

# a sensor whose normal axis stiffens after 5 mm, shear axes of both signs, a torque axis
TRUE = {
    "Fx": AxisFit(0.02, [-120.0]),
    "Fy": AxisFit(-0.01, [90.0]),
    "Fz": AxisFit(0.05, [200.0, 520.0], [0.005]),
    "tau_z": AxisFit(0.0, [1.5]),
}


def synthetic_pushes(seed: int, n: int = 600, noise: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Displacements like calibration pushes (normal 0..2.5 cm, shear +-1 cm, rotation +-0.5 rad)
    with readings from TRUE plus noise."""
    rng = np.random.default_rng(seed)
    e = np.stack(
        [rng.uniform(-0.01, 0.01, n), rng.uniform(-0.01, 0.01, n), rng.uniform(0, 0.025, n), rng.uniform(-0.5, 0.5, n)],
        axis=1,
    )
    e[: n // 10] = 0.0  # out of contact
    f = np.stack([TRUE[a].force(e[:, k]) for k, a in enumerate(WRENCH_AXES)], axis=1)
    return e, f + rng.normal(0.0, noise, f.shape)


def test_fit_recovers_piecewise_gains_and_breakpoint():
    e, f = synthetic_pushes(0)
    cal = fit_calibration(e, f, "sts-test", provenance={"pushes": "synthetic"})
    for a in WRENCH_AXES:
        assert cal.axes[a].slopes == pytest.approx(TRUE[a].slopes, rel=0.03), a
        assert cal.axes[a].offset == pytest.approx(TRUE[a].offset, abs=0.02), a
    assert len(cal.axes["Fz"].breakpoints) == 1
    assert cal.axes["Fz"].breakpoints[0] == pytest.approx(0.005, abs=0.0007)
    assert cal.axes["Fz"].clip == 0.026  # offsets clipped at 2.6 cm (the reference robot's)
    assert cal.residuals["fit"]["Fz"]["max_abs_displacement"] == pytest.approx(0.025, abs=1e-3)
    # held-out pushes: the inverse (what force matching uses) predicts the displacement
    held_e, held_f = synthetic_pushes(1)
    pred = cal.displacement(held_f)
    for k, a in enumerate(WRENCH_AXES):
        rel = np.sqrt(np.mean((pred[:, k] - held_e[:, k]) ** 2)) / np.sqrt(np.mean(held_e[:, k] ** 2))
        assert rel < 0.05, a
    assert cal.residuals["fit"]["Fz"]["relative_rmse_displacement"] < 0.05


def test_inverse_is_exact_and_clipped():
    fit = AxisFit(0.1, [-200.0, -600.0], [0.004], clip=0.02)
    e = np.linspace(-0.02, 0.02, 81)
    assert fit.displacement(fit.force(e)) == pytest.approx(e, abs=1e-12)
    assert fit.displacement(fit.force(np.array([0.05, -0.05]))) == pytest.approx([0.02, -0.02])
    assert fit.displacement(np.array([0.1])) == pytest.approx([0.0])  # the offset reads as no displacement


def test_file_round_trip_and_plot(tmp_path):
    e, f = synthetic_pushes(2, n=200)
    cal = fit_calibration(e, f, "sts-A", provenance={"seeds": [0, 1]})
    path = cal.save(tmp_path / "calib.json")
    loaded = load_calibration(path, sensor_id="sts-A")
    assert loaded.axes == cal.axes and loaded.provenance == {"seeds": [0, 1]}
    assert loaded.displacement(f) == pytest.approx(cal.displacement(f))
    held_e, held_f = synthetic_pushes(3, n=50)
    from matplotlib.figure import Figure

    drawn = []
    save = Figure.savefig
    with pytest.MonkeyPatch.context() as mp:  # keep the figure the function writes, to read its titles
        mp.setattr(Figure, "savefig", lambda fig, *a, **k: (drawn.append(fig), save(fig, *a, **k))[1])
        png = plot_calibration(cal, e, f, tmp_path / "fit.png", held_out=(held_e, held_f, np.ones(held_e.shape, bool)))
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    (fig,) = drawn
    assert fig.get_suptitle().startswith("force calibration of sensor sts-A") and "200 fit samples, 50 held-out" in (
        fig.get_suptitle()
    )
    assert fig.axes[0].get_title().startswith("Fx vs ex: n = 200 fit, 50 held-out")


def test_bad_files_are_one_line_errors(tmp_path):
    e, f = synthetic_pushes(4, n=100)
    good = fit_calibration(e, f, "sts-A").to_json()
    cases = {
        "other_sensor": (good, "is for sensor 'sts-A', not 'sts-B'"),
        "version": ({**good, "version": 99}, "version 99 is not supported"),
        "format": ({**good, "format": "something"}, "not a shiftkit force calibration"),
        "slopes": (
            {**good, "axes": {**good["axes"], "Fz": {"offset": 0, "slopes": [1.0, -1.0], "breakpoints": [0.1]}}},
            "change sign",
        ),
        "missing": ({**good, "axes": {"Fx": good["axes"]["Fx"]}}, "axis 'Fy' needs"),
    }
    for name, (data, message) in cases.items():
        path = tmp_path / f"{name}.json"
        path.write_text(json.dumps(data))
        with pytest.raises(ConfigError, match=message) as info:
            load_calibration(path, sensor_id="sts-B" if name == "other_sensor" else None)
        assert "\n" not in str(info.value)
    (tmp_path / "broken.json").write_text("{not json")
    with pytest.raises(ConfigError, match="invalid JSON"):
        load_calibration(tmp_path / "broken.json")
    with pytest.raises(ConfigError, match="not found"):
        load_calibration(tmp_path / "nope.json")


def test_calibrate_command_on_the_simulated_sensor(tmp_path, capsys):
    """`shiftkit calibrate` pushes the door-tactile STS, fits it and writes the file and the plot;
    the fit recovers the sensor's hidden normal gain on held-out pushes."""
    from shiftkit.app.cli import main

    out = tmp_path / "calib.json"
    assert main(["calibrate", "--env", "door-tactile", "--out", str(out), "--pushes", "1", "--held-out", "1"]) == 0
    cal = load_calibration(out, sensor_id="door-tactile-v1:sts")
    assert (tmp_path / "calib.png").read_bytes()[:4] == b"\x89PNG"
    assert cal.provenance["fit_seeds"] == [0] and cal.provenance["held_out_seeds"] == [1]
    for axis in ("Fx", "Fy", "Fz"):
        assert cal.residuals["held_out"][axis]["relative_rmse_displacement"] < 0.15, axis
    assert "held_out displacement RMSE" in capsys.readouterr().out
    assert main(["calibrate", "--env", "panda-play", "--task", "lift", "--out", str(tmp_path / "x.json")]) == 2
    assert "has no tactile sensor" in capsys.readouterr().err


@pytest.mark.slow
def test_the_committed_calibration_is_what_its_documented_command_makes_today(tmp_path):
    """docs/force_matching_calibration.json (which the force-matched pipelines and figures use) is
    what `shiftkit calibrate` writes from the current scene with the command docs/force_matching.md
    gives: a change to the scene or the fit fails here until the file is regenerated."""
    from pathlib import Path

    from shiftkit.app.cli import main

    committed = Path(__file__).resolve().parents[1] / "docs" / "force_matching_calibration.json"
    out = tmp_path / "calib.json"
    argv = ["calibrate", "--env", "door-tactile", "--out", str(out), "--pushes", "3", "--held-out", "3"]
    assert main(argv) == 0
    fresh, kept = json.loads(out.read_text()), json.loads(committed.read_text())
    assert fresh["provenance"] == kept["provenance"]
    for axis, fit in kept["axes"].items():
        for key in ("slopes", "breakpoints", "offset"):
            np.testing.assert_allclose(
                fresh["axes"][axis][key], fit[key], rtol=1e-6, atol=1e-9, err_msg=f"{axis} {key}"
            )


def test_plan_executed_by_the_simulated_robot_fits_like_the_simulated_pushes(tmp_path, capsys):
    """`calibrate --plan` -> the door-tactile robot executes and records it (`sim-robot`) ->
    `calibrate --from` fits every slope within 2% of `calibrate`'s simulated pushes (same seeds)."""
    from shiftkit.app.cli import main

    assert main(["calibrate", "--out", str(tmp_path / "sim.json"), "--pushes", "2", "--held-out", "0"]) == 0
    assert main(["calibrate", "--plan", str(tmp_path / "plan"), "--pushes", "2", "--held-out", "1"]) == 0
    plan = json.loads((tmp_path / "plan" / "dataset.json").read_text())
    assert plan["fps"] == 10 and len(plan["episodes"]) == 12  # 3 seeds x 4 kinds
    first = np.load(tmp_path / "plan" / "episode_000000" / "arrays" / "action.npy")
    assert np.diff(first[2::3, 2]) == pytest.approx(np.full(35, 0.001))  # 1 mm steps, 3.5 cm travel
    assert main(["sim-robot", str(tmp_path / "plan"), "--out", str(tmp_path / "rec")]) == 0
    assert main(["calibrate", "--from", str(tmp_path / "rec"), "--out", str(tmp_path / "rec.json")]) == 0
    assert "held_out displacement RMSE" in capsys.readouterr().out
    sim = load_calibration(tmp_path / "sim.json")
    rec = load_calibration(tmp_path / "rec.json", sensor_id="door-tactile-v1:sts")
    assert rec.provenance["fit_seeds"] == [0, 1] and rec.provenance["held_out_seeds"] == [2]
    for axis in WRENCH_AXES:
        assert rec.axes[axis].slopes == pytest.approx(sim.axes[axis].slopes, rel=0.02), axis
    assert rec.residuals["held_out"]["Fz"]["relative_rmse_displacement"] < 0.15


def test_bad_plans_and_recordings_are_one_line_errors(tmp_path, capsys):
    from shiftkit.app.cli import main
    from shiftkit.datasets.sources.raw import RawDatasetWriter

    assert main(["calibrate", "--plan", str(tmp_path / "plan"), "--pushes", "1", "--held-out", "0"]) == 0
    capsys.readouterr()
    with RawDatasetWriter(tmp_path / "other", fps=10) as writer:
        writer.add_episode({"timestamp": np.arange(3) / 10, "action": np.zeros((3, 2))}, meta={"task": "t"})
    ep = tmp_path / "plan" / "episode_000000" / "arrays"
    broken = {"nowrench": tmp_path / "nowrench", "nan": tmp_path / "nan"}
    for folder in broken.values():
        shutil.copytree(tmp_path / "plan", folder)
        n = len(np.load(ep / "action.npy"))
        arrays = folder / "episode_000000" / "arrays"
        np.save(arrays / "ee_pose.npy", np.load(ep / "action.npy"))
        if folder.name == "nan":
            wrench = np.zeros((n, 4))
            wrench[5, 2] = np.nan
            np.save(arrays / "wrench_raw.npy", wrench)
    cases = [
        (["sim-robot", str(tmp_path / "other"), "--out", str(tmp_path / "r1")], "not a calibration plan"),
        (["sim-robot", str(tmp_path), "--out", str(tmp_path / "r2")], "not a plan"),
        (["calibrate", "--from", str(tmp_path / "other"), "--out", str(tmp_path / "c.json")], "not a recorded"),
        (
            ["calibrate", "--from", str(broken["nowrench"]), "--out", str(tmp_path / "c.json")],
            "no 'observation.wrench'",
        ),
        (["calibrate", "--from", str(broken["nan"]), "--out", str(tmp_path / "c.json")], "'wrench_raw' contains NaN"),
        (["calibrate", "--plan", str(tmp_path / "plan")], "give a new folder"),
        (["calibrate", "--from", str(tmp_path / "plan")], "give --out"),
    ]
    if Path("/proc/self").is_dir():  # a folder no one can create files in, root included: refused before the pushes
        cases.append((["calibrate", "--pushes", "1", "--out", "/proc/c.json"], "--out: cannot write into /proc"))
    for argv, message in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, (argv, err)
    assert not (tmp_path / "c.json").exists() and not (tmp_path / "r1").exists()
