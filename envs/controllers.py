"""Cartesian controllers shared by the scenes: differential inverse kinematics from MuJoCo Jacobians."""

from __future__ import annotations

import mujoco
import numpy as np

from shiftkit.envs.geometry import rotation_vector


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


class CartesianImpedance:
    """Cartesian impedance control of a site in joint torque, from MuJoCo Jacobians (the Franka /
    Polymetis default controller's law): tau = J^T (K e - D v) + N (k_n (q_home - q) - d_n dq), with
    e the pose error (position, rotation vector in the world frame), v the site twist, D = 2 zeta
    sqrt(K Lambda) from the diagonal of the task-space inertia Lambda = (J M^-1 J^T)^-1 (near-critical
    damping whatever the arm's posture), and N the dynamically consistent null-space projector that
    keeps the posture term from disturbing the site. Gravity is left to the model (`gravcomp`).
    Call `torque` between `mj_step1` and `mj_step2` so it sees the current state."""

    def __init__(
        self,
        model: mujoco.MjModel,
        site: int,
        qpos: slice,
        dofs: slice,
        home: np.ndarray,
        torque_limit: np.ndarray,
        stiffness: tuple[float, float] = (550.0, 30.0),
        damping_ratio: float = 1.0,
        null_stiffness: float = 5.0,
        null_damping: float = 1.0,
    ) -> None:
        self.model, self.site, self.qpos, self.dofs = model, site, qpos, dofs
        self.home, self.torque_limit = np.asarray(home, float), np.asarray(torque_limit, float)
        self.stiffness = np.repeat(np.asarray(stiffness, float), 3)
        self.damping_ratio = damping_ratio
        self.null_stiffness, self.null_damping = null_stiffness, null_damping
        self._jac = np.zeros((6, model.nv))
        self._minv_j = np.zeros((6, model.nv))

    def torque(
        self,
        data: mujoco.MjData,
        target_pos: np.ndarray,
        target_rot: np.ndarray,
        stiffness_scale: float = 1.0,
        min_damping: float = 0.0,
    ) -> np.ndarray:
        """Joint torques (clipped to the limits) pulling the site to (`target_pos`, `target_rot`).
        `stiffness_scale` = 0 gives freedrive (damping only, at least `min_damping` per unit of
        task-space inertia)."""
        m, d = self.model, data
        mujoco.mj_jacSite(m, d, self._jac[:3], self._jac[3:], self.site)
        rot = d.site_xmat[self.site].reshape(3, 3)
        err = np.concatenate((target_pos - d.site_xpos[self.site], rotation_vector(target_rot @ rot.T)))
        dq = d.qvel[self.dofs]
        jac = self._jac[:, self.dofs]
        # rows of J M^-1 over all dofs (the arm's columns are what is used)
        mujoco.mj_solveM(m, d, self._minv_j, self._jac)
        minv_jt = self._minv_j[:, self.dofs].T
        lam = np.linalg.inv(jac @ minv_jt + 1e-6 * np.eye(6))
        k = self.stiffness * stiffness_scale
        damping = 2.0 * self.damping_ratio * np.sqrt(k * np.diag(lam))
        damping = np.maximum(damping, min_damping * np.diag(lam))
        wrench = k * err - damping * (jac @ dq)
        tau = jac.T @ wrench
        # dynamically consistent null space: N = I - J^T (Lambda J M^-1)
        null = np.eye(jac.shape[1]) - jac.T @ (lam @ minv_jt.T)
        q = d.qpos[self.qpos]
        tau += null @ (self.null_stiffness * (self.home - q) - self.null_damping * dq)
        return tau.clip(-self.torque_limit, self.torque_limit)
