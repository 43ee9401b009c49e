"""Rotations in one place: 3x3 matrices, quaternions (x, y, z, w as datasets store them; MuJoCo's
w, x, y, z), rotation vectors and yaw rotations about z.

Arrays of rotations (a recording's poses) go through scipy's `Rotation`. Conversions of a single
rotation that run every control step (the impedance controller's pose error, an env's action and
observation) use MuJoCo's `mju_*` functions: scipy's `Rotation` costs 37 us (from a quaternion) to
170 us (from a matrix) per single rotation against MuJoCo's 5 us for the same conversion (measured
on 2026-12-02 at 38f366a, 2-core dev machine), several times a 500 Hz impedance step's own cost.
Quaternions returned in x, y, z, w have w >= 0, so a pose has one representation. MuJoCo and scipy
are imported by the functions that call them, so that the stages and commands that import this
module load without them (`shiftkit plan --stages` in 0.3 s instead of 0.8 s).
"""

from __future__ import annotations

import numpy as np


def rotation_z(angle: float) -> np.ndarray:
    """The 3x3 rotation by `angle` (rad) about the z axis."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def yaw_quat_wxyz(angle: float) -> np.ndarray:
    """MuJoCo's quaternion (w, x, y, z) of the rotation by `angle` (rad) about z."""
    return np.array([np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2)])


def quat_wxyz_to_xyzw(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions w, x, y, z (MuJoCo) -> x, y, z, w with w >= 0."""
    q = np.asarray(q)[..., [1, 2, 3, 0]]
    return np.where(q[..., 3:4] < 0, -q, q)


def quat_xyzw_to_wxyz(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions x, y, z, w -> w, x, y, z (MuJoCo)."""
    return np.asarray(q)[..., [3, 0, 1, 2]]


def quat_xyzw_to_matrix(quat: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions x, y, z, w (normalised here) -> (..., 3, 3) rotations."""
    from scipy.spatial.transform import Rotation

    quat = np.asarray(quat, dtype=np.float64)
    return Rotation.from_quat(quat.reshape(-1, 4)).as_matrix().reshape(*quat.shape[:-1], 3, 3)


def matrix_to_quat_xyzw(rot: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations -> (..., 4) quaternions x, y, z, w with w >= 0."""
    from scipy.spatial.transform import Rotation

    rot = np.asarray(rot, dtype=np.float64)
    quat = Rotation.from_matrix(rot.reshape(-1, 3, 3)).as_quat().reshape(*rot.shape[:-2], 4)
    return np.where(quat[..., 3:4] < 0, -quat, quat)


def quat_wxyz(rot: np.ndarray) -> np.ndarray:
    """MuJoCo's quaternion (w, x, y, z) of one 3x3 matrix, at control-step cost. Unlike scipy it
    accepts any matrix (a model spec's frame given by its axes keeps the orientation MuJoCo gives it)."""
    import mujoco

    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(rot, dtype=np.float64).ravel())
    return q


def quat_xyzw(rot: np.ndarray) -> np.ndarray:
    """The quaternion x, y, z, w (w >= 0) of one 3x3 rotation, at control-step cost."""
    return quat_wxyz_to_xyzw(quat_wxyz(rot))


def rotation_vector(rot: np.ndarray) -> np.ndarray:
    """The axis-angle vector of one 3x3 rotation, at control-step cost."""
    import mujoco

    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.ascontiguousarray(rot, dtype=np.float64).ravel())
    vec = np.zeros(3)
    mujoco.mju_quat2Vel(vec, quat, 1.0)
    return vec


def rotation_from_vector(vec: np.ndarray) -> np.ndarray:
    """The 3x3 rotation of one axis-angle vector, at control-step cost."""
    import mujoco

    q = np.zeros(4)
    angle = float(np.linalg.norm(vec))
    axis = vec / angle if angle > 1e-12 else np.array([1.0, 0.0, 0.0])
    mujoco.mju_axisAngle2Quat(q, axis, angle)
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, q)
    return mat.reshape(3, 3)
