"""Simulated STS sensor on the door-tactile scene: cost, contact signal and wrench-estimate accuracy.

1. Which contact signal (why `envs/sts.py` uses contact forces): a 1.8 cm sphere pressed on the
   pad with a known force, MuJoCo's built-in `tactile` sensor (a 7x7 taxel grid on the pad) against
   `mj_contactForce`; then a static shear force.
2. Cost: sensor frames/s (true wrench + F~, marker image, marker wrench estimate, visual image)
   against the scene's bare control step (10 Hz step: 50 physics steps under impedance control), at
   contact states of scripted-expert episodes.
3. Accuracy: Pearson correlation per axis between the marker estimate in the observation and the
   true contact wrench on the pad, over held-out kinesthetic episodes (seeds 1000+, every frame,
   approach included; 64 x 64 STS images).

Last line: JSON with metric `sts_tactile_frames_per_s` (goal: at least the 10 Hz control rate
with the bare step included, i.e. real time), plus the correlation table.
"""

from __future__ import annotations

import argparse
import json
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from shiftkit.envs import ENV_TASKS, make  # noqa: E402
from shiftkit.envs.door_tactile.experts import kinesthetic_rollout, rollout  # noqa: E402
from shiftkit.envs.door_tactile.physics import PAD_SOLIMP, PAD_SOLREF  # noqa: E402

AXES = ("Fx", "Fy", "Fz", "tau_z")


def contact_signal_table() -> list[dict[str, float]]:
    """Built-in tactile sensor vs contact force on a pad like the finger's (same gel parameters)."""
    xs, ys = np.linspace(-0.012, 0.012, 7), np.linspace(-0.01, 0.01, 7)
    taxels = " ".join(f"{x} {y} {z}" for z in (0.003, 0.0) for x in xs for y in ys)
    solref, solimp = " ".join(map(str, PAD_SOLREF)), " ".join(map(str, PAD_SOLIMP))
    xml = f"""<mujoco><asset><mesh name="taxels" vertex="{taxels}"/></asset>
    <option timestep="0.002" gravity="0 0 0" cone="elliptic" impratio="100"/>
    <worldbody><body pos="0 0 0.1"><geom name="pad" type="box" size="0.014 0.011 0.003"
      solref="{solref}" solimp="{solimp}" solmix="1000" friction="0.5 0.005 0.0001"/></body>
    <body pos="0.003 0.002 0.1215"><joint type="slide" axis="0 0 1" damping="5"/>
      <joint type="slide" axis="1 0 0" damping="5"/>
      <geom type="sphere" size="0.018" friction="0.7 0.005 0.0001"/></body></worldbody>
    <sensor><tactile name="tac" geom="pad" mesh="taxels"/></sensor></mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    rows = []
    f6 = np.zeros(6)
    for press, shear in ((0.5, 0.0), (2.0, 0.0), (5.0, 0.0), (10.0, 0.0), (10.0, 3.0)):
        mujoco.mj_resetData(model, data)
        data.qfrc_applied[:] = (-press, shear)
        mujoco.mj_step(model, data, nstep=300)
        readings = data.sensordata.reshape(3, -1)  # depth, slip x, slip y per taxel
        normal = tangential = 0.0
        for i in range(data.ncon):
            mujoco.mj_contactForce(model, data, i, f6)
            normal += f6[0]
            tangential += float(np.hypot(f6[1], f6[2]))
        rows.append(
            {
                "press_N": press,
                "shear_N": shear,
                "contact_normal_N": round(normal, 2),
                "contact_tangential_N": round(tangential, 2),
                "tactile_depth_sum_mm": round(float(readings[0].sum()) * 1000, 1),
                "tactile_taxels_touched": int((readings[0] > 1e-6).sum()),
                "tactile_slip_sum": round(float(np.abs(readings[1:]).sum()), 4),
            }
        )
    return rows


def contact_states(episodes: int) -> dict[str, list[tuple[np.ndarray, np.ndarray]]]:
    """Simulator states in contact from scripted-expert episodes, per task."""
    states: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    for task in ENV_TASKS["door-tactile"]:
        env = make("door-tactile", task)
        states[task] = []
        for seed in range(episodes):
            r = rollout(env, seed)
            touching = np.flatnonzero(r.observations[:, 23] > 0.5)
            states[task] += [(r.qpos[t], r.qvel[t]) for t in touching[:: max(1, len(touching) // 10)]]
        env.close()
    return states


def timing(states: dict[str, list[tuple[np.ndarray, np.ndarray]]], repeats: int) -> dict[str, float]:
    """Per-frame seconds of the bare step and of each sensor part (median over states)."""
    parts: dict[str, list[float]] = {k: [] for k in ("bare_step", "wrench", "tactile_image", "estimate", "visual")}
    for task, pairs in states.items():
        env = make("door-tactile", task)
        env.reset(seed=0)
        s, p = env.sensor, env.physics
        for qpos, qvel in pairs:
            env.set_sim_state(qpos, qvel)
            t0 = time.perf_counter()
            for _ in range(repeats):
                p.simulate(p.n_substeps)
            parts["bare_step"].append((time.perf_counter() - t0) / repeats)
            env.set_sim_state(qpos, qvel)
            t0 = time.perf_counter()
            for _ in range(repeats):
                s.raw_wrench(s.contact_wrench(p.data))
            parts["wrench"].append((time.perf_counter() - t0) / repeats)
            t0 = time.perf_counter()
            for _ in range(repeats):
                image = s.tactile_image(p.data)
            parts["tactile_image"].append((time.perf_counter() - t0) / repeats)
            t0 = time.perf_counter()
            for _ in range(repeats):
                env.estimator.update(image)
            parts["estimate"].append((time.perf_counter() - t0) / repeats)
            t0 = time.perf_counter()
            for _ in range(repeats):
                s.visual_image(p.data)
            parts["visual"].append((time.perf_counter() - t0) / repeats)
        env.close()
    return {k: float(np.median(v)) for k, v in parts.items()}


def correlations(episodes: int, first_seed: int = 1000) -> dict[str, dict[str, float]]:
    """Pearson r per axis (estimate vs true pad wrench) over every frame, per task and overall."""
    table: dict[str, dict[str, float]] = {}
    est_all, true_all = [], []
    for task in ENV_TASKS["door-tactile"]:
        env = make("door-tactile", task, width=64, height=64)
        est, true = [], []
        for seed in tqdm(range(first_seed, first_seed + episodes), desc=task, leave=False):
            r = kinesthetic_rollout(env, seed)
            tactile = r.observations[:, 18] > 0.5  # freedrive records in tactile mode
            est.append(r.observations[tactile, 14:18])
            true.append(r.observations[tactile, 21:25])
        env.close()
        e, t = np.concatenate(est), np.concatenate(true)
        est_all.append(e)
        true_all.append(t)
        table[task] = {a: round(float(np.corrcoef(e[:, i], t[:, i])[0, 1]), 3) for i, a in enumerate(AXES)}
        table[task]["frames"] = len(e)
    e, t = np.concatenate(est_all), np.concatenate(true_all)
    table["all"] = {a: round(float(np.corrcoef(e[:, i], t[:, i])[0, 1]), 3) for i, a in enumerate(AXES)}
    table["all"]["frames"] = len(e)
    return table


def figure(path: str) -> None:
    """Visual- and tactile-mode STS images without and with contact (knob-open, scripted expert)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    env = make("door-tactile", "knob-open", width=64, height=64)
    r = rollout(env, seed=3)
    free = max(0, int(np.argmax(r.observations[:, 23] > 0.05)) - 2)  # just before first contact
    touch = int(np.argmax(r.observations[:, 23]))
    fig, axes = plt.subplots(2, 2, figsize=(6, 6.4))
    for col, (t, label) in enumerate(
        ((free, "no contact"), (touch, f"contact, Fz = {r.observations[touch, 23]:.1f} N"))
    ):
        env.set_sim_state(r.qpos[t], r.qvel[t])
        for row, mode in enumerate(("visual", "tactile")):
            env.sensor.set_mode(mode)
            image = env.sensor.image(env.physics.data)
            axes[row, col].imshow(image, interpolation="nearest")
            axes[row, col].set_title(f"{mode} mode, {label}", fontsize=9)
            axes[row, col].axis("off")
    fig.suptitle("Simulated STS (64 x 64), knob-open", fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    env.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="1 episode per task for timing and correlation")
    parser.add_argument("--episodes", type=int, default=5, help="held-out kinesthetic episodes per task")
    parser.add_argument("--figure", metavar="PNG", help="also write the STS image figure (docs/door_tactile_sts.png)")
    args = parser.parse_args()
    if args.figure:
        figure(args.figure)
    start = time.time()
    signal = contact_signal_table()
    print("contact signal: sphere pressed on the pad")
    print(
        f"{'press N':>8s} {'shear N':>8s} {'contact Fn':>10s} {'contact Ft':>10s} {'tactile depth mm':>17s} {'taxels':>7s}"
    )
    for row in signal:
        print(
            f"{row['press_N']:8.1f} {row['shear_N']:8.1f} {row['contact_normal_N']:10.2f} "
            f"{row['contact_tangential_N']:10.2f} {row['tactile_depth_sum_mm']:17.1f} {row['tactile_taxels_touched']:7d}"
        )
    n = 1 if args.quick else args.episodes
    cost = timing(contact_states(1 if args.quick else 2), repeats=3 if args.quick else 10)
    sensor = cost["wrench"] + cost["tactile_image"] + cost["estimate"]
    tactile_fps = 1.0 / (cost["bare_step"] + sensor)
    print("cost per frame (ms): " + ", ".join(f"{k} {v * 1000:.2f}" for k, v in cost.items()))
    table = correlations(n)
    print(f"{'task':18s} " + " ".join(f"{a:>7s}" for a in AXES) + "  frames")
    for task, row in table.items():
        print(f"{task:18s} " + " ".join(f"{row[a]:7.3f}" for a in AXES) + f"  {row['frames']}")
    print(
        json.dumps(
            {
                "bench": "sts_sensor",
                "metric": "sts_tactile_frames_per_s",
                "value": round(tactile_fps, 1),
                "goal": 10.0,
                "higher_is_better": True,
                "bare_step_per_s": round(1.0 / cost["bare_step"], 1),
                "sensor_only_frames_per_s": round(1.0 / sensor, 1),
                "visual_frames_per_s": round(1.0 / cost["visual"], 1),
                "ms_per_frame": {k: round(v * 1000, 3) for k, v in cost.items()},
                "estimate_correlation": table,
                "held_out_episodes_per_task": n,
                "contact_signal": signal,
                "seconds": round(time.time() - start, 1),
            }
        )
    )


if __name__ == "__main__":
    main()
