"""Forward kinematics, Jacobian and tool motion of the Gen3 with its suction tool, by pinocchio.

The model is built from the same joint table as the URDF (``gen3.JOINTS``), so it agrees with pybullet's forward
kinematics to 1e-5 m (tested). It is used to refine pybullet's IK answer by damped least squares (pybullet's
null-space IK alone leaves 5-20 mm of error on this arm, and the refinement needs thousands of FK calls per
episode) and to give the tool's velocity and acceleration along a trajectory, from which the held parcel's
inertial wrench follows (the hold check asks for it at every carrying step: 3 us in pinocchio, 70-90 in numpy).
"""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
from scipy.spatial.transform import Rotation

from parcelpick_env.robot.gen3 import EE_OFFSET, JOINTS

ARM_DOF = 7
_FLIP = np.diag([1.0, -1.0, -1.0])  # bracelet frame -> end-effector (and tool) frame: roll pi
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
        model = pin.Model()
        joint = 0
        placement = pin.SE3(Rotation.from_euler("z", base_yaw).as_matrix(), np.asarray(base_position, np.float64))
        for name, offset, roll, *_ in JOINTS:  # the parent frame moved by offset, rolled about x, then turned by q
            placement = placement * pin.SE3(_rot_x(roll), np.asarray(offset, dtype=np.float64))
            joint = model.addJoint(joint, pin.JointModelRZ(), placement, name)
            placement = pin.SE3.Identity()
        # the tool frame: the bracelet's, rolled by pi (x kept, z out of the cup), at the cup lip
        tip = pin.SE3(_FLIP, np.asarray(EE_OFFSET, dtype=np.float64) + [0.0, 0.0, -tool_length])
        self._tip = model.addFrame(pin.Frame("tool_tip", joint, tip, pin.FrameType.OP_FRAME))
        self._model, self._data = model, model.createData()

    def _placements(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Forward kinematics of ``q``: the tool's world position and rotation (columns x, y, z = approach)."""
        pin.forwardKinematics(self._model, self._data, np.asarray(q, dtype=np.float64))
        frame = pin.updateFramePlacement(self._model, self._data, self._tip)
        return frame.translation, frame.rotation

    def forward(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Tip position, tip axis (+z of the tool), joint axes (7,3) and joint origins (7,3), world."""
        tip, R = self._placements(q)
        joints = self._data.oMi
        axes = np.array([joints[i].rotation[:, 2] for i in range(1, ARM_DOF + 1)])
        origins = np.array([joints[i].translation for i in range(1, ARM_DOF + 1)])
        return tip, R[:, 2].copy(), axes, origins

    def tips(self, qs: np.ndarray) -> np.ndarray:
        """Tool-tip positions (K, 3) of K configurations (K, 7)."""
        qs = np.asarray(qs, dtype=np.float64).reshape(-1, ARM_DOF)
        return np.array([self._placements(q)[0] for q in qs]).reshape(-1, 3)

    def tool_pose(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tool-tip position and rotation matrix (columns: tool x, y, z = approach axis), world."""
        return self._placements(q)

    def tip_x(self, q: np.ndarray) -> np.ndarray:
        """The tool frame's x axis (world), i.e. the yaw of the cup about its axis."""
        return self._placements(q)[1][:, 0].copy()

    def jacobian(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Tip position, tip axis and the (6, 7) geometric Jacobian of the tip: rows linear, angular."""
        tip, R, J = self._frame_jacobian(q)
        return tip, R[:, 2].copy(), J

    def _frame_jacobian(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Tip position, tool rotation and the tip's (6, 7) Jacobian, world-aligned."""
        J = pin.computeFrameJacobian(self._model, self._data, np.asarray(q, dtype=np.float64), self._tip,
                                     pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
        frame = self._data.oMf[self._tip]  # a view of pinocchio's data: copied out
        return frame.translation.copy(), frame.rotation.copy(), J

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
            tip, R, J = self._frame_jacobian(q)
            cur_axis = R[:, 2].copy()
            e_pos = target - tip
            e_rot = cross_rows(cur_axis, axis)
            if x_axis is not None:
                cur_x = R[:, 0].copy()
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

        ``[v; omega] = J qd`` and ``[a; alpha] = J qdd + Jdot qd``, the tip's classical acceleration (the second
        derivative of its position, not the spatial one), from pinocchio's first and second order kinematics.
        """
        model, data, world = self._model, self._data, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
        pin.forwardKinematics(model, data, *(np.asarray(x, dtype=np.float64) for x in (q, qd, qdd)))
        frame = pin.updateFramePlacement(model, data, self._tip)
        twist = pin.getFrameVelocity(model, data, self._tip, world)
        accel = pin.getFrameClassicalAcceleration(model, data, self._tip, world)
        return frame.translation, frame.rotation, twist.linear, twist.angular, accel.linear, accel.angular
