"""The rotation helpers agree with each other and with scipy's `Rotation` on random rotations."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from shiftkit.envs.geometry import (
    matrix_to_quat_xyzw,
    quat_wxyz,
    quat_wxyz_to_xyzw,
    quat_xyzw,
    quat_xyzw_to_matrix,
    quat_xyzw_to_wxyz,
    rotation_from_vector,
    rotation_vector,
    rotation_z,
    yaw_quat_wxyz,
)

ROTATIONS = Rotation.random(64, random_state=0)


def test_batched_conversions_round_trip_with_w_non_negative():
    quats = ROTATIONS.as_quat()
    back = matrix_to_quat_xyzw(quat_xyzw_to_matrix(quats))
    assert (back[:, 3] >= 0).all()
    assert np.abs(back - np.where(quats[:, 3:] < 0, -quats, quats)).max() < 1e-12
    assert quat_xyzw_to_matrix(quats * 3.0) == pytest.approx(ROTATIONS.as_matrix(), abs=1e-12)  # normalised


def test_single_and_batched_shapes():
    rot = ROTATIONS[0].as_matrix()
    assert matrix_to_quat_xyzw(rot).shape == (4,) and quat_xyzw_to_matrix(ROTATIONS[0].as_quat()).shape == (3, 3)
    assert quat_xyzw_to_matrix(ROTATIONS.as_quat().reshape(8, 8, 4)).shape == (8, 8, 3, 3)


def test_control_step_conversions_match_the_batched_ones():
    mats = ROTATIONS.as_matrix()
    assert np.array([quat_xyzw(r) for r in mats]) == pytest.approx(matrix_to_quat_xyzw(mats), abs=1e-12)
    vecs = ROTATIONS.as_rotvec()
    assert np.array([rotation_vector(r) for r in mats]) == pytest.approx(vecs, abs=1e-9)
    assert np.array([rotation_from_vector(v) for v in vecs]) == pytest.approx(mats, abs=1e-12)
    assert rotation_from_vector(np.zeros(3)) == pytest.approx(np.eye(3))
    # a model spec's axes MuJoCo turns into a quaternion (the same rotation, either sign)
    assert quat_xyzw_to_matrix(quat_wxyz_to_xyzw(quat_wxyz(mats[0]))) == pytest.approx(mats[0], abs=1e-12)


@pytest.mark.parametrize("angle", [-3.0, -0.4, 0.0, 1.2, np.pi])
def test_yaw_rotations(angle):
    expected = Rotation.from_euler("z", angle)
    assert rotation_z(angle) == pytest.approx(expected.as_matrix(), abs=1e-12)
    xyzw = quat_wxyz_to_xyzw(yaw_quat_wxyz(angle))
    assert quat_xyzw_to_matrix(xyzw) == pytest.approx(expected.as_matrix(), abs=1e-12)
    assert quat_xyzw_to_wxyz(xyzw) == pytest.approx(yaw_quat_wxyz(angle))  # w = cos(angle / 2) >= 0 here
