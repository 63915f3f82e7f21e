"""Collision-free free-space moves for the Gen3: OMPL's RRTConnect over pybullet's distance queries.

A configuration is valid when every arm link and the tool keep ``margin`` from every other body
(bin, ground, parcels, pedestal), and, when a parcel is held, that parcel (placed rigidly at the tool
pose) keeps ``margin`` from everything but the arm; the folded arm must not touch itself
(``SELF_PAIRS``). The queries are kinematic: the arm (and the held parcel) are placed with pybullet's
reset calls while the world is *not* stepped, and put back after.

Most moves need no search: ``plan`` first checks the straight joint segment and returns it when it is
clear. Otherwise RRTConnect searches the 7-D joint box (continuous joints limited to a window around
the start and goal), and the path is shortened deterministically (OMPL's vertex reduction, then a
greedy shortcut). OMPL's global RNG is re-seeded before every search, so a plan depends only on the
scene, the query and ``PlannerConfig.seed``.
"""

from __future__ import annotations

import itertools
import math
import time
from collections import deque
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import pybullet as p
from ompl import base as ob
from ompl import geometric as og
from ompl import util as ou
from scipy.spatial.transform import Rotation

from parcelpick_env.robot.kinematics import ARM_DOF

if TYPE_CHECKING:
    from parcelpick_env.robot.arm import Gen3Arm

HELD_LINK = "held parcel"  # Collision.link when the attached parcel is the one that collides
# Link pairs that can meet when the arm folds (the wrist and tool against the base, shoulder and upper arm;
# the forearm against the base and the tool). Pairs joined by a joint overlap by construction and are left
# out. Self-contact is a penetration test (distance < 0): the capsules are already the links' envelopes.
_DISTAL = ("spherical_wrist_1_link", "spherical_wrist_2_link", "bracelet_link", "tool_flange", "tool_rod",
           "suction_cup")
_PROXIMAL = ("base_link", "shoulder_link", "half_arm_1_link", "half_arm_2_link")
SELF_PAIRS: tuple[tuple[str, str], ...] = tuple((a, b) for a in _DISTAL for b in _PROXIMAL) + (
    ("forearm_link", "base_link"), ("forearm_link", "shoulder_link"), ("forearm_link", "tool_flange"),
    ("forearm_link", "tool_rod"), ("forearm_link", "suction_cup"))


@dataclass(frozen=True)
class PlannerConfig:
    """How free-space moves are planned and checked."""

    # RRTConnect's budget per search, in state-validity checks (about 0.1 ms each in a 30-parcel pile), not
    # wall-clock seconds: a timed search finds a path on an idle machine and misses it on a loaded one, so
    # the same seed would give another episode. A search that exhausts it is tried again with the next
    # seed and twice the budget, ``retries`` times.
    check_budget: int = 8000
    retries: int = 2
    margin: float = 0.01  # m: clearance every link, the tool and a held parcel keep while planning
    resolution: float = 0.01  # rad: longest joint-space step (Euclidean) between checked states
    seed: int = 1  # OMPL RNG seed, set before every search (0 is not allowed by OMPL)
    rrt_range: float = 0.5  # rad: RRTConnect's extension step
    joint_window: float = math.pi  # rad: continuous joints search within this of min/max(start, goal)
    shortcut_rounds: int = 3  # greedy shortcut passes after OMPL's vertex reduction
    self_collision: bool = True  # also check the wrist and tool against the base, shoulder and upper arm

    def __post_init__(self) -> None:
        for name in ("resolution", "rrt_range", "joint_window"):
            if not getattr(self, name) > 0:
                raise ValueError(f"PlannerConfig.{name} must be > 0, got {getattr(self, name)}")
        if isinstance(self.check_budget, bool) or not isinstance(self.check_budget, int) or self.check_budget < 1:
            raise ValueError(f"PlannerConfig.check_budget must be an int >= 1, got {self.check_budget!r}")
        if self.margin < 0:
            raise ValueError(f"PlannerConfig.margin must be >= 0, got {self.margin}")
        if self.seed < 1:
            raise ValueError(f"PlannerConfig.seed must be >= 1 (OMPL rejects 0), got {self.seed}")
        if self.shortcut_rounds < 0:
            raise ValueError(f"PlannerConfig.shortcut_rounds must be >= 0, got {self.shortcut_rounds}")
        if isinstance(self.retries, bool) or not isinstance(self.retries, int) or self.retries < 0:
            raise ValueError(f"PlannerConfig.retries must be an int >= 0, got {self.retries!r}")


@dataclass
class Attachment:
    """A parcel held rigidly by the tool: ``tool_T_body`` is its pybullet base frame (the inertial
    frame that getBasePositionAndOrientation reports) in the tool-tip frame, 4x4."""

    body: int
    tool_T_body: np.ndarray

    def __post_init__(self) -> None:
        T = np.asarray(self.tool_T_body, dtype=np.float64)
        if T.shape != (4, 4) or not np.allclose(T[3], [0, 0, 0, 1]):
            raise ValueError(f"Attachment.tool_T_body must be a 4x4 homogeneous transform, got {T.shape}")
        self.tool_T_body = T
        # the same transform as pybullet's (position, xyzw quaternion), for placing the body fast
        self._relative = (T[:3, 3].tolist(), Rotation.from_matrix(T[:3, :3]).as_quat().tolist())

    @classmethod
    def current(cls, arm: Gen3Arm, body: int) -> Attachment:
        """The attachment of ``body`` at its present pose relative to the arm's present tool pose."""
        pos, R = arm.kin.tool_pose(arm.q)
        world_T_tool = _transform(pos, R)
        bpos, born = p.getBasePositionAndOrientation(body, physicsClientId=arm.client)
        world_T_body = _transform(np.array(bpos), Rotation.from_quat(born).as_matrix())
        return cls(body, np.linalg.inv(world_T_tool) @ world_T_body)


@dataclass
class Collision:
    """The first violation found: which arm link (or ``HELD_LINK``) came within the margin of which
    body, where (on the arm/parcel side, world frame), and the signed distance (m, < 0 penetrating)."""

    link: str
    body: int
    position: np.ndarray
    distance: float = 0.0

    def __str__(self) -> str:
        return f"{self.link} within {self.distance * 1000:.1f} mm of body {self.body}"


@dataclass
class PlanStats:
    """What the last ``plan`` call did."""

    method: str = ""  # 'straight', 'rrt' or 'failed'
    seconds: float = 0.0
    checks: int = 0  # configurations checked
    waypoints: int = 0
    failure: str | None = None
    extra: dict = field(default_factory=dict)


def _transform(pos: np.ndarray, R: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, pos
    return T


class MotionPlanner:
    """Collision queries and RRTConnect plans for ``arm`` in the pybullet world ``sim_client``."""

    def __init__(self, arm: Gen3Arm, sim_client: int | None = None, config: PlannerConfig | None = None) -> None:
        self.arm = arm
        self.client = arm.client if sim_client is None else sim_client
        if self.client != arm.client:
            raise ValueError(f"MotionPlanner: sim_client {sim_client} is not the arm's client {arm.client}")
        self.config = config or PlannerConfig()
        self._links = list(range(-1, p.getNumJoints(arm.body, physicsClientId=self.client)))
        index = {name: i for i, name in arm.link_names.items()} | {"base_link": -1}
        self._self_pairs = np.array([(index[a], index[b]) for a, b in SELF_PAIRS])
        self.checks = 0
        self.stats = PlanStats()
        self.last_failure: str | None = None

    # --- queries -----------------------------------------------------------------------------------
    @contextmanager
    def _preserved(self, attached: Attachment | None) -> Iterator[None]:
        """Put the arm (and the held parcel) back exactly as they were after kinematic queries."""
        c = self.client
        q, qd = self.arm.q.copy(), self.arm.qd.copy()
        saved = None
        if attached is not None:
            saved = (p.getBasePositionAndOrientation(attached.body, physicsClientId=c),
                     p.getBaseVelocity(attached.body, physicsClientId=c))
        try:
            yield
        finally:
            self.arm.set_joints(q, qd)
            if saved is not None and attached is not None:
                (pos, orn), (lin, ang) = saved
                p.resetBasePositionAndOrientation(attached.body, pos, orn, physicsClientId=c)
                p.resetBaseVelocity(attached.body, lin, ang, physicsClientId=c)

    def _near(self, lo: np.ndarray, hi: np.ndarray, margin: float, exclude: set[int]) -> list[int]:
        found = p.getOverlappingObjects((lo - margin).tolist(), (hi + margin).tolist(), physicsClientId=self.client)
        return sorted({o[0] for o in (found or ())} - exclude)

    def _check_placed(self, attached: Attachment | None, margin: float, exclude: set[int],
                      first: bool = True) -> Collision | None:
        """Check the arm as it is placed now (and the parcel, placed here at the tool pose): the first
        violation found, or with ``first=False`` the closest of all (a full scan)."""
        c, arm = self.client, self.arm
        self.checks += 1
        closest: Collision | None = None

        def found(hit: Collision) -> bool:  # True: stop scanning
            nonlocal closest
            if closest is None or hit.distance < closest.distance:
                closest = hit
            return first

        boxes = np.array([p.getAABB(arm.body, j, physicsClientId=c) for j in self._links])
        skip = exclude | {arm.body} | ({attached.body} if attached is not None else set())
        reach = max(margin, 0.0)  # a negative margin asks for penetrations deeper than -margin
        for body in self._near(boxes[1:, 0].min(axis=0), boxes[1:, 1].max(axis=0), reach, skip):
            for cp in p.getClosestPoints(arm.body, body, reach, physicsClientId=c):
                # the base never moves and sits in its pedestal (queries ignore collision filters)
                if cp[3] == -1 or (body == arm.pedestal and cp[3] == 0):
                    continue
                if cp[8] < margin and found(Collision(arm.link_names[cp[3]], body, np.array(cp[5]), float(cp[8]))):
                    return closest
        if self.config.self_collision:
            hit = self._self_hit(boxes)
            if hit is not None and found(hit):
                return closest
        if attached is None:
            return closest
        self.place_attachment(attached)
        lo, hi = (np.array(v) for v in p.getAABB(attached.body, -1, physicsClientId=c))
        for body in self._near(lo, hi, reach, skip):
            for cp in p.getClosestPoints(attached.body, body, reach, physicsClientId=c):
                if cp[8] < margin and found(Collision(HELD_LINK, body, np.array(cp[5]), float(cp[8]))):
                    return closest
        return closest

    def _self_hit(self, boxes: np.ndarray) -> Collision | None:
        """The first self-contact among ``SELF_PAIRS`` whose link boxes overlap (most configurations: none)."""
        a, b = self._self_pairs[:, 0] + 1, self._self_pairs[:, 1] + 1  # rows of ``boxes`` (base is row 0)
        overlap = np.all((boxes[a, 0] <= boxes[b, 1]) & (boxes[b, 0] <= boxes[a, 1]), axis=1)
        arm, c = self.arm, self.client
        for la, lb in self._self_pairs[overlap]:
            for cp in p.getClosestPoints(arm.body, arm.body, 0.0, linkIndexA=int(la), linkIndexB=int(lb),
                                         physicsClientId=c):
                if cp[8] < 0.0:
                    other = arm.link_names.get(int(lb), "base_link")
                    return Collision(f"{arm.link_names[int(la)]} (self: {other})", arm.body, np.array(cp[5]),
                                     float(cp[8]))
        return None

    def place_attachment(self, attached: Attachment) -> None:
        """Put the held parcel at the arm's present tool pose (as the attachment holds it)."""
        c, arm = self.client, self.arm
        tool = p.getLinkState(arm.body, arm.tip_link, computeForwardKinematics=True, physicsClientId=c)
        pos, orn = p.multiplyTransforms(tool[4], tool[5], *attached._relative, physicsClientId=c)
        p.resetBasePositionAndOrientation(attached.body, pos, orn, physicsClientId=c)

    def placed_collision(self, attached: Attachment | None = None, ignore_bodies: Iterable[int] = (),
                         margin: float | None = None) -> Collision | None:
        """Like ``collision`` for the arm where it is now; the held parcel is moved to the tool pose
        and left there (kinematic carrying, as in ``Gen3Arm.sweep_trajectory``)."""
        m = self.config.margin if margin is None else margin
        return self._check_placed(attached, m, set(ignore_bodies))

    def _check(self, q: np.ndarray, attached: Attachment | None, margin: float, exclude: set[int],
               first: bool = True) -> Collision | None:
        self.arm.set_joints(q)
        return self._check_placed(attached, margin, exclude, first)

    def collision(self, q, attached: Attachment | None = None, ignore_bodies: Iterable[int] = (),
                  margin: float | None = None) -> Collision | None:
        """The first link (or the held parcel) within ``margin`` (default: the config's) of another body
        at configuration ``q``, or None. The arm and the parcel are left where they were."""
        q = self._as_q(q, "q")
        m = self.config.margin if margin is None else margin
        with self._preserved(attached):
            return self._check(q, attached, m, set(ignore_bodies))

    def _segment(self, q0: np.ndarray, q1: np.ndarray, attached, margin: float, exclude: set[int]
                 ) -> Collision | None:
        n = max(1, math.ceil(float(np.linalg.norm(q1 - q0)) / self.config.resolution))
        # endpoints first, then bisection order: a blocked segment is usually found early
        order = [n, 0] + _coarse_to_fine(n)
        for k in order:
            hit = self._check(q0 + (q1 - q0) * (k / n), attached, margin, exclude)
            if hit is not None:
                return hit
        return None

    def segment_collision(self, q0, q1, attached: Attachment | None = None, ignore_bodies: Iterable[int] = (),
                          margin: float | None = None) -> Collision | None:
        """The first collision on the straight joint segment q0 -> q1, checked every ``resolution`` rad."""
        q0, q1 = self._as_q(q0, "q0"), self._as_q(q1, "q1")
        m = self.config.margin if margin is None else margin
        with self._preserved(attached):
            return self._segment(q0, q1, attached, m, set(ignore_bodies))

    def path_collision(self, path: Sequence[np.ndarray], attached: Attachment | None = None,
                       ignore_bodies: Iterable[int] = (), margin: float | None = None) -> Collision | None:
        """The first collision along a joint polyline (each segment checked as in segment_collision)."""
        pts = [self._as_q(q, "path") for q in path]
        m = self.config.margin if margin is None else margin
        with self._preserved(attached):
            for a, b in itertools.pairwise(pts):
                hit = self._segment(a, b, attached, m, set(ignore_bodies))
                if hit is not None:
                    return hit
        return None

    # --- planning ----------------------------------------------------------------------------------
    def plan(self, q_start, q_goal, attached: Attachment | None = None, ignore_bodies: Iterable[int] = ()
             ) -> list[np.ndarray] | None:
        """A collision-free joint polyline [q_start, ..., q_goal], or None (reason in ``last_failure``
        and ``stats.failure``: start/goal in collision, or no path within the ``check_budget``).

        A start or goal closer than ``margin`` to something (e.g. a pre-grasp pose just above the pile)
        but not touching it is accepted: the whole plan then keeps half that clearance instead
        (``stats.extra['margin']``).
        """
        q0, q1 = self._as_q(q_start, "q_start"), self._as_q(q_goal, "q_goal")
        for name, q in (("q_start", q0), ("q_goal", q1)):
            if np.any(q < self.arm.lower - 1e-9) or np.any(q > self.arm.upper + 1e-9):
                raise ValueError(f"{name} is outside the joint limits: {q}")
        exclude = set(ignore_bodies)
        m = self.config.margin
        t0, checks0 = time.perf_counter(), self.checks
        self.stats = PlanStats()
        self.last_failure = None
        with self._preserved(attached):
            path, method, failure = None, "failed", None
            for name, q in (("start", q0), ("goal", q1)):
                hit = self._check(q, attached, m, exclude, first=False)
                if hit is not None and hit.distance <= 0.0:
                    failure = f"{name} in collision: {hit}"
                    break
                if hit is not None:
                    m = min(m, 0.5 * hit.distance)
            else:
                if self._segment(q0, q1, attached, m, exclude) is None:
                    path, method = [q0, q1], "straight"
                else:
                    budget = self.config.check_budget
                    for attempt in range(self.config.retries + 1):
                        path = self._rrt(q0, q1, attached, m, exclude, budget * 2**attempt, attempt)
                        if path is not None:
                            break
                    if path is None:
                        spent = budget * (2 ** (self.config.retries + 1) - 1)
                        failure = (f"no collision-free path within {spent} state checks (RRTConnect, "
                                   f"{self.config.retries + 1} searches)")
                    else:
                        path, method = self._shortcut(path, attached, m, exclude), "rrt"
        self.stats = PlanStats(method, time.perf_counter() - t0, self.checks - checks0,
                               0 if path is None else len(path), failure, {"margin": m})
        self.last_failure = failure
        return path

    def _bounds(self, q0: np.ndarray, q1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Joint box of the search: the limits, with the +-2 pi continuous joints cut to a window."""
        lo, hi = self.arm.lower.copy(), self.arm.upper.copy()
        w = self.config.joint_window
        wide = (hi - lo) > 2 * math.pi
        lo[wide] = np.maximum(lo[wide], np.minimum(q0, q1)[wide] - w)
        hi[wide] = np.minimum(hi[wide], np.maximum(q0, q1)[wide] + w)
        return lo, hi

    def _rrt(self, q0, q1, attached, margin, exclude, budget: int | None = None,
             attempt: int = 0) -> list[np.ndarray] | None:
        """RRTConnect until a path or ``budget`` state checks (default the config's), seeded with the config's
        seed + ``attempt``: the same inputs give the same answer however loaded the machine is."""
        cfg = self.config
        budget = cfg.check_budget if budget is None else budget
        checked = [0]
        level = ou.getLogLevel()
        ou.setLogLevel(ou.LogLevel.LOG_NONE)  # re-seeding after the first plan logs an error by design
        try:
            ou.RNG.setSeed(cfg.seed + attempt)
            space = ob.RealVectorStateSpace(ARM_DOF)
            lo, hi = self._bounds(q0, q1)
            bounds = ob.RealVectorBounds(ARM_DOF)
            for i in range(ARM_DOF):
                bounds.setLow(i, float(lo[i]))
                bounds.setHigh(i, float(hi[i]))
            space.setBounds(bounds)
            ss = og.SimpleSetup(space)

            def valid(state) -> bool:
                checked[0] += 1
                q = np.fromiter((state[i] for i in range(ARM_DOF)), dtype=np.float64, count=ARM_DOF)
                return self._check(q, attached, margin, exclude) is None

            ss.setStateValidityChecker(valid)
            si = ss.getSpaceInformation()
            si.setStateValidityCheckingResolution(min(1.0, cfg.resolution / space.getMaximumExtent()))
            planner = og.RRTConnect(si)
            planner.setRange(cfg.rrt_range)
            ss.setPlanner(planner)
            start, goal = space.allocState(), space.allocState()
            start[0:ARM_DOF] = q0.tolist()
            goal[0:ARM_DOF] = q1.tolist()
            ss.setStartAndGoalStates(start, goal)
            status = ss.solve(ob.PlannerTerminationCondition(lambda: checked[0] >= budget))
            if not ss.haveExactSolutionPath():
                return None
            path = ss.getSolutionPath()
            simplifier = og.PathSimplifier(si)
            simplifier.reduceVertices(path, 0, 0, 0.33)
            simplifier.collapseCloseVertices(path, 0, 0)
            states = [np.array(s[0:ARM_DOF]) for s in path.getStates()]
            del status
        finally:
            ou.setLogLevel(level)
        states[0], states[-1] = q0.copy(), q1.copy()
        return states

    def _shortcut(self, path: list[np.ndarray], attached, margin, exclude) -> list[np.ndarray]:
        """Greedy shortcut: from each kept vertex jump to the farthest vertex it sees in a straight line."""
        for _ in range(self.config.shortcut_rounds):
            out, i = [path[0]], 0
            while i < len(path) - 1:
                j = len(path) - 1
                while j > i + 1 and self._segment(path[i], path[j], attached, margin, exclude) is not None:
                    j -= 1
                out.append(path[j])
                i = j
            if len(out) == len(path):
                break
            path = out
        return path

    @staticmethod
    def _as_q(q, name: str) -> np.ndarray:
        arr = np.asarray(q, dtype=np.float64)
        if arr.shape != (ARM_DOF,) or not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} must be {ARM_DOF} finite joint values, got shape {arr.shape}")
        return arr


def _coarse_to_fine(n: int) -> list[int]:
    """Interior sample indices 1..n-1, midpoints first (breadth-first bisection): a blocked segment
    is usually found after a few checks."""
    out: list[int] = []
    queue = deque([(0, n)])
    while queue:
        a, b = queue.popleft()
        if b - a < 2:
            continue
        m = (a + b) // 2
        out.append(m)
        queue.extend(((a, m), (m, b)))
    return out
