"""Force matching: replay poses x_rep = A^-1 (F~ - b) + x_raw in the sensor frame."""

from __future__ import annotations

import numpy as np
import pytest

from shiftkit.transforms.force_calibration import AxisFit, Calibration
from shiftkit.transforms.force_matching import (
    force_matched_poses,
    matrix_to_quat_xyzw,
    median_filter,
    quat_xyzw_to_matrix,
)


def linear_calibration(offset: float = 0.0) -> Calibration:
    axes = {
        "Fx": AxisFit(offset, [100.0], clip=0.02),
        "Fy": AxisFit(offset, [-100.0], clip=0.02),
        "Fz": AxisFit(offset, [200.0, 400.0], [0.005], clip=0.026),
        "tau_z": AxisFit(offset, [2.0], clip=1.0),
    }
    return Calibration("test", axes)


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1
    return np.concatenate([rng.uniform(-0.5, 0.5, (n, 3)), q], axis=1)


def test_median_filter_removes_spikes_and_keeps_steps():
    x = np.zeros((9, 2))
    x[4, 0] = 10.0  # a one-frame spike
    x[6:, 1] = 1.0  # a step
    out = median_filter(x, 3)
    assert out[:, 0].tolist() == [0.0] * 9
    assert out[:, 1].tolist() == x[:, 1].tolist()
    assert median_filter(x, 1).tolist() == x.tolist()


def test_quaternion_round_trip():
    poses = random_poses(20)
    assert matrix_to_quat_xyzw(quat_xyzw_to_matrix(poses[:, 3:])) == pytest.approx(poses[:, 3:], abs=1e-12)


def test_zero_force_is_position_replay():
    poses = random_poses(12)
    assert np.array_equal(force_matched_poses(poses, np.zeros((12, 4)), linear_calibration(), 5)[:, :3], poses[:, :3])
    rep = force_matched_poses(poses, np.full((12, 4), 0.3), linear_calibration(offset=0.3), 5)
    assert rep == pytest.approx(poses, abs=1e-12)


def test_offsets_in_the_sensor_frame():
    poses = random_poses(6, seed=3)
    rot = quat_xyzw_to_matrix(poses[:, 3:])
    wrench = np.tile([1.0, 0.5, 2.0, 0.2], (6, 1))  # constant: the median filter keeps it
    rep = force_matched_poses(poses, wrench, linear_calibration(), 3)
    # Fx / 100, Fy / -100, Fz past the 5 mm breakpoint on the second slope, tau_z / 2
    e = np.array([0.01, -0.005, 0.005 + (2.0 - 200.0 * 0.005) / 400.0, 0.1])
    assert rep[:, :3] == pytest.approx(poses[:, :3] + np.einsum("tij,j->ti", rot, e[:3]), abs=1e-12)
    turn = quat_xyzw_to_matrix(rep[:, 3:]) @ np.transpose(rot, (0, 2, 1))  # world-frame rotation R_rep R^T
    local = np.transpose(rot, (0, 2, 1)) @ turn @ rot  # in the sensor frame: about z by erz
    angle = np.arctan2(local[:, 1, 0], local[:, 0, 0])
    assert angle == pytest.approx(np.full(6, 0.1), abs=1e-12)
    assert local[:, 2, 2] == pytest.approx(np.ones(6), abs=1e-12)


def test_offsets_are_clipped():
    poses = random_poses(3)
    rep = force_matched_poses(poses, np.tile([0.0, 0.0, 1e6, 0.0], (3, 1)), linear_calibration(), 1)
    assert np.linalg.norm(rep[:, :3] - poses[:, :3], axis=1) == pytest.approx(np.full(3, 0.026))
