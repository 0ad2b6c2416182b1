"""Inverse kinematics: damped least squares on MuJoCo's Jacobians.

One step moves the arm joints by Δq = Jᵀ (J Jᵀ + λ² I)⁻¹ e, the joint move of least norm that
reduces the end-effector error e (position, and optionally orientation as a rotation vector
weighted by ``ROTATION_WEIGHT``) with the damping λ keeping steps bounded near singular poses.
Steps repeat, clipped to the joint ranges, until the error is within tolerance.

``Kinematics`` works on its own ``MjData`` of the compiled model, so solving never disturbs the
simulation; a target it cannot reach within tolerance is reported (``IkResult.converged``).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from phirie_jax.rotations import matrix_to_rotvec

DAMPING = 0.03           # λ, in metres (the rotation rows are weighted into metres)
ROTATION_WEIGHT = 0.2    # m per rad: how a rotation error weighs against a position error
MAX_STEP = 0.25          # rad: the largest joint move of one step (norm)
POSITION_TOL = 2e-3      # m
ROTATION_TOL = 0.02      # rad
ITERATIONS = 300


def dls_step(jacobian: np.ndarray, error: np.ndarray, damping: float = DAMPING) -> np.ndarray:
    """Δq (n,) = Jᵀ (J Jᵀ + λ² I)⁻¹ e for a Jacobian (m, n) and an error (m,)."""
    jacobian = np.asarray(jacobian, np.float64)
    gram = jacobian @ jacobian.T + damping**2 * np.eye(jacobian.shape[0])
    return jacobian.T @ np.linalg.solve(gram, np.asarray(error, np.float64))


@dataclasses.dataclass(frozen=True)
class IkResult:
    q: np.ndarray               # (n,) arm joints
    position_error: float       # m
    rotation_error: float       # rad (0 when no orientation was asked)
    converged: bool


class Kinematics:
    """Forward and inverse kinematics of a site driven by some joints of a compiled model.

    Args:
        model: the compiled ``mujoco.MjModel`` (the whole scene, or the robot alone).
        site: the end-effector site's name.
        joints: the arm joints' names (hinge or slide), in the order of ``q``.
    """

    def __init__(self, model, site: str, joints: tuple[str, ...]):
        import mujoco

        self.model = model
        self.data = mujoco.MjData(model)
        self.site = model.site(site).id
        ids = [model.joint(j).id for j in joints]
        self.qpos = np.array([model.jnt_qposadr[j] for j in ids])
        self.dofs = np.array([model.jnt_dofadr[j] for j in ids])
        limited = model.jnt_limited[ids].astype(bool)
        self.low = np.where(limited, model.jnt_range[ids, 0], -np.inf)
        self.high = np.where(limited, model.jnt_range[ids, 1], np.inf)

    def forward(self, q) -> tuple[np.ndarray, np.ndarray]:
        """Site position (3,) and rotation (3, 3) at arm configuration ``q`` (n,)."""
        import mujoco

        self.data.qpos[self.qpos] = q
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_comPos(self.model, self.data)  # the Jacobian needs the motion axes (cdof)
        return self.data.site_xpos[self.site].copy(), self.data.site_xmat[self.site].reshape(3, 3).copy()

    def jacobian(self, q) -> np.ndarray:
        """(6, n) world-frame Jacobian of the site (linear rows, then angular) at ``q``."""
        import mujoco

        self.forward(q)
        jacp, jacr = np.zeros((3, self.model.nv)), np.zeros((3, self.model.nv))
        mujoco.mj_jacSite(self.model, self.data, jacp, jacr, self.site)
        return np.concatenate([jacp[:, self.dofs], jacr[:, self.dofs]])

    def error(self, q, position, rotation=None) -> np.ndarray:
        """(3,) or (6,) error of the site at ``q`` towards the target (rotation vector in world axes)."""
        pos, rot = self.forward(q)
        e = np.asarray(position, np.float64) - pos
        if rotation is None:
            return e
        turn = matrix_to_rotvec(np.asarray(rotation, np.float64) @ rot.T)
        return np.concatenate([e, ROTATION_WEIGHT * turn])

    def solve(self, position, rotation=None, q0=None, iterations: int = ITERATIONS,
              position_tol: float = POSITION_TOL, rotation_tol: float = ROTATION_TOL) -> IkResult:
        """Arm joints that put the site at ``position`` (3,) (and ``rotation`` (3, 3)), from ``q0``."""
        q = np.clip(np.asarray(q0 if q0 is not None else np.zeros(len(self.qpos)), np.float64), self.low, self.high)
        rows = 3 if rotation is None else 6
        for _ in range(iterations + 1):
            e = self.error(q, position, rotation)
            pos_err = float(np.linalg.norm(e[:3]))
            rot_err = float(np.linalg.norm(e[3:]) / ROTATION_WEIGHT) if rows == 6 else 0.0
            if pos_err <= position_tol and rot_err <= rotation_tol:
                return IkResult(q, pos_err, rot_err, True)
            jac = self.jacobian(q)[:rows]
            if rows == 6:
                jac[3:] *= ROTATION_WEIGHT
            step = dls_step(jac, e)
            norm = float(np.linalg.norm(step))
            if norm > MAX_STEP:
                step *= MAX_STEP / norm
            q = np.clip(q + step, self.low, self.high)
        return IkResult(q, pos_err, rot_err, False)
