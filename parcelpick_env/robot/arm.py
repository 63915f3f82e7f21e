"""The Gen3 arm in a pybullet world: loading, verified IK with joint limits, execution of moves, contacts.

Kinematics live in ``kinematics``, trajectory timing in ``timing`` (jerk-limited, ruckig) and
collision-free planning in ``planning`` (OMPL); this class drives the simulator with their results:

- ``free_trajectory``: a planned free-space move (straight when clear, else RRTConnect), timed;
  ``cartesian_trajectory``: the tool tip along straight lines with a fixed approach axis (and yaw).
- ``execute``: dynamic execution. pybullet's position motors, torque-limited to the Gen3's efforts,
  servo the arm along the trajectory while the world steps; the joints are never reset, so contacts
  and a held parcel's constraint see a physically driven arm.
- ``sweep_trajectory``: kinematic free-space execution while the world is NOT stepped (the pile is at
  rest): the arm (and a held parcel) are placed at every sample and collision-checked.
- ``tool_motion``: the tool's pose, twist and acceleration, for the held parcel's inertial wrench.
- ``hold``: stand still while the world steps, driven by the motors like ``execute``.

Velocity, acceleration and jerk limits are ``timing.GEN3_LIMITS`` (``Gen3Arm.limits``).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import pybullet as p
from scipy.spatial.transform import Rotation

from parcelpick_env.robot.gen3 import JOINTS, URDF_PATH, SuctionToolSpec, write_urdf
from parcelpick_env.robot.kinematics import ARM_DOF, Gen3Kinematics
from parcelpick_env.robot.planning import Attachment, Collision, MotionPlanner, PlannerConfig
from parcelpick_env.robot.timing import (GEN3_LIMITS, JointLimits, Trajectory, concatenate, hold_trajectory,
                                        joint_trajectory, path_trajectory)

CARTESIAN_STEP = 0.02  # m between IK points on Cartesian lines timed by path_trajectory
PATH_IK_TOLERANCE = 0.01  # of the IK tolerances: points on a Cartesian path converge to 0.04 mm
MAX_IK_JUMP = 0.25  # rad: a larger joint change between neighbouring IK points is a branch switch
LINE_STEP = 0.015  # m between IK points of a Cartesian line (3 cm lets IK jump branches near the drop zone)
FINE_STEPS = 4  # a line whose IK jumps is solved again this many times finer (``line_path``)


@dataclass(frozen=True)
class ArmConfig:
    """Where the arm stands and how it moves. The default pedestal puts the base beside the bin's long
    side (bin centred at the origin, long side along x) on a 0.30 m pedestal, facing the bin. Chosen by
    a grid search of top-down IK coverage (floor to 0.7 m: about 90% of the bin volume, floor 94%)."""

    # 0.175 m behind the 0.70 x 0.45 m tote's near wall, 0.30 m above its floor: reaches 99.8% of a
    # floor x [0, 0.45 m] grid top-down (docs/piles.md, tests/test_pile.py::test_arm_reaches_the_tote_top_down)
    base_position: tuple[float, float, float] = (0.0, -0.40, 0.30)
    base_yaw: float = math.pi / 2
    home: tuple[float, ...] = (0.0, -0.35, 0.0, -2.3, 0.0, -0.5, math.pi / 2)  # tucked, out of the camera view
    # Kinova's own "home" (elbow up, tool forward): seeds IK for the first pose above the bin
    ik_seed: tuple[float, ...] = (0.0, 0.26, math.pi, -2.27, 0.0, 0.96, math.pi / 2)
    ik_position_tol: float = 0.004  # m, verified after IK
    ik_angle_tol: float = math.radians(3.0)  # rad, between the reached and the asked tool axis
    ik_iterations: int = 200
    ik_refinements: int = 3  # re-solve from the previous answer; pybullet's IK is a single damped step
    yaw_candidates: int = 4  # the cup is axisymmetric: try this many tool yaws about its axis
    pedestal_width: float = 0.14  # m, static column from the ground to the base (0 disables it)
    collision_force: float = 20.0  # N, a non-cup link pushing harder than this is a collision
    # execute(): pybullet's position motors, torque-limited to the Gen3's efforts (gen3.JOINTS).
    # The position gain is the fraction of the joint error corrected per step (0.3: an error decays
    # in ~10 steps without ringing); the velocity gain 1 makes the motor take the target velocity.
    servo_position_gain: float = 0.3
    servo_velocity_gain: float = 1.0
    start_tolerance: float = 0.02  # rad: a trajectory must start this close to the arm's state

    def __post_init__(self) -> None:
        if len(self.home) != ARM_DOF or len(self.ik_seed) != ARM_DOF:
            raise ValueError(f"ArmConfig.home and ik_seed need {ARM_DOF} joint values")
        if not self.ik_position_tol > 0 or not self.ik_angle_tol > 0:
            raise ValueError("ArmConfig IK tolerances must be > 0")
        if self.ik_iterations < 1 or self.ik_refinements < 1 or self.yaw_candidates < 1:
            raise ValueError("ArmConfig IK counts must be >= 1")
        if not (0 < self.servo_position_gain <= 1 and 0 < self.servo_velocity_gain <= 1):
            raise ValueError("ArmConfig servo gains must be in (0, 1]")
        if not self.start_tolerance > 0:
            raise ValueError("ArmConfig.start_tolerance must be > 0")


@dataclass
class Contact:
    link: int
    body: int
    position: np.ndarray
    normal_force: float


@dataclass
class MoveResult:
    """How a move ended: ``completed`` or stopped early by ``stop`` (contact) or a collision.

    ``collision`` is a dynamic ``Contact`` (execute, drive) or a kinematic ``Collision`` (sweeps);
    ``link`` names the arm link (or the held parcel) either way. ``tracking_error`` (rad, joints) and
    ``tip_error`` (m, tool tip) are the largest gaps between the commanded and the driven state.
    """

    completed: bool
    steps: int
    collision: Contact | Collision | None = None
    stopped_by: object | None = None
    link: str | None = None
    tracking_error: float = 0.0
    tip_error: float = 0.0


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

    def __init__(self, client: int, config: ArmConfig | None = None,
                 planner_config: PlannerConfig | None = None, limits: JointLimits = GEN3_LIMITS) -> None:
        self.client = client
        self.limits = limits
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
        self.qdd = np.zeros(ARM_DOF)  # measured (finite difference of qd) while executing
        self.command: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # (q, qd, qdd) being servoed
        self.efforts = np.array([j[6] for j in JOINTS])  # N m, motor torque limits
        self.set_joints(self.q)
        self._collides = True
        self.set_collision(False)
        self.planner = MotionPlanner(self, client, planner_config)

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
        """Place the arm kinematically (only while the world is not being stepped: IK, planning, sweeps).
        The motors are re-aimed at ``q`` too, so a later world step holds the arm there instead of
        pulling it back to the last executed target."""
        qd = np.zeros(ARM_DOF) if qd is None else qd
        p.resetJointStatesMultiDof(self.body, self._joint_list, [[float(v)] for v in q],
                                   targetVelocities=[[float(v)] for v in qd], physicsClientId=self.client)
        self.q, self.qd = np.array(q, dtype=np.float64), np.array(qd, dtype=np.float64)
        self._servo(self.q, np.zeros(ARM_DOF))

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
    def ik(self, position: Sequence[float] | np.ndarray, axis: Sequence[float] | np.ndarray,
           seed: np.ndarray | None = None, x_axis: Sequence[float] | np.ndarray | None = None,
           valid: Callable[[np.ndarray], bool] | None = None) -> np.ndarray | None:
        """Joint angles putting the tool tip at ``position`` with its approach axis along ``axis``.

        pybullet's null-space IK (joint limits, rest pose = seed) gives initial guesses for a few tool
        yaws; each is refined by damped least squares on position and axis only (the cup is
        axisymmetric, so its yaw is free) within the joint limits, then verified by pybullet's own
        forward kinematics. Returns the verified answer closest to the seed, or None.
        ``x_axis`` also fixes the cup's yaw (its x axis, projected orthogonal to ``axis``). ``valid``, if
        given, must accept an answer (a collision check, say): the closest answer it refuses gives way to
        another branch from the other guesses. The arm's state is left unchanged.
        """
        cfg = self.config
        saved_q, saved_qd = self.q.copy(), self.qd.copy()
        seed = self.q.copy() if seed is None else np.asarray(seed, dtype=np.float64)
        target = np.asarray(position, dtype=np.float64)
        ax = np.asarray(axis, dtype=np.float64)
        ax = ax / np.linalg.norm(ax)
        xa: np.ndarray | None = None
        if x_axis is not None:
            xa = np.asarray(x_axis, dtype=np.float64)
            xa = xa - ax * (xa @ ax)
            xa = xa / np.linalg.norm(xa)
        ranges = (self.upper - self.lower).tolist()
        best: tuple[float, np.ndarray] | None = None
        try:
            def guesses() -> Iterator[tuple[np.ndarray, np.ndarray, int]]:  # (start, rest pose, iterations)
                yield seed, seed, 60
                for k in range(1 if xa is not None else cfg.yaw_candidates):
                    self.set_joints(seed)
                    if xa is not None:
                        orn = Rotation.from_matrix(np.column_stack([xa, np.cross(ax, xa), ax])).as_quat()
                    else:
                        orn = approach_orientation(ax, 2 * math.pi * k / cfg.yaw_candidates)
                    sol = p.calculateInverseKinematics(
                        self.body, self.tip_link, target.tolist(), orn.tolist(),
                        lowerLimits=self.lower.tolist(), upperLimits=self.upper.tolist(), jointRanges=ranges,
                        restPoses=seed.tolist(), maxNumIterations=cfg.ik_iterations, residualThreshold=1e-5,
                        physicsClientId=self.client)
                    yield np.clip(np.array(sol[:ARM_DOF]), self.lower, self.upper), seed, 60
                # last, the Kinova home (elbow up, tool forward), pulled towards itself, with a longer search:
                # the damped least squares from there finds high or far top-down poses that a seed tucked
                # near the pile and pybullet's guesses miss (the oracle's reach check solves the same way)
                home = np.asarray(cfg.ik_seed, dtype=np.float64)
                yield home, home, 150

            for guess, rest, iterations in guesses():
                q = self._refine(guess, target, ax, rest, xa, iterations=iterations)
                if q is None:
                    continue
                self.set_joints(q)
                pos, quat = self.tip_pose()
                reached = Rotation.from_quat(quat).as_matrix()[:, 2]
                yaw_ok = xa is None or Rotation.from_quat(quat).as_matrix()[:, 0] @ xa >= math.cos(cfg.ik_angle_tol)
                if (np.linalg.norm(pos - target) <= cfg.ik_position_tol and yaw_ok
                        and math.acos(float(np.clip(reached @ ax, -1.0, 1.0))) <= cfg.ik_angle_tol
                        and (valid is None or valid(q))):
                    cost = float(np.abs(q - seed).max())
                    if best is None or cost < best[0]:
                        best = (cost, q)
                    if cost < 1.0:
                        break
        finally:
            self.set_joints(saved_q, saved_qd)
        return None if best is None else best[1]

    def _refine(self, q: np.ndarray, target: np.ndarray, axis: np.ndarray, rest: np.ndarray,
                x_axis: np.ndarray | None = None, iterations: int = 60, damping: float = 0.02,
                tolerance: float = 0.25) -> np.ndarray | None:
        """Damped least squares on (position, axis[, yaw]) within joint limits, null-space pull to rest;
        converged at ``tolerance`` times the configured IK tolerances (``Gen3Kinematics.refine``)."""
        return self.kin.refine(q, target, axis, rest, self.lower, self.upper,
                               tolerance * self.config.ik_position_tol, tolerance * self.config.ik_angle_tol,
                               x_axis, iterations, damping)

    def cartesian_path(self, start_q: np.ndarray, points: np.ndarray, axis: np.ndarray,
                       x_axis: Sequence[float] | np.ndarray | None = None) -> list[np.ndarray] | None:
        """IK along a polyline of tip positions, each seeded by the previous answer (None if any fails).
        ``x_axis`` also holds the cup's yaw fixed along the way."""
        path, q = [], start_q
        axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
        x = None if x_axis is None else np.asarray(x_axis, dtype=np.float64)
        if x is not None:
            x = x - axis * (x @ axis)
            x = x / np.linalg.norm(x)
        for point in points:
            target = np.asarray(point, dtype=np.float64)
            # neighbouring points: damped least squares from the previous answer usually converges in a
            # few steps (the numpy kinematics match pybullet's to 1e-5 m, tested); converge far below
            # the IK tolerance, as IK noise would show as joint-path curvature that slows a
            # path_trajectory through these points. Fall back to the full, verified IK otherwise.
            fine = self._refine(q, target, axis, q, x, tolerance=PATH_IK_TOLERANCE)
            if fine is None:
                full = self.ik(target, axis, seed=q, x_axis=x)
                if full is None:
                    return None
                fine = self._refine(full, target, axis, full, x, tolerance=PATH_IK_TOLERANCE)
                fine = full if fine is None else fine
            q = fine
            path.append(q)
        return path

    def line_path(self, q0: np.ndarray, end: np.ndarray, axis: np.ndarray, x_axis: np.ndarray | None = None,
                  step: float = LINE_STEP) -> tuple[np.ndarray | None, str | None]:
        """Joint waypoints (``q0`` first) of the tip on a straight line from its place at ``q0`` to ``end``, the
        tool on ``axis`` (and yaw ``x_axis``), IK every ``step``: (path, None), or (None, why) where IK fails
        or jumps branches. The rule every carrying and approach line of the cell obeys (``envs/grasp.py``), and
        the one the oracle checks a lift with."""
        q0 = np.asarray(q0, dtype=np.float64)
        start = self.kin.tool_pose(q0)[0]
        # A joint change above MAX_IK_JUMP between neighbours is a branch switch, or a fast but continuous turn
        # near a singular pose: a continuous one shrinks with the step (kept, FINE_STEPS times finer), a switch not.
        for k, limit in ((1, MAX_IK_JUMP), (FINE_STEPS, MAX_IK_JUMP / 2)):
            n = max(1, math.ceil(float(np.linalg.norm(end - start)) * k / step))
            qs = self.cartesian_path(q0, start + (end - start) * (np.arange(1, n + 1)[:, None] / n), axis, x_axis)
            if qs is None:
                return None, "ik failed along the line"
            path = np.vstack([q0[None], np.asarray(qs)])
            jump = float(np.abs(np.diff(path, axis=0)).max())
            if jump <= limit:
                return path, None
        return None, f"ik jumped {jump:.2f} rad between neighbouring points"

    def cartesian_trajectory(self, start_q: np.ndarray, points: Sequence[Sequence[float]], axis: Sequence[float],
                             dt: float, speed_scale: float = 1.0, x_axis: Sequence[float] | None = None,
                             step: float = CARTESIAN_STEP) -> tuple[Trajectory | None, str | None]:
        """The tool tip along the polyline start tip -> ``points`` with its approach axis held at ``axis``
        (and its yaw at ``x_axis`` when given): IK every ``step`` m, then ``timing.path_trajectory``, so
        the tip stays on the line and the axis does not tilt between IK points.

        Returns (trajectory, None) or (None, reason): an IK failure or a jump between IK branches.
        """
        q = np.asarray(start_q, dtype=np.float64)
        tip = self.kin.tool_pose(q)[0]
        corners = np.vstack([tip[None], np.asarray(points, dtype=np.float64).reshape(-1, 3)])
        approach = np.asarray(axis, dtype=np.float64)
        legs = []
        for k, (a, b) in enumerate(itertools.pairwise(corners)):  # each straight leg rest-to-rest
            n = max(1, math.ceil(float(np.linalg.norm(b - a)) / step))
            # the leg's first point is its own start, solved precisely too: an arm a little off the line
            # (within the IK tolerance) first settles onto it by a tiny move, rather than the spline
            # taking that offset as a kink
            qs = self.cartesian_path(q, a + (b - a) * (np.arange(0, n + 1)[:, None] / n), approach, x_axis)
            if qs is None:
                return None, f"ik failed along leg {k} of the line"
            path = np.array(qs)
            jump = float(np.abs(np.diff(np.vstack([q[None], path]), axis=0)).max())
            if jump > MAX_IK_JUMP:
                return None, f"ik jumped {jump:.2f} rad between neighbouring points on leg {k}"
            if np.abs(path[0] - q).max() > 1e-9:
                legs.append(joint_trajectory(q, [path[0]], self.limits.scaled(speed_scale), dt))
            legs.append(path_trajectory(path, self.limits, dt, speed_scale))
            q = path[-1]
        return concatenate(legs), None

    def free_trajectory(self, q_goal: np.ndarray, dt: float, attached: Attachment | None = None,
                        ignore_bodies: Iterable[int] = (), speed_scale: float = 1.0
                        ) -> tuple[Trajectory | None, str | None]:
        """A planned (collision-free) and timed free-space move from ``arm.q`` to ``q_goal``:
        (trajectory, None), or (None, the planner's reason). The start is the arm's state clipped to the
        joint limits: a driven joint can end a move a few microradians past one (measured: joint 7 at
        2 pi + 5e-6 after a carry), which the planner would refuse as a start."""
        start = np.clip(self.q, self.lower, self.upper)
        path = self.planner.plan(start, q_goal, attached=attached, ignore_bodies=ignore_bodies)
        if path is None:
            return None, self.planner.last_failure
        return joint_trajectory(start, path[1:], self.limits.scaled(speed_scale), dt), None

    # --- contacts -----------------------------------------------------------------------------------
    def contacts(self) -> list[Contact]:
        return [Contact(c[3], c[2], np.array(c[6]), float(c[9]))
                for c in p.getContactPoints(bodyA=self.body, physicsClientId=self.client)]

    def _collision(self, contacts: list[Contact], allowed_links: set[int]) -> Contact | None:
        for c in contacts:
            if c.link not in allowed_links and c.normal_force > self.config.collision_force:
                return c
        return None

    def first_penetration(self, ignore_bodies: Iterable[int] = (), depth: float = 1e-3) -> Collision | None:
        """The first link pressing more than ``depth`` into another body (or into the arm itself), as
        the arm is placed now; a narrow-phase check of only the bodies near the arm."""
        return self.planner.placed_collision(ignore_bodies=ignore_bodies, margin=-depth)

    # --- planned, time-parameterised motion (timing.Trajectory) ------------------------------------
    def tool_motion(self, q=None, qd=None, qdd=None):
        """Tool-tip (position, R, v, omega, a, alpha), world frame, at (q, qd, qdd); defaults to the
        arm's measured state (``q``, ``qd``, ``qdd``). See ``Gen3Kinematics.tool_motion``."""
        return self.kin.tool_motion(self.q if q is None else q, self.qd if qd is None else qd,
                                    self.qdd if qdd is None else qdd)

    def _check_start(self, traj: Trajectory) -> None:
        if not isinstance(traj, Trajectory) or len(traj) < 1:
            raise ValueError("traj must be a non-empty timing.Trajectory")
        gap = float(np.abs(traj.q[0] - self.q).max())
        if gap > self.config.start_tolerance:
            raise ValueError(f"traj starts {gap:.3f} rad from the arm's state (tolerance "
                             f"{self.config.start_tolerance} rad); time it from arm.q")

    def _read_state(self) -> tuple[np.ndarray, np.ndarray]:
        states = p.getJointStates(self.body, self._joint_list, physicsClientId=self.client)
        return np.array([s[0] for s in states]), np.array([s[1] for s in states])

    def _servo(self, q: np.ndarray, qd: np.ndarray) -> None:
        cfg = self.config
        p.setJointMotorControlArray(self.body, self._joint_list, p.POSITION_CONTROL, targetPositions=q.tolist(),
                                    targetVelocities=qd.tolist(), forces=self.efforts.tolist(),
                                    positionGains=[cfg.servo_position_gain] * ARM_DOF,
                                    velocityGains=[cfg.servo_velocity_gain] * ARM_DOF, physicsClientId=self.client)

    def execute(self, traj: Trajectory, step_world: Callable[[], None],
                stop: Callable[[list[Contact]], object] | None = None, on_step: Callable[[], object] | None = None,
                allowed_links: set[int] | None = None) -> MoveResult:
        """Dynamic move: pybullet's position motors (torque-limited to the Gen3's efforts) servo the
        arm to each sample's (q, qd) and ``step_world()`` advances one physics step of ``traj.dt``; the
        joints are never reset, so contacts and a held parcel's constraint see a physically driven arm.

        After each step ``arm.q``/``arm.qd`` are the measured joint state, ``arm.qdd`` its finite
        difference and ``arm.command`` the sample being servoed. ``stop(contacts)`` returning a truthy
        value ends the move (a guarded move: the motors then hold the reached position); ``on_step()``
        returning truthy also ends it (e.g. a seal broke). A non-allowed link pressing on the scene
        harder than ``collision_force`` ends it as a collision.
        """
        self._check_start(traj)
        engine_dt = p.getPhysicsEngineParameters(physicsClientId=self.client)["fixedTimeStep"]
        if abs(engine_dt - traj.dt) > 1e-9:
            raise ValueError(f"traj.dt {traj.dt} s differs from the physics step {engine_dt} s")
        allowed = self.tool_links | {self.tip_link} if allowed_links is None else allowed_links
        self.set_collision(True)
        try:
            return self._execute(traj, step_world, stop, on_step, allowed)
        finally:
            self.set_collision(False)

    def _execute(self, traj, step_world, stop, on_step, allowed) -> MoveResult:
        dt = traj.dt
        measured = np.empty((len(traj), ARM_DOF))
        steps = 0

        def errors() -> tuple[float, float]:  # largest joint and tool-tip gaps over the steps taken
            if steps == 0:
                return 0.0, 0.0
            q_run, q_cmd_run = measured[1:steps + 1], traj.q[1:steps + 1]
            tips = np.linalg.norm(self.kin.tips(q_run) - self.kin.tips(q_cmd_run), axis=1)
            return float(np.abs(q_run - q_cmd_run).max()), float(tips.max())
        for k in range(1, len(traj)):
            q_cmd, qd_cmd = traj.q[k], traj.qd[k]
            # pybullet's motor sets v_new = v_target + kp (q_target - q) / dt and then q_new = q + v_new dt;
            # aiming at the step's start sample with the step's mean velocity lands on q_cmd (no lag)
            self._servo(traj.q[k - 1], (q_cmd - traj.q[k - 1]) / dt)
            step_world()
            steps += 1
            self.sim_time += dt
            q, qd = self._read_state()
            self.qdd = (qd - self.qd) / dt
            self.q, self.qd = q, qd
            self.command = (q_cmd, qd_cmd, traj.qdd[k])
            measured[k] = q

            contacts = self.contacts()
            hit = self._collision(contacts, allowed)
            reason = None
            if hit is None and stop is not None:
                reason = stop(contacts)
            if hit is None and not reason and on_step is not None:
                reason = on_step()
            if hit is not None or reason:
                self._servo(q, np.zeros(ARM_DOF))  # brake: the motors hold the reached position
                joint_err, tip_err = errors()
                return MoveResult(False, steps, collision=hit, stopped_by=reason or None,
                                  link=None if hit is None else self.link_names.get(hit.link, "base_link"),
                                  tracking_error=joint_err, tip_error=tip_err)
        joint_err, tip_err = errors()
        return MoveResult(True, steps, tracking_error=joint_err, tip_error=tip_err)

    def sweep_trajectory(self, traj: Trajectory, attached: Attachment | None = None,
                         ignore_bodies: Iterable[int] = (), on_step: Callable[[], object] | None = None,
                         check: bool = True, margin: float = 0.0) -> MoveResult:
        """Kinematic free-space move: the arm is placed at every sample of ``traj`` while the world is
        NOT stepped (the pile is at rest), and each sample is checked by ``self.planner`` for any link,
        the tool or the ``attached`` parcel (carried along at the tool pose) coming within ``margin``
        of another body. Stops at the first collision, which ``collision``/``link`` name."""
        self._check_start(traj)
        ignore = set(ignore_bodies)
        steps = 0
        for k in range(1, len(traj)):
            self.set_joints(traj.q[k], traj.qd[k])
            self.qdd = traj.qdd[k]
            steps += 1
            self.sim_time += traj.dt
            hit = self.planner.placed_collision(attached, ignore, margin) if check else None
            if attached is not None and not check:
                self.planner.place_attachment(attached)
            if on_step is not None:
                on_step()
            if hit is not None:
                self.qd = np.zeros(ARM_DOF)
                return MoveResult(False, steps, collision=hit, link=hit.link)
        self.qd, self.qdd = np.zeros(ARM_DOF), np.zeros(ARM_DOF)
        return MoveResult(True, steps)

    def hold(self, steps: int, step_world: Callable[[], None], dt: float) -> MoveResult:
        """Keep the current configuration while the world runs ``steps`` steps: driven by the motors
        like ``execute`` (never reset), with contacts on every link allowed (nothing ends the hold)."""
        if steps < 1:
            return MoveResult(True, 0)
        every_link = set(range(-1, self._num_links))
        return self.execute(hold_trajectory(self.q, steps * dt, dt), step_world, allowed_links=every_link)


def reachability(arm: Gen3Arm, points: np.ndarray, axis: Sequence[float] = (0.0, 0.0, -1.0),
                 seed: np.ndarray | None = None) -> np.ndarray:
    """Which points the tool tip reaches with the given approach axis (verified IK from ``seed``)."""
    seed = np.asarray(arm.config.home if seed is None else seed, dtype=np.float64)
    return np.array([arm.ik(pt, axis, seed=seed) is not None for pt in np.asarray(points)], dtype=bool)
