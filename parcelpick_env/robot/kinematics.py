"""Forward kinematics, Jacobian and tool motion of the Gen3 with its suction tool, in numpy.

The same joint table as the URDF (``gen3.JOINTS``), so it agrees with pybullet's forward kinematics
to 1e-5 m (tested). It is used to refine pybullet's IK answer by damped least squares (pybullet's
null-space IK alone leaves 5-20 mm of error on this arm, and the refinement needs thousands of FK
calls per episode) and to give the tool's velocity and acceleration along a trajectory, from which
the held parcel's inertial wrench follows.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from parcelpick_env.robot.gen3 import EE_OFFSET, JOINTS

ARM_DOF = 7
_FLIP = np.diag([1.0, -1.0, -1.0])  # bracelet frame -> end-effector (and tool) frame: roll pi
JDOT_STEP = 1e-4  # s, central-difference step of J along qd for Jdot
_EYE6, _EYE_DOF = np.eye(6), np.eye(ARM_DOF)  # the IK loop's identities, made once (read only)
_EYE6.flags.writeable = _EYE_DOF.flags.writeable = False


def cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product without np.cross's per-call overhead (hot in the IK loop and the hold check);
    filled in place, not stacked. One pair of float64 3-vectors, the hot case, takes the same six products and
    three differences on Python floats (IEEE doubles, so the same bits) at a quarter of the cost."""
    if a.shape == (3,) and b.shape == (3,) and a.dtype == np.float64 and b.dtype == np.float64:
        a0, a1, a2 = a.tolist()
        b0, b1, b2 = b.tolist()
        return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


class Gen3Kinematics:
    """Tool-tip kinematics of the arm standing at ``base_position`` with ``base_yaw`` (world frame)."""

    def __init__(self, base_position, base_yaw: float, tool_length: float) -> None:
        self.base_R = np.array(Rotation.from_euler("z", base_yaw).as_matrix())
        self.base_p = np.asarray(base_position, dtype=np.float64)
        self.offsets = [np.array(j[1]) for j in JOINTS]
        self.rolls = [_rot_x(j[2]) for j in JOINTS]
        self.ee = np.array(EE_OFFSET)
        self.tip = np.array([0.0, 0.0, -tool_length])  # EE frame is bracelet rolled by pi: -z there
        self._last_R = np.eye(3)  # bracelet frame of the last forward(); tool x = its x, tool z = -its z

    def forward(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Tip position, tip axis (+z of the tool), joint axes (7,3) and joint origins (7,3), world."""
        R, t = self.base_R, self.base_p
        axes, origins = np.empty((ARM_DOF, 3)), np.empty((ARM_DOF, 3))
        rz = np.eye(3)
        for i in range(ARM_DOF):
            t = t + R @ self.offsets[i]
            R = R @ self.rolls[i]
            axes[i], origins[i] = R[:, 2], t
            c, s = math.cos(q[i]), math.sin(q[i])
            rz[0, 0], rz[0, 1], rz[1, 0], rz[1, 1] = c, -s, s, c
            R = R @ rz
        t = t + R @ self.ee
        tip = t + R @ self.tip
        self._last_R = R
        return tip, -R[:, 2], axes, origins

    def _chain(self, qs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``forward`` of K configurations (K, 7) at once: tips (K, 3), bracelet frames (K, 3, 3), joint axes
        and origins (K, 7, 3), world."""
        qs = np.asarray(qs, dtype=np.float64).reshape(-1, ARM_DOF)
        k = len(qs)
        R = np.broadcast_to(self.base_R, (k, 3, 3))
        t = np.broadcast_to(self.base_p, (k, 3))
        c, s = np.cos(qs), np.sin(qs)
        axes, origins = np.empty((k, ARM_DOF, 3)), np.empty((k, ARM_DOF, 3))
        rz = np.zeros((k, 3, 3))
        rz[:, 2, 2] = 1.0
        for i in range(ARM_DOF):
            t = t + R @ self.offsets[i]
            R = R @ self.rolls[i]
            axes[:, i], origins[:, i] = R[:, :, 2], t
            rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1] = c[:, i], -s[:, i], s[:, i], c[:, i]
            R = R @ rz
        return t + R @ (self.ee + self.tip), R, axes, origins

    def tips(self, qs: np.ndarray) -> np.ndarray:
        """Tool-tip positions (K, 3) of K configurations at once (batched ``forward``)."""
        return self._chain(qs)[0]

    def tool_pose(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tool-tip position and rotation matrix (columns: tool x, y, z = approach axis), world."""
        tip, _, _, _ = self.forward(q)
        return tip, self._last_R @ _FLIP

    def tip_x(self, q: np.ndarray) -> np.ndarray:
        """The tool frame's x axis (world), i.e. the yaw of the cup about its axis."""
        self.forward(q)
        return self._last_R[:, 0].copy()

    def jacobian(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Tip position, tip axis and the (6, 7) geometric Jacobian of the tip: rows linear, angular."""
        tip, axis, axes, origins = self.forward(q)
        J = np.empty((6, ARM_DOF))
        J[:3] = cross_rows(axes, tip - origins).T  # linear
        J[3:] = axes.T  # angular
        return tip, axis, J

    def refine(self, q: np.ndarray, target: np.ndarray, axis: np.ndarray, rest: np.ndarray, lower: np.ndarray,
               upper: np.ndarray, tol_p: float, tol_a: float, x_axis: np.ndarray | None = None,
               iterations: int = 60, damping: float = 0.02) -> np.ndarray | None:
        """Damped least squares on (position, axis[, yaw]) within the joint limits ``lower``/``upper``, with
        a null-space pull to ``rest``: joint angles with the tip within ``tol_p`` of ``target`` and the tool
        axis within ``tol_a`` (rad) of ``axis`` (and its x axis of ``x_axis``), or None. Pure numpy (the
        arm's IK refines pybullet's guesses with it; the oracle checks reachability with it)."""
        q = np.asarray(q, dtype=np.float64)
        regulariser = damping**2 * _EYE6
        for _ in range(iterations):
            tip, cur_axis, J = self.jacobian(q)
            e_pos = target - tip
            e_rot = cross_rows(cur_axis, axis)
            if x_axis is not None:
                cur_x = self._last_R[:, 0]
                e_x = cross_rows(cur_x, x_axis)
                if (np.linalg.norm(e_pos) < tol_p and np.linalg.norm(e_rot) < math.sin(tol_a)
                        and np.linalg.norm(e_x) < math.sin(tol_a) and cur_axis @ axis > 0 and cur_x @ x_axis > 0):
                    return q
                if cur_x @ x_axis > 0:  # standard small-angle orientation error over all three axes
                    e_y = cross_rows(cross_rows(cur_axis, cur_x), cross_rows(axis, x_axis))
                    e_rot = 0.5 * (e_rot + e_x + e_y)
                else:  # yaw near the antipode: turn about the tool axis first
                    e_rot = e_rot + 0.5 * cur_axis
            elif np.linalg.norm(e_pos) < tol_p and np.linalg.norm(e_rot) < math.sin(tol_a) and cur_axis @ axis > 0:
                return q
            if cur_axis @ axis < 0:  # pointing backwards: rotate about any perpendicular
                e_rot = cross_rows(cur_axis, np.array([1.0, 0.0, 0.0]) if abs(cur_axis[0]) < 0.9
                                   else np.array([0.0, 1.0, 0.0]))
            # without a yaw target the rotation about the tool axis is free: drop it from the task
            Ja = J[3:] if x_axis is not None else J[3:] - np.outer(cur_axis, cur_axis @ J[3:])
            A = np.vstack([J[:3], Ja])
            e = np.concatenate([e_pos, e_rot])
            JJt = A @ A.T + regulariser
            dq = A.T @ np.linalg.solve(JJt, e)
            N = _EYE_DOF - A.T @ np.linalg.solve(JJt, A)
            dq += N @ (0.1 * (rest - q))
            step = np.abs(dq).max()
            if step > 0.3:
                dq *= 0.3 / step
            q = np.clip(q + dq, lower, upper)
        return None

    def tool_motion(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Tool-tip (position, R, v, omega, a, alpha) in the world frame for joint state (q, qd, qdd).

        ``[v; omega] = J qd`` and ``[a; alpha] = J qdd + Jdot qd``, with ``Jdot qd`` a central
        difference of J along the motion (``J(q + h qd) - J(q - h qd)) / 2h``, exact to O(h^2)).
        """
        q, qd, qdd = (np.asarray(x, dtype=np.float64) for x in (q, qd, qdd))
        # the three configurations in one batched chain (a quarter of the cost of four ``forward`` calls)
        tips, R, axes, origins = self._chain(np.stack([q - JDOT_STEP * qd, q + JDOT_STEP * qd, q]))
        J = np.concatenate([cross_rows(axes, tips[:, None, :] - origins), axes], axis=2).transpose(0, 2, 1)
        twist = J[2] @ qd
        accel = J[2] @ qdd + (J[1] - J[0]) @ qd / (2.0 * JDOT_STEP)
        self._last_R = R[2]
        return tips[2], R[2] @ _FLIP, twist[:3], twist[3:], accel[:3], accel[3:]
