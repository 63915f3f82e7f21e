"""The Gen3 arm in a pybullet world: loading, verified IK with joint limits, bounded-speed motion, contacts.

Motion is joint-space at a bounded joint speed in simulated time. Every move follows a cosine velocity
profile whose peak joint speed is the limit (0.8727 rad/s), so a held parcel sees finite accelerations.
Two ways to execute a move, both passing through every intermediate configuration (no teleport):

- ``sweep``: free-space moves. The arm is set to each control waypoint and checked for contact with
  collision detection only; the resting pile is not integrated. Cheap, and exact for a static scene.
- ``drive``: contact-rich or load-carrying moves. The arm is set to each waypoint (position and
  velocity) and the world is stepped with dynamics, so contacts and constraint forces are real.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Iterator, Sequence

import numpy as np
import pybullet as p
from scipy.spatial.transform import Rotation

from parcelpick_env.robot.gen3 import EE_OFFSET, JOINTS, URDF_PATH, VELOCITY_LIMIT, SuctionToolSpec, write_urdf

ARM_DOF = 7


@dataclass(frozen=True)
class ArmConfig:
    """Where the arm stands and how it moves. The default pedestal puts the base beside the bin's long
    side (bin centred at the origin, long side along x) on a 0.30 m pedestal, facing the bin. Chosen by
    a grid search of top-down IK coverage (floor to 0.7 m: about 90% of the bin volume, floor 94%)."""

    base_position: tuple[float, float, float] = (0.0, -0.38, 0.30)
    base_yaw: float = math.pi / 2
    home: tuple[float, ...] = (0.0, -0.35, 0.0, -2.3, 0.0, -0.5, math.pi / 2)  # tucked, out of the camera view
    # Kinova's own "home" (elbow up, tool forward): seeds IK for the first pose above the bin
    ik_seed: tuple[float, ...] = (0.0, 0.26, math.pi, -2.27, 0.0, 0.96, math.pi / 2)
    joint_speed: float = VELOCITY_LIMIT  # rad/s, the V12 velocity limit
    ik_position_tol: float = 0.004  # m, verified after IK
    ik_angle_tol: float = math.radians(3.0)  # rad, between the reached and the asked tool axis
    ik_iterations: int = 200
    ik_refinements: int = 3  # re-solve from the previous answer; pybullet's IK is a single damped step
    yaw_candidates: int = 4  # the cup is axisymmetric: try this many tool yaws about its axis
    pedestal_width: float = 0.14  # m, static column from the ground to the base (0 disables it)
    hold_force: float = 2000.0  # joint motor force while driven (the arm is position-servoed)
    collision_force: float = 20.0  # N, a non-cup link pushing harder than this is a collision

    def __post_init__(self) -> None:
        if len(self.home) != ARM_DOF or len(self.ik_seed) != ARM_DOF:
            raise ValueError(f"ArmConfig.home and ik_seed need {ARM_DOF} joint values")
        if not self.joint_speed > 0 or not self.ik_position_tol > 0 or not self.ik_angle_tol > 0:
            raise ValueError("ArmConfig speeds and tolerances must be > 0")
        if self.ik_iterations < 1 or self.ik_refinements < 1 or self.yaw_candidates < 1:
            raise ValueError("ArmConfig IK counts must be >= 1")


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product without np.cross's per-call overhead (hot in the IK loop)."""
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                     a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


class Gen3Kinematics:
    """Forward kinematics and Jacobian of the tool tip in numpy, from the same table as the URDF.

    Used to refine pybullet's IK answer by damped least squares: pybullet's null-space IK alone leaves
    5-20 mm of error on this arm, and the refinement needs thousands of FK calls per episode.
    """

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

    def tip_x(self, q: np.ndarray) -> np.ndarray:
        """The tool frame's x axis (world), i.e. the yaw of the cup about its axis."""
        self.forward(q)
        return self._last_R[:, 0].copy()

    def jacobian(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        tip, axis, axes, origins = self.forward(q)
        J = np.empty((6, ARM_DOF))
        J[:3] = _cross(axes, tip - origins).T  # linear
        J[3:] = axes.T  # angular
        return tip, axis, J


@dataclass
class Contact:
    link: int
    body: int
    position: np.ndarray
    normal_force: float


@dataclass
class MoveResult:
    """How a move ended: ``completed`` or stopped early by ``stop`` (contact) or a collision."""

    completed: bool
    steps: int
    collision: Contact | None = None
    stopped_by: object | None = None


def approach_orientation(axis: np.ndarray, yaw: float = 0.0) -> np.ndarray:
    """Quaternion (xyzw) of a tool frame whose +z is ``axis`` (the approach direction), yawed about it."""
    z = np.asarray(axis, dtype=np.float64)
    z = z / np.linalg.norm(z)
    ref = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = ref - z * (ref @ z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.column_stack([x, y, z]) @ Rotation.from_euler("z", yaw).as_matrix()
    return Rotation.from_matrix(R).as_quat()


class Gen3Arm:
    """A Gen3 with the suction tool, fixed on its pedestal in an existing pybullet client."""

    def __init__(self, client: int, config: ArmConfig | None = None) -> None:
        self.client = client
        self.config = config or ArmConfig()
        if not URDF_PATH.exists():
            write_urdf()
        orn = p.getQuaternionFromEuler((0.0, 0.0, self.config.base_yaw))
        self.body = p.loadURDF(str(URDF_PATH), self.config.base_position, orn, useFixedBase=True,
                               flags=p.URDF_USE_INERTIA_FROM_FILE, physicsClientId=client)
        self.pedestal = self._add_pedestal()
        names = {}
        joints, lower, upper = [], [], []
        for j in range(p.getNumJoints(self.body, physicsClientId=client)):
            info = p.getJointInfo(self.body, j, physicsClientId=client)
            names[info[12].decode()] = j
            if info[2] == p.JOINT_REVOLUTE:
                joints.append(j)
                lower.append(info[8])
                upper.append(info[9])
        self.joints = np.array(joints)
        self._joint_list = [int(j) for j in joints]
        self.lower, self.upper = np.array(lower), np.array(upper)
        self.tip_link = names["tool_tip"]
        self._num_links = p.getNumJoints(self.body, physicsClientId=client)
        self.cup_link = names["suction_cup"]
        self.tool_links = {names["suction_cup"], names["tool_rod"], names["tool_flange"]}
        self.link_names = {v: k for k, v in names.items()}
        self.kin = Gen3Kinematics(self.config.base_position, self.config.base_yaw, SuctionToolSpec().length)
        self.q = np.asarray(self.config.home, dtype=np.float64).copy()
        self.qd = np.zeros(ARM_DOF)
        self.sim_time = 0.0
        self.set_joints(self.q)
        self._collides = True
        self.set_collision(False)

    def set_collision(self, enabled: bool) -> None:
        """Whether the links take part in the dynamics' contacts. Off while idle or sweeping (sweeps
        query distances directly, which ignores this), so a parcel resting against the arm does not
        keep the whole pile's simulation island awake; on for every dynamic move."""
        if enabled == self._collides:
            return
        for link in range(self._num_links):
            p.setCollisionFilterGroupMask(self.body, link, 1 if enabled else 0, -1 if enabled else 0,
                                          physicsClientId=self.client)
        self._collides = enabled

    def _add_pedestal(self) -> int | None:
        """A static column under the base. Parcels leaning on it touch a static body, so the resting
        pile can still sleep (a touch on the arm's own base link would keep its island awake); the
        base link itself stops colliding, as it sits on the column."""
        w = self.config.pedestal_width
        if w <= 0:
            return None
        x, y, z = self.config.base_position
        bottom = -0.05
        half = [w / 2, w / 2, (z - bottom) / 2]
        col = p.createCollisionShape(p.GEOM_BOX, halfExtents=half, physicsClientId=self.client)
        vis = p.createVisualShape(p.GEOM_BOX, halfExtents=half, rgbaColor=[0.2, 0.2, 0.22, 1],
                                  physicsClientId=self.client)
        body = p.createMultiBody(0.0, col, vis, basePosition=[x, y, (z + bottom) / 2], physicsClientId=self.client)
        p.setCollisionFilterGroupMask(self.body, -1, 0, 0, physicsClientId=self.client)
        p.setCollisionFilterPair(self.body, body, 0, -1, 0, physicsClientId=self.client)
        return body

    # --- state -------------------------------------------------------------------------------------
    def set_joints(self, q: np.ndarray, qd: np.ndarray | None = None) -> None:
        qd = np.zeros(ARM_DOF) if qd is None else qd
        p.resetJointStatesMultiDof(self.body, self._joint_list, [[float(v)] for v in q],
                                   targetVelocities=[[float(v)] for v in qd], physicsClientId=self.client)
        self.q, self.qd = np.array(q, dtype=np.float64), np.array(qd, dtype=np.float64)

    def home(self) -> None:
        self.set_joints(np.asarray(self.config.home, dtype=np.float64))

    def tip_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Tool-tip (cup lip centre) position and xyzw orientation; its +z is the approach direction."""
        s = p.getLinkState(self.body, self.tip_link, computeForwardKinematics=True, physicsClientId=self.client)
        return np.array(s[4]), np.array(s[5])

    def tip_axis(self) -> np.ndarray:
        return Rotation.from_quat(self.tip_pose()[1]).as_matrix()[:, 2]

    def link_poses(self) -> list[tuple[str, np.ndarray, np.ndarray]]:
        out = []
        for j in range(p.getNumJoints(self.body, physicsClientId=self.client)):
            s = p.getLinkState(self.body, j, computeForwardKinematics=True, physicsClientId=self.client)
            out.append((self.link_names[j], np.array(s[4]), np.array(s[5])))
        return out

    # --- inverse kinematics ------------------------------------------------------------------------
    def ik(self, position: Sequence[float], axis: Sequence[float], seed: np.ndarray | None = None,
           x_axis: Sequence[float] | None = None) -> np.ndarray | None:
        """Joint angles putting the tool tip at ``position`` with its approach axis along ``axis``.

        pybullet's null-space IK (joint limits, rest pose = seed) gives initial guesses for a few tool
        yaws; each is refined by damped least squares on position and axis only (the cup is
        axisymmetric, so its yaw is free) within the joint limits, then verified by pybullet's own
        forward kinematics. Returns the verified answer closest to the seed, or None.
        ``x_axis`` also fixes the cup's yaw (its x axis, projected orthogonal to ``axis``).
        The arm's state is left unchanged.
        """
        cfg = self.config
        saved_q, saved_qd = self.q.copy(), self.qd.copy()
        seed = self.q.copy() if seed is None else np.asarray(seed, dtype=np.float64)
        target = np.asarray(position, dtype=np.float64)
        axis = np.asarray(axis, dtype=np.float64)
        axis = axis / np.linalg.norm(axis)
        if x_axis is not None:
            x_axis = np.asarray(x_axis, dtype=np.float64)
            x_axis = x_axis - axis * (x_axis @ axis)
            x_axis = x_axis / np.linalg.norm(x_axis)
        ranges = (self.upper - self.lower).tolist()
        best: tuple[float, np.ndarray] | None = None
        try:
            def guesses() -> Iterator[np.ndarray]:
                yield seed
                for k in range(1 if x_axis is not None else cfg.yaw_candidates):
                    self.set_joints(seed)
                    if x_axis is not None:
                        orn = Rotation.from_matrix(np.column_stack([x_axis, np.cross(axis, x_axis), axis])).as_quat()
                    else:
                        orn = approach_orientation(axis, 2 * math.pi * k / cfg.yaw_candidates)
                    sol = p.calculateInverseKinematics(
                        self.body, self.tip_link, target.tolist(), orn.tolist(),
                        lowerLimits=self.lower.tolist(), upperLimits=self.upper.tolist(), jointRanges=ranges,
                        restPoses=seed.tolist(), maxNumIterations=cfg.ik_iterations, residualThreshold=1e-5,
                        physicsClientId=self.client)
                    yield np.clip(np.array(sol[:ARM_DOF]), self.lower, self.upper)

            for guess in guesses():
                q = self._refine(guess, target, axis, seed, x_axis)
                if q is None:
                    continue
                self.set_joints(q)
                pos, quat = self.tip_pose()
                reached = Rotation.from_quat(quat).as_matrix()[:, 2]
                yaw_ok = x_axis is None or Rotation.from_quat(quat).as_matrix()[:, 0] @ x_axis >= math.cos(cfg.ik_angle_tol)
                if (np.linalg.norm(pos - target) <= cfg.ik_position_tol and yaw_ok
                        and math.acos(float(np.clip(reached @ axis, -1.0, 1.0))) <= cfg.ik_angle_tol):
                    cost = float(np.abs(q - seed).max())
                    if best is None or cost < best[0]:
                        best = (cost, q)
                    if cost < 1.0:
                        break
        finally:
            self.set_joints(saved_q, saved_qd)
        return None if best is None else best[1]

    def _refine(self, q: np.ndarray, target: np.ndarray, axis: np.ndarray, rest: np.ndarray,
                x_axis: np.ndarray | None = None, iterations: int = 60, damping: float = 0.02
                ) -> np.ndarray | None:
        """Damped least squares on (position, axis[, yaw]) within joint limits, null-space pull to rest."""
        tol_p, tol_a = 0.25 * self.config.ik_position_tol, 0.25 * self.config.ik_angle_tol
        for _ in range(iterations):
            tip, cur_axis, J = self.kin.jacobian(q)
            e_pos = target - tip
            e_rot = _cross(cur_axis, axis)
            if x_axis is not None:
                cur_x = self.kin._last_R[:, 0]
                e_x = _cross(cur_x, x_axis)
                if (np.linalg.norm(e_pos) < tol_p and np.linalg.norm(e_rot) < math.sin(tol_a)
                        and np.linalg.norm(e_x) < math.sin(tol_a) and cur_axis @ axis > 0 and cur_x @ x_axis > 0):
                    return q
                if cur_x @ x_axis > 0:  # standard small-angle orientation error over all three axes
                    e_y = _cross(_cross(cur_axis, cur_x), _cross(axis, x_axis))
                    e_rot = 0.5 * (e_rot + e_x + e_y)
                else:  # yaw near the antipode: turn about the tool axis first
                    e_rot = e_rot + 0.5 * cur_axis
            elif np.linalg.norm(e_pos) < tol_p and np.linalg.norm(e_rot) < math.sin(tol_a) and cur_axis @ axis > 0:
                return q
            if cur_axis @ axis < 0:  # pointing backwards: rotate about any perpendicular
                e_rot = _cross(cur_axis, np.array([1.0, 0.0, 0.0]) if abs(cur_axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0]))
            # without a yaw target the rotation about the tool axis is free: drop it from the task
            Ja = J[3:] if x_axis is not None else J[3:] - np.outer(cur_axis, cur_axis @ J[3:])
            A = np.vstack([J[:3], Ja])
            e = np.concatenate([e_pos, e_rot])
            JJt = A @ A.T + damping**2 * np.eye(6)
            dq = A.T @ np.linalg.solve(JJt, e)
            N = np.eye(ARM_DOF) - A.T @ np.linalg.solve(JJt, A)
            dq += N @ (0.1 * (rest - q))
            step = np.abs(dq).max()
            if step > 0.3:
                dq *= 0.3 / step
            q = np.clip(q + dq, self.lower, self.upper)
        return None

    def cartesian_path(self, start_q: np.ndarray, points: np.ndarray, axis: np.ndarray) -> list[np.ndarray] | None:
        """IK along a polyline of tip positions, each seeded by the previous answer (None if any fails)."""
        path, q = [], start_q
        for point in points:
            q = self.ik(point, axis, seed=q)
            if q is None:
                return None
            path.append(q)
        return path

    # --- motion ------------------------------------------------------------------------------------
    def trajectory(self, waypoints: Sequence[np.ndarray], dt: float, speed_scale: float = 1.0,
                   min_duration: float = 0.0) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """(q, qd) at every control step along the joint-space polyline current -> ``waypoints``.

        One cosine velocity profile covers the whole polyline (no stop at inner waypoints), timed so
        the peak joint speed is ``joint_speed * speed_scale`` (or slower, to last ``min_duration``).
        """
        vmax = self.config.joint_speed * speed_scale
        pts = np.vstack([self.q[None, :], np.asarray(waypoints, dtype=np.float64).reshape(-1, ARM_DOF)])
        seg = np.abs(np.diff(pts, axis=0)).max(axis=1)
        total = float(seg.sum())
        if total < 1e-9:
            return
        knots = np.concatenate([[0.0], np.cumsum(seg)]) / total  # path parameter at each waypoint
        duration = max(math.pi / 2 * total / vmax, min_duration)
        n = max(1, math.ceil(duration / dt))
        duration = n * dt
        for k in range(1, n + 1):
            s = 0.5 * (1 - math.cos(math.pi * k / n))
            sd = 0.5 * math.pi / duration * math.sin(math.pi * k / n)
            i = min(int(np.searchsorted(knots, s, side="right")) - 1, len(seg) - 1)
            while i > 0 and knots[i + 1] - knots[i] <= 0:
                i -= 1
            width = max(knots[i + 1] - knots[i], 1e-12)
            u = (s - knots[i]) / width
            dqds = (pts[i + 1] - pts[i]) / width
            yield pts[i] + u * (pts[i + 1] - pts[i]), sd * dqds

    def contacts(self) -> list[Contact]:
        return [Contact(c[3], c[2], np.array(c[6]), float(c[9]))
                for c in p.getContactPoints(bodyA=self.body, physicsClientId=self.client)]

    def _collision(self, contacts: list[Contact], allowed_links: set[int]) -> Contact | None:
        for c in contacts:
            if c.link not in allowed_links and c.normal_force > self.config.collision_force:
                return c
        return None

    def first_penetration(self, ignore_bodies: set[int], depth: float = 1e-3) -> Contact | None:
        """Narrow-phase check of the arm against bodies whose AABB overlaps the arm's (no full
        collision pass over the pile, whose parcel-parcel pairs are irrelevant here)."""
        c = self.client
        boxes = np.array([p.getAABB(self.body, j, physicsClientId=c) for j in range(-1, self._num_links)])
        lo, hi = boxes[:, 0].min(axis=0), boxes[:, 1].max(axis=0)
        near = {o[0] for o in (p.getOverlappingObjects(lo.tolist(), hi.tolist(), physicsClientId=c) or ())}
        for body in sorted(near - {self.body} - set(ignore_bodies)):
            for cp in p.getClosestPoints(self.body, body, 0.0, physicsClientId=c):
                # the base never moves and sits in its pedestal (queries ignore collision filters)
                if cp[3] == -1 or (body == self.pedestal and cp[3] == 0):
                    continue
                if cp[8] < -depth:
                    return Contact(cp[3], cp[2], np.array(cp[5]), float(cp[9]))
        return None

    def sweep(self, waypoints: Sequence[np.ndarray], dt: float, ignore_bodies: set[int] = frozenset(),
              check: bool = True, on_step: Callable[[], object] | None = None) -> MoveResult:
        """Free-space move checked by collision detection at each control step (the pile is at rest).

        Any arm or tool contact with the scene is a collision here: nothing should be touched.
        """
        steps = 0
        for q, qd in self.trajectory(waypoints, dt):
            self.set_joints(q, qd)
            steps += 1
            self.sim_time += dt
            if on_step is not None:
                on_step()
            if not check:
                continue
            hit = self.first_penetration(ignore_bodies)
            if hit is not None:
                self.qd = np.zeros(ARM_DOF)
                return MoveResult(False, steps, hit)
        self.qd = np.zeros(ARM_DOF)
        return MoveResult(True, steps)

    def drive(self, waypoints: Sequence[np.ndarray], step_world: Callable[[], None], dt: float,
              speed_scale: float = 1.0, min_duration: float = 0.0, stop: Callable[[list[Contact]], object] | None = None,
              on_step: Callable[[], object] | None = None, allowed_links: set[int] | None = None
              ) -> MoveResult:
        """Dynamic move: set the servo target each step, step the world, read contacts.

        ``stop(contacts)`` returning a truthy value ends the move (a guarded move); ``on_step()``
        returning truthy also ends it (e.g. a seal broke). A non-allowed link pressing on the scene
        ends it as a collision.
        """
        allowed = self.tool_links | {self.tip_link} if allowed_links is None else allowed_links
        self.set_collision(True)
        try:
            return self._drive(waypoints, step_world, dt, speed_scale, min_duration, stop, on_step, allowed)
        finally:
            self.set_collision(False)

    def _drive(self, waypoints, step_world, dt, speed_scale, min_duration, stop, on_step, allowed) -> MoveResult:
        steps = 0
        for q, qd in self.trajectory(waypoints, dt, speed_scale, min_duration):
            self.set_joints(q, qd)
            p.setJointMotorControlArray(self.body, self.joints.tolist(), p.VELOCITY_CONTROL,
                                        targetVelocities=qd.tolist(),
                                        forces=[self.config.hold_force] * ARM_DOF,
                                        physicsClientId=self.client)
            step_world()
            steps += 1
            self.sim_time += dt
            contacts = self.contacts()
            hit = self._collision(contacts, allowed)
            if hit is not None:
                self.qd = np.zeros(ARM_DOF)
                return MoveResult(False, steps, collision=hit)
            if stop is not None:
                reason = stop(contacts)
                if reason:
                    self.set_joints(q)
                    return MoveResult(False, steps, stopped_by=reason)
            if on_step is not None:
                reason = on_step()
                if reason:
                    return MoveResult(False, steps, stopped_by=reason)
        self.qd = np.zeros(ARM_DOF)
        self.set_joints(self.q)
        return MoveResult(True, steps)


    def hold(self, steps: int, step_world: Callable[[], None], dt: float) -> None:
        """Keep the current configuration while the world runs ``steps`` steps."""
        self.set_collision(True)
        try:
            self._hold(steps, step_world, dt)
        finally:
            self.set_collision(False)

    def _hold(self, steps: int, step_world: Callable[[], None], dt: float) -> None:
        for _ in range(steps):
            self.set_joints(self.q)
            p.setJointMotorControlArray(self.body, self.joints.tolist(), p.VELOCITY_CONTROL,
                                        targetVelocities=[0.0] * ARM_DOF,
                                        forces=[self.config.hold_force] * ARM_DOF, physicsClientId=self.client)
            step_world()
            self.sim_time += dt
        self.set_joints(self.q)


def reachability(arm: Gen3Arm, points: np.ndarray, axis: Sequence[float] = (0.0, 0.0, -1.0),
                 seed: np.ndarray | None = None) -> np.ndarray:
    """Which points the tool tip reaches with the given approach axis (verified IK from ``seed``)."""
    seed = np.asarray(arm.config.home if seed is None else seed, dtype=np.float64)
    return np.array([arm.ik(pt, axis, seed=seed) is not None for pt in np.asarray(points)], dtype=bool)
