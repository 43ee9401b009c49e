"""`force_match`: replay kinesthetic demonstrations so that the replay presses as the person did
(thesis §4.3.6, SPEC §5.2).

Kinesthetic teaching records the sensor poses x_raw,t and the unscaled tactile wrench F~_raw,t.
Under an impedance controller a replay of x_raw alone loses the contact force, since the force
comes from the error between the commanded and the reached pose. Force matching offsets each
replayed pose by the displacement that the calibration says produces the recorded reading,

    x_rep,t = A^-1 (F~_raw,t - b) + x_raw,t,

in the sensor frame (translation (ex, ey, ez), rotation erz about the pad normal as a rotation
vector), with F~ median-filtered over time first. With a zero offset (zero force against a
calibration without offset) it is exactly position replay.
"""

from __future__ import annotations

import mujoco
import numpy as np

from shiftkit.transforms.force_calibration import Calibration


def median_filter(values: np.ndarray, kernel: int) -> np.ndarray:
    """Running median over the first axis (odd `kernel`, edges repeat the end values)."""
    if kernel <= 1:
        return np.asarray(values, dtype=np.float64).copy()
    half = kernel // 2
    padded = np.concatenate([np.repeat(values[:1], half, 0), values, np.repeat(values[-1:], half, 0)])
    windows = np.lib.stride_tricks.sliding_window_view(padded, kernel, axis=0)
    return np.median(windows, axis=-1)


def quat_xyzw_to_matrix(quat: np.ndarray) -> np.ndarray:
    """(T, 4) quaternions x, y, z, w (the raw format's `ee_pose` order) -> (T, 3, 3) rotations."""
    out = np.zeros((len(quat), 9))
    for i, q in enumerate(np.asarray(quat, dtype=np.float64)):
        mujoco.mju_quat2Mat(out[i], q[[3, 0, 1, 2]] / np.linalg.norm(q))
    return out.reshape(-1, 3, 3)


def matrix_to_quat_xyzw(rot: np.ndarray) -> np.ndarray:
    """(T, 3, 3) rotations -> (T, 4) quaternions x, y, z, w with w >= 0."""
    out = np.zeros((len(rot), 4))
    q = np.zeros(4)
    for i, r in enumerate(np.asarray(rot, dtype=np.float64)):
        mujoco.mju_mat2Quat(q, np.ascontiguousarray(r).ravel())
        out[i] = (q if q[0] >= 0 else -q)[[1, 2, 3, 0]]
    return out


def force_matched_poses(
    ee_pose: np.ndarray, wrench: np.ndarray, calibration: Calibration, median_kernel: int = 5
) -> np.ndarray:
    """x_rep for (T, 7) poses (position, quaternion xyzw; sensor frame = the pose's frame) and
    (T, 4) raw readings (Fx, Fy, Fz, tau_z): each pose moved by the calibrated displacement of its
    median-filtered reading, expressed in its own sensor frame."""
    ee_pose = np.asarray(ee_pose, dtype=np.float64)
    offset = calibration.displacement(median_filter(np.asarray(wrench, dtype=np.float64), median_kernel))
    rot = quat_xyzw_to_matrix(ee_pose[:, 3:7])
    pos = ee_pose[:, :3] + np.einsum("tij,tj->ti", rot, offset[:, :3])
    c, s = np.cos(offset[:, 3]), np.sin(offset[:, 3])
    turn = np.zeros((len(offset), 3, 3))
    turn[:, 0, 0], turn[:, 0, 1], turn[:, 1, 0], turn[:, 1, 1], turn[:, 2, 2] = c, -s, s, c, 1.0
    return np.concatenate([pos, matrix_to_quat_xyzw(rot @ turn)], axis=1)
