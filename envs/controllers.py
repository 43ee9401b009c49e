"""Cartesian controllers shared by the scenes: differential inverse kinematics from MuJoCo Jacobians."""

from __future__ import annotations

import mujoco
import numpy as np


def _rotation_error_matrix(rotation: np.ndarray) -> np.ndarray:
    """(3, 9) matrix C with C @ R.ravel() = the small-angle rotation from a site orientation R to
    `rotation`: the skew-symmetric part of E = rotation @ R.T, (E21 - E12, E02 - E20, E10 - E01) / 2,
    which is linear in R (one matrix product per IK step)."""
    c = np.zeros((3, 3, 3))
    for k, (i, j) in enumerate(((2, 1), (0, 2), (1, 0))):
        c[k, j] += 0.5 * rotation[i]  # E_ij = rotation[i] . R[j]
        c[k, i] -= 0.5 * rotation[j]
    return c.reshape(3, 9)


class FixedOrientationIK:
    """Damped least-squares differential IK of a site's position with its orientation held at
    `rotation`, plus a null-space pull towards a home posture (keeps the elbow up and away from
    joint limits). `step` evaluates kinematics on a scratch `MjData`, never the simulated one."""

    def __init__(
        self,
        model: mujoco.MjModel,
        site: int,
        qpos: slice,
        dofs: slice,
        rotation: np.ndarray,
        home: np.ndarray,
        low: np.ndarray,
        high: np.ndarray,
        damping: float = 1e-4,
        posture_gain: float = 0.05,
        max_dq: float = 0.2,
    ) -> None:
        self.model, self.site, self.qpos, self.dofs = model, site, qpos, dofs
        self.home, self.low, self.high = home, low, high
        self.posture_gain, self.max_dq = posture_gain, max_dq
        self._rotation_error = _rotation_error_matrix(np.asarray(rotation, dtype=np.float64))
        self._damping = damping * np.eye(6)
        self._jac = np.zeros((6, model.nv))  # rows 0:3 translation, 3:6 rotation
        self._sol = np.zeros(6)

    def step(self, data: mujoco.MjData, q: np.ndarray, target: np.ndarray) -> np.ndarray:
        """One IK update: the joint positions moved from `q` towards the site at `target`."""
        m = self.model
        data.qpos[self.qpos] = q
        mujoco.mj_kinematics(m, data)
        mujoco.mj_comPos(m, data)
        mujoco.mj_jacSite(m, data, self._jac[:3], self._jac[3:], self.site)
        err = np.concatenate((target - data.site_xpos[self.site], self._rotation_error @ data.site_xmat[self.site]))
        jac = self._jac[:, self.dofs]
        posture = self.posture_gain * (self.home - q)
        # dq = J^T (J J^T + D)^-1 (err - J posture) + posture; MuJoCo's 6x6 Cholesky costs a
        # fraction of numpy.linalg's per-call overhead
        a = jac @ jac.T + self._damping
        mujoco.mju_cholFactor(a, 0.0)
        mujoco.mju_cholSolve(self._sol, a, err - jac @ posture)
        dq = (jac.T @ self._sol + posture).clip(-self.max_dq, self.max_dq)  # large errors converge over calls
        return (q + dq).clip(self.low, self.high)
