"""One physical pick attempt as a sequence of named moves; physics, not the label, decides it.

Each move returns a ``MoveReport``; the first that fails ends the attempt with a typed ``Failure``
(move, arm link, condition, body). The moves (docs/cell.md, 'Moves'):

- ``plan``: verified IK for the hover point, the descent to the pre-grasp point ``p + d_pre n`` and
  the approach line to ``p - overshoot n`` (``unreachable`` otherwise). The hover height comes from
  the pile: the highest parcel, fixture or wall near the pick, plus a margin.
- ``hover``: a planned free-space move to the hover configuration (collision-free by construction).
- ``descend``: a straight line down to the pre-grasp point (checked before it is run).
- ``approach``: a guarded line along ``-n`` with dynamics, stopped at the first cup contact
  (``no_contact`` past the overshoot; another link, or the cup on the bin: ``collision``).
- ``seal``: the vacuum builds while the cup rests; the bellows cup's seal is judged at the actual lip
  pose on the true mesh (``no_seal`` below threshold); its quality sets the vacuum (``suction.cup``).
- ``lift`` and ``transport``: the parcel is attached and carried along straight Cartesian lines with
  the tool on its contact axis and yaw, up to a height cleared above the pile and the rim, then over
  to the drop zone, timed so the predicted ring loads stay within ``carry_load_target``. Every step the
  physical wrench (Newton-Euler of the held parcel plus its real contacts, ``suction.cup``) is checked
  against Dex-Net 3.0's ring conditions: a sustained violation is ``dropped`` (condition named); a
  held parcel pressing on a wall or another parcel is ``collision`` (that body named). A parcel touching
  a wall or neighbour sideways is first moved a few millimetres off it (``_break_away``); a tilted pick whose lift or
  transport no IK solves at its contact axis is turned down about the lip first (``_turn_down``; the lift
  turns once the parcel clears its neighbours, ``_turned_lift``).
- ``release``: at the drop zone the parcel is released and leaves the scene (``success``).
- ``retreat``: back to home (it never changes the outcome).
"""

from __future__ import annotations

import dataclasses
import math
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from typing import Any, Callable, TypeVar

import numpy as np
import pybullet as p
import trimesh
from scipy.spatial.transform import Rotation

from parcelpick_env.envs.config import GraspConfig
from parcelpick_env.robot.arm import LINE_STEP, MAX_IK_JUMP, Contact, Gen3Arm
from parcelpick_env.robot.planning import Attachment
from parcelpick_env.robot.timing import Trajectory, concatenate, hold_trajectory, joint_trajectory, path_trajectory
from parcelpick_env.scene.scene import BinSpec, ParcelState, Scene
from parcelpick_env.sim.simulator import Simulator
from parcelpick_env.suction.config import SuctionConfig
from parcelpick_env.suction.cup import (CONDITIONS, Contacts, HoldMonitor, ToolState, contact_forces, mesh_inertia,
                                        suction_ring_ratios)
from parcelpick_env.suction.geometry import tangent_frames
from parcelpick_env.suction.physical import lip_face
from parcelpick_env.suction.scorer import SuctionScorer

__all__ = ["OUTCOMES", "CONDITIONS", "MOVES", "Failure", "MoveReport", "PickResult", "PickExecutor",
           "cup_loads", "suction_ring_ratios"]

OUTCOMES: tuple[str, ...] = ("success", "unreachable", "no_contact", "no_seal", "dropped", "collision",
                             "invalid_action")
MOVES: tuple[str, ...] = ("plan", "hover", "descend", "approach", "seal", "lift", "transport", "release",
                          "retreat")
SLOWDOWN_TRIES = 6  # PickExecutor._timed_within: slow-downs measured again before the exact re-timing
HOVER_RISE = 1e-3  # m: a hover less than this above the pre-grasp point is the pre-grasp point (no descent)
LIP_SEAT_BAND = 0.005  # m: the lip is seated on the collision hull when it lies this close along the axis
SIDEWAYS_NORMAL_Z = 0.5  # a contact whose normal is within 60 deg of horizontal presses sideways (else bears or loads)
# the break-away leaves every sideways contact at least this cosine (80 deg) off its normal, or is not made
MIN_BREAK_AWAY_COS = math.cos(math.radians(80.0))
TURN_STEP = math.radians(3.0)  # rad between IK points when the tool is turned down about the lip

_T = TypeVar("_T")


def _required(value: _T | None, what: str) -> _T:
    """``value``, known to be set: a move reads what an earlier move of the attempt set (``_Pick``), and
    one run out of order fails here, naming what is missing, instead of deep inside numpy or pybullet."""
    if value is None:
        raise RuntimeError(f"PickExecutor: {what} is not set yet (a move ran before the one that sets it)")
    return value


def cup_loads(contacts: Contacts, exempt: set[int]) -> Contacts:
    """The contacts on a held parcel that load the cup (``PickExecutor._carry_step``): all but the exempt
    bodies' bearing ones (pushing up from below), and, while any of those still bears, all but the exempt
    bodies' sideways pushes too (``SIDEWAYS_NORMAL_Z``): the supports' friction reacts them, as it did at
    rest. Pushes from above (a parcel lying on it) always load the cup, as its own weight does."""
    bearing = contacts.bearing(exempt) & (contacts.normal_force > 0.0)
    if not np.any(bearing):
        return contacts
    sideways = contacts.from_bodies(exempt) & (np.abs(contacts.normals[:, 2]) < SIDEWAYS_NORMAL_Z)
    return contacts.without(~(bearing | sideways))


def away_from_all(normals: np.ndarray, min_cos: float = MIN_BREAK_AWAY_COS) -> np.ndarray | None:
    """The unit 2-D direction that moves a body most directly off all the contacts whose horizontal
    normals (``(k, 2)``, pointing into the body) are given: the bisector of the narrowest arc holding
    every normal, which maximises the smallest cosine to any of them. None when there are none, or
    when that cosine is below ``min_cos`` (the normals span half a turn or more: the body is wedged)."""
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 2)
    normals = normals[np.linalg.norm(normals, axis=1) > 1e-9]
    if len(normals) == 0:
        return None
    angle = np.sort(np.arctan2(normals[:, 1], normals[:, 0]))
    gaps = np.diff(np.append(angle, angle[0] + 2.0 * np.pi))
    widest = int(np.argmax(gaps))  # the arc holding every normal starts after the widest empty gap
    half = (2.0 * np.pi - gaps[widest]) / 2.0
    if math.cos(half) < min_cos:
        return None
    centre = angle[(widest + 1) % len(angle)] + half
    return np.array([math.cos(centre), math.sin(centre)])


@dataclass(frozen=True)
class Failure:
    """Why an attempt failed: the move, the arm link involved, the condition (a ring condition, a seal
    reason, why an action was invalid) and the other body (pybullet id), each None when not known."""

    move: str
    link: str | None = None
    condition: str | None = None
    body: int | None = None

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class MoveReport:
    """One move's result: ``outcome`` is 'ok' or the attempt's failing outcome (one of ``OUTCOMES``)."""

    move: str
    outcome: str = "ok"
    failure: Failure | None = None
    steps: int = 0
    duration: float = 0.0  # s of simulated time

    @property
    def ok(self) -> bool:
        return self.outcome == "ok"


@dataclass
class PickResult:
    """One attempt: its outcome (one of ``OUTCOMES``), the typed ``failure``, the contacted parcel and
    seal, each ring condition's peak load ratio, every move's report and the replay ``trace``."""

    outcome: str
    failure: Failure | None = None
    object_id: int | None = None
    body_id: int | None = None
    contact_point: np.ndarray | None = None  # where the cup axis meets the true mesh
    contact_axis: np.ndarray | None = None  # actual cup approach axis at contact
    seal: float | None = None
    peak_ratios: dict[str, float] = field(default_factory=dict)  # load / capacity per condition
    sim_time: float = 0.0
    dynamic_steps: int = 0
    moves: list[MoveReport] = field(default_factory=list)
    trace: list[dict[str, Any]] = field(default_factory=list)

    @property
    def failure_cause(self) -> str | None:
        """The condition when one is known, else 'move: link', else the move (older string form)."""
        f = self.failure
        if f is None:
            return None
        if f.condition:
            return f.condition
        return f"{f.move}: {f.link}" if f.link else f.move

    @property
    def failure_phase(self) -> str | None:
        return None if self.failure is None else self.failure.move


@dataclass
class _Pick:
    """What the moves of one attempt hand on to each other."""

    point: np.ndarray
    normal: np.ndarray
    axis: np.ndarray
    hover: np.ndarray
    pre: np.ndarray
    q_hover: np.ndarray | None = None
    descend: Trajectory | None = None  # hover -> pre-grasp (None when the hover is the pre-grasp point)
    approach: Trajectory | None = None  # pre-grasp -> p - overshoot n
    lift: Trajectory | None = None  # as executed, to set the parcel back down
    parcel: ParcelState | None = None
    seal: float | None = None
    contact_point: np.ndarray | None = None
    contact_axis: np.ndarray | None = None
    cid: int | None = None
    monitor: HoldMonitor | None = None
    supports: set[int] = field(default_factory=set)  # bodies touching the parcel when it was attached
    relief: np.ndarray | None = None  # horizontal move off the bodies pressing it sideways, at the lift's start
    x_axis: np.ndarray | None = None  # the cup's yaw, kept while carrying
    carry_axis: np.ndarray | None = None  # the tool axis while carrying: the contact axis, or straight down once turned
    com_in_tool: np.ndarray | None = None  # the held parcel's COM in the tool frame, as attached
    R_in_tool: np.ndarray | None = None  # and its rotation

    @property
    def held(self) -> ParcelState:
        """The parcel the cup came down on (set by ``approach``), for the moves after it."""
        return _required(self.parcel, "the contacted parcel (set by approach)")


class PickExecutor:
    """Runs pick attempts with one arm in one simulator."""

    def __init__(self, sim: Simulator, arm: Gen3Arm, grasp: GraspConfig, suction: SuctionConfig) -> None:
        self.sim, self.arm, self.grasp, self.suction = sim, arm, grasp, suction
        self.home_q = np.asarray(arm.config.home, dtype=np.float64)
        self.ready_q = self.home_q.copy()
        self.kin = arm.kin
        self.planner = arm.planner
        self._contact_config = dataclasses.replace(suction, seal_model="bellows")  # the physical cup's seal
        self._lip_face = lip_face(self._contact_config)  # (K, 2): where the cup's face can first touch
        self._trace: list[dict[str, Any]] = []
        self._next_trace = 0.0
        self._held: int | None = None
        self._move = "plan"
        self._reports: list[MoveReport] = []
        self._dynamic_steps = 0
        self._t0 = 0.0

    def ready_pose(self, spec: BinSpec) -> np.ndarray | None:
        """Joint angles with the cup straight down ``ready_height`` above the centre of the bin ``spec``, solved
        from the Kinova home (``ArmConfig.ik_seed``): the hover IK's seed (``set_ready_seed``), or None."""
        centre = np.array([*spec.center_xy, spec.floor_z + self.grasp.ready_height])
        return self.arm.ik(centre, np.array([0.0, 0.0, -1.0]), seed=np.asarray(self.arm.config.ik_seed, dtype=np.float64))

    def set_ready_seed(self, q: np.ndarray) -> None:
        """A configuration above the bin centre: seeds IK for the hover point."""
        self.ready_q = np.asarray(q, dtype=np.float64)

    # ------------------------------------------------------------------------------------ bookkeeping
    def _record(self) -> None:
        t = self.arm.sim_time
        if t + 1e-9 < self._next_trace:
            return
        self._next_trace = t + self.grasp.trace_interval
        tip, axis = self.kin.forward(self.arm.q)[:2]
        entry: dict[str, Any] = {"t": t, "move": self._move, "q": self.arm.q.copy(), "tip": tip, "axis": axis}
        if self._held is not None:
            entry["held"] = self._held
            entry["held_pose"] = self.sim.body_pose(self._held)
        self._trace.append(entry)

    def _report(self, move: str, outcome: str = "ok", failure: Failure | None = None, steps: int = 0,
                t_start: float | None = None) -> MoveReport:
        t_start = self.arm.sim_time if t_start is None else t_start
        rep = MoveReport(move, outcome, failure, steps, self.arm.sim_time - t_start)
        self._reports.append(rep)
        return rep

    def _result(self, outcome: str, failure: Failure | None = None, pick: _Pick | None = None) -> PickResult:
        kw: dict[str, Any] = {}
        if pick is not None and pick.parcel is not None:
            kw = {"object_id": pick.parcel.object_id, "body_id": pick.parcel.body_id, "seal": pick.seal,
                  "contact_point": pick.contact_point, "contact_axis": pick.contact_axis}
            if pick.monitor is not None:
                kw["peak_ratios"] = pick.monitor.peak_ratios
        return PickResult(outcome, failure, sim_time=self.arm.sim_time - self._t0,
                          dynamic_steps=self._dynamic_steps, moves=list(self._reports), trace=self._trace, **kw)

    # ------------------------------------------------------------------------------------ geometry
    @staticmethod
    def _obstacles(scene: Scene) -> list[int]:
        """Bodies a move must clear: the parcels and any fixtures of the scene (the bin is handled by
        its rim)."""
        return [ps.body_id for ps in scene.parcels] + list(scene.meta.get("fixtures", ()))

    def _obstacle_top(self, scene: Scene, xy: np.ndarray, radius: float, exclude: int | None = None) -> float:
        """Highest point of any parcel (but ``exclude``), fixture or bin wall whose footprint comes within
        ``radius`` of ``xy`` (the bin floor if none)."""
        spec = scene.bin
        top = spec.floor_z
        half = np.asarray(spec.inner_size) / 2
        if np.any(np.abs(np.asarray(xy) - np.asarray(spec.center_xy)) > half - radius):
            top = spec.floor_z + spec.wall_height
        for body in self._obstacles(scene):
            if body == exclude or not self.sim.has_body(body):
                continue
            lo, hi = self.sim.aabb(body)
            gap = np.maximum(np.maximum(lo[:2] - xy, xy - hi[:2]), 0.0)
            if float(np.linalg.norm(gap)) <= radius:
                top = max(top, float(hi[2]))
        return top

    def _line(self, q0: np.ndarray, end: np.ndarray, axis: np.ndarray, dt: float, max_speed: float,
              max_accel: float | None = None, x_axis: np.ndarray | None = None, step: float = LINE_STEP
              ) -> tuple[Trajectory | None, str | None]:
        """The tip on a straight line from its place at ``q0`` to ``end`` with the tool on ``axis`` (and
        yaw ``x_axis``): IK every ``step`` (``Gen3Arm.line_path``), then ``path_trajectory`` within
        the Gen3's joint limits, slowed until the tip's peak speed is within ``max_speed`` and its peak
        acceleration within ``max_accel`` (``_timed_within``). (trajectory, None) or (None, why)."""
        path, why = self.arm.line_path(q0, end, axis, x_axis, step)
        if path is None:
            return None, why

        def tip_peaks(traj: Trajectory) -> tuple[float, float]:
            motion = self._sampled_motion(traj)
            return (max(float(np.linalg.norm(m[2])) for m in motion),
                    max(float(np.linalg.norm(m[4])) for m in motion))

        return self._timed_within(path, dt, tip_peaks, max_speed, max_accel), None

    def _sampled_motion(self, traj: Trajectory) -> list[tuple[np.ndarray, ...]]:
        """``kin.tool_motion`` at every fourth sample of ``traj`` (the tool's peaks, as the time laws bound them)."""
        return [self.kin.tool_motion(traj.q[k], traj.qd[k], traj.qdd[k]) for k in range(0, len(traj), 4)]

    def _timed_within(self, path: np.ndarray, dt: float, peaks: Callable[[Trajectory], tuple[float, float]],
                      max_speed: float, max_accel: float | None) -> Trajectory:
        """``path_trajectory`` of ``path`` within the Gen3's limits, slowed until ``peaks`` (a tool speed and
        acceleration) are within ``max_speed`` and ``max_accel``.

        Two candidates: the full-speed move re-timed uniformly (``speed_scale`` s: speed s, acceleration s^2,
        each ramp 1/s longer), and the move slowed by ``JointLimits.slowed`` (velocity s, acceleration and jerk
        s^2, the ramps kept), measured again and slowed further while a peak is over (``SLOWDOWN_TRIES``
        times). The sooner of the two that is within the bounds is the move: the kept ramps win where they
        dominate (a heavy parcel's carry), the re-timing where the slowed move's higher acceleration peak
        needs more slowing down."""
        arm = self.arm
        fast = path_trajectory(path, arm.limits, dt)

        def needed(t: Trajectory) -> float:
            v, a = peaks(t)
            scale = min(1.0, max_speed / max(v, 1e-9))
            return scale if max_accel is None or a <= max_accel else min(scale, math.sqrt(max_accel / a))

        first = scale = needed(fast)
        if first >= 1.0:
            return fast
        retimed = path_trajectory(path, arm.limits, dt, 0.98 * first)
        total = 1.0
        for _ in range(SLOWDOWN_TRIES):
            total *= 0.98 * scale
            traj = path_trajectory(path, arm.limits.slowed(total), dt)
            if traj.duration >= retimed.duration:
                break  # slower still at each further slow-down
            scale = needed(traj)
            if scale >= 1.0:
                return traj
        return retimed

    def _line_collision(self, traj: Trajectory, attached: Attachment | None = None):
        """The first collision (planner's margin) at the samples of a Cartesian line, taken every
        ``LINE_STEP`` of tip travel at the carrying speed cap (``planner.collision`` per sample)."""
        stride = max(1, int(LINE_STEP / (self.grasp.carry_speed * traj.dt)))
        for q in list(traj.q[::stride]) + [traj.q[-1]]:
            hit = self.planner.collision(q, attached)
            if hit is not None:
                return hit
        return None

    # ------------------------------------------------------------------------------------ motion
    def _sweep(self, traj: Trajectory, attached: Attachment | None = None) -> None:
        """Kinematic move along a trajectory already known to be clear (the pile is at rest)."""
        self.arm.sweep_trajectory(traj, attached, on_step=self._record, check=False)

    def _execute(self, traj: Trajectory, stop: Callable[[list[Contact]], object] | None = None,
                 on_step: Callable[[], object] | None = None, allowed_links: set[int] | None = None):
        """Drive the arm along ``traj`` with dynamics (``Gen3Arm.execute``: motors, never reset)."""
        def step_world() -> None:
            self.sim.step(1)

        def after() -> object:
            self._record()
            return on_step() if on_step is not None else None

        res = self.arm.execute(traj, step_world, stop=stop, on_step=after, allowed_links=allowed_links)
        self._dynamic_steps += res.steps
        return res

    def _free_move(self, move: str, q_goal: np.ndarray) -> MoveReport:
        """A planned (collision-free by construction) free-space move to ``q_goal``."""
        t0 = self.arm.sim_time
        self._move = move
        traj, why = self.arm.free_trajectory(q_goal, self.grasp.control_dt_free)
        if traj is None:
            return self._report(move, "unreachable", Failure(move, condition=why), t_start=t0)
        self._sweep(traj)
        return self._report(move, t_start=t0)

    def _retreat(self, *back: Trajectory | None) -> None:
        """Back out along the given trajectories reversed, then home; never changes the outcome (an
        unplannable return goes straight, unchecked: nothing is simulated during kinematic moves)."""
        self._move = "retreat"
        t0, dt = self.arm.sim_time, self.grasp.control_dt_free
        path = [traj.q[0] for traj in back if traj is not None]
        if path:
            self._sweep(joint_trajectory(self.arm.q, path, self.arm.limits, dt))
        traj, _ = self.arm.free_trajectory(self.home_q, dt)
        self._sweep(traj if traj is not None else joint_trajectory(self.arm.q, [self.home_q], self.arm.limits, dt))
        self._report("retreat", t_start=t0)

    # ------------------------------------------------------------------------------------ attempt
    def begin(self) -> None:
        """Fresh bookkeeping (trace, move reports, step count, clock) for one step's moves: a pick or a push."""
        arm = self.arm
        self._trace, self._next_trace, self._held, self._reports = [], arm.sim_time, None, []
        self._t0, self._dynamic_steps, self._move = arm.sim_time, 0, "plan"
        self._record()

    def _among_the_pile(self) -> AbstractContextManager[None]:
        """The physics of a driven move with the pile awake around the tool (the approach, the seal's dwell, the
        lift, the settle after an attempt): ``lift_dt``, the coarsest step at which a parcel sliding off
        another does not tunnel through the floor, and the carry's solver iterations."""
        return self.sim.physics_overrides(timestep=self.grasp.lift_dt, solver_iterations=self.grasp.carry_solver_iterations)

    def settle_pile(self, scene: Scene) -> None:
        """After a step that ran dynamics, the rest of the pile comes to rest (``Simulator.settle``, at the physics
        of ``_among_the_pile``), all of it awake: a parcel the step left balanced at rest may still topple
        (docs/cell.md). The env and the oracle's twin (``CellTwin.rehearse_push``) settle alike."""
        bodies = [ps.body_id for ps in scene.parcels if self.sim.has_body(ps.body_id)]
        if bodies:
            with self._among_the_pile():
                self.sim.settle(bodies, max_steps=self.grasp.max_post_settle_steps)

    def attempt(self, scene: Scene, point: np.ndarray, normal: np.ndarray) -> PickResult:
        """One attempt at suction point ``point`` with outward unit ``normal`` (both world frame)."""
        self.begin()
        pick = self._plan(scene, np.asarray(point, dtype=np.float64), np.asarray(normal, dtype=np.float64))
        if isinstance(pick, MoveReport):
            return self._result(pick.outcome, pick.failure)
        for move in (self._hover, self._descend, self._approach, self._seal):
            rep = move(scene, pick)
            if not rep.ok:
                self._retreat(pick.approach, pick.descend)
                return self._result(rep.outcome, rep.failure, pick)
        for move in (self._lift, self._transport):
            rep = move(scene, pick)
            if not rep.ok:
                if rep.outcome == "unreachable" and pick.cid is not None:
                    self._set_down(pick)
                self._detach(pick)
                self._retreat()
                return self._result(rep.outcome, rep.failure, pick)
        self._release(pick)
        self._retreat()
        return self._result("success", None, pick)

    def refusal(self, scene: Scene, point: np.ndarray, normal: np.ndarray) -> Failure | None:
        """Why the cell would refuse a pick before anything moves, or None where it would go ahead: its plan
        (``_plan``: hover, descent and approach on the IK branch it takes, and the lift from there) and the
        descent's check against the scene (``_descend``). The arm and the scene are left as they were (the
        privileged oracle asks this of a twin of the cell, ``policies/cell_twin.py``)."""
        self._reports = []
        pick = self._plan(scene, np.asarray(point, dtype=np.float64), np.asarray(normal, dtype=np.float64))
        if isinstance(pick, MoveReport):
            return pick.failure
        hit = None if pick.descend is None else self._line_collision(pick.descend)
        return None if hit is None else Failure("descend", hit.link, body=hit.body)

    # ------------------------------------------------------------------------------------ moves
    def _plan(self, scene: Scene, point: np.ndarray, normal: np.ndarray) -> _Pick | MoveReport:
        """Hover, descent and approach on the IK branch nearest the ready pose; where that branch cannot
        approach, or the lift cannot rise from it (a wrist joint at its limit part-way up), the branch the
        Kinova home seed gives (``ArmConfig.ik_seed``), if that one does. A cell plans the whole pick before
        it moves: the branch chosen for the approach decides whether the parcel can be raised at all (in the
        oracle's 10-episode, 30-parcel heap, lifts failed on IK where the home-seeded branch at the same
        contact lifted: joint 6 reached its limit part-way up from the ready-pose branch)."""
        normal = normal / np.linalg.norm(normal)
        pick = self._plan_branch(scene, point, normal, self.ready_q)
        if not (isinstance(pick, _Pick) and self._lift_solves(scene, pick)):
            other = self._plan_branch(scene, point, normal, np.asarray(self.arm.config.ik_seed, dtype=np.float64))
            if isinstance(other, _Pick) and (isinstance(pick, MoveReport) or self._lift_solves(scene, other)):
                pick = other
        if isinstance(pick, MoveReport):
            return self._report("plan", pick.outcome, pick.failure)
        self._report("plan")
        return pick

    def _lift_solves(self, scene: Scene, pick: _Pick) -> bool:
        """Whether the straight lift from the contact, on the approach's IK branch, solves up to the carrying
        height (``_lift_height`` for the parcel the approach line meets first; yaw free, as the lift's
        fallback). Without a parcel on the line there is nothing to lift: True."""
        approach = _required(pick.approach, "the approach (set by plan)")
        start, end = pick.pre, pick.point - self.grasp.overshoot * pick.normal
        bodies = {ps.body_id for ps in scene.parcels}
        hits = [h for h in p.rayTest(start.tolist(), end.tolist(), physicsClientId=self.sim.client) if h[0] in bodies]
        if not hits:
            return True
        q_contact = self.arm.ik(pick.point, pick.axis, seed=approach.q[-1])
        if q_contact is None:
            return True  # the approach reaches the overshoot point; the lift's own IK decides
        top = self._lift_height(scene, hits[0][0], float(pick.point[2]))
        path, _ = self.arm.line_path(q_contact, np.array([pick.point[0], pick.point[1], top]), pick.axis)
        return path is not None

    def _plan_branch(self, scene: Scene, point: np.ndarray, normal: np.ndarray, seed: np.ndarray
                     ) -> _Pick | MoveReport:
        """The pick's free-space and approach moves with the hover IK seeded at ``seed``, or the (unfiled)
        report of the move that cannot be planned."""
        g, arm = self.grasp, self.arm
        axis = -normal
        pre = point + g.pregrasp_distance * normal
        clear = self._obstacle_top(scene, point[:2], g.hover_corridor) + g.hover_clearance
        hover = pre.copy()
        hover[2] = max(pre[2], clear)
        pick = _Pick(point, normal, axis, hover, pre)
        # an IK branch whose wrist would stand in a wall gives way to another (the yaw is free); a goal closer
        # than the planner's margin but not touching stays acceptable, as the planner accepts it
        pick.q_hover = arm.ik(hover, axis, seed=seed, valid=lambda q: self.planner.collision(q, margin=0.0) is None)
        high = hover[2] > pre[2] + HOVER_RISE
        why = None
        if pick.q_hover is not None and high:
            pick.descend, why = self._line(pick.q_hover, pre, axis, g.control_dt_free, g.carry_speed)
        if high and pick.descend is None:
            # above a heap the hover IK may find no answer, or a branch that cannot come straight down (it jumps
            # mid-line): solve at the pre-grasp point and climb the line instead, as high as the arm reaches
            climbed = self._climb(pre, hover, axis, seed)
            if climbed is not None and self.planner.collision(climbed, margin=0.0) is not None:
                climbed = None  # a climb that ends with a link inside the tote or the pile is no hover
            if climbed is not None:
                if float(self.kin.tool_pose(climbed)[0][2]) <= pre[2] + HOVER_RISE:  # no higher: hover at pre-grasp
                    pick.q_hover, high = climbed, False
                else:
                    descend, why_climbed = self._line(climbed, pre, axis, g.control_dt_free, g.carry_speed)
                    if descend is not None or pick.q_hover is None:
                        pick.q_hover, pick.descend, why = climbed, descend, why_climbed

        def failed(move: str, condition: str | None) -> MoveReport:
            return MoveReport("plan", "unreachable", Failure(move, condition=condition), 0, 0.0)

        if pick.q_hover is None:
            return failed("hover", "ik")
        q_pre = pick.q_hover
        if high:
            if pick.descend is None:
                return failed("descend", why)
            q_pre = pick.descend.q[-1]
        pick.approach, why = self._line(q_pre, point - g.overshoot * normal, axis, g.lift_dt, g.approach_speed)
        if pick.approach is None:
            return failed("approach", why)
        return pick

    def _climb(self, low: np.ndarray, high: np.ndarray, axis: np.ndarray, seed: np.ndarray) -> np.ndarray | None:
        """Joint angles for the highest point towards ``high`` reached from an IK answer at ``low`` and up the
        straight line between them (``cartesian_path``, every ``LINE_STEP``), or None without an answer at
        ``low``. A far, high hover pose that the seed above the bin centre does not converge to is usually one
        small step from a configuration that reaches the pile below it; one beyond the arm's reach gives way to
        the highest hover the arm reaches above the pick (the planned free move to it is still collision-free)."""
        q = self.arm.ik(low, axis, seed=seed)
        if q is None:
            return None
        n = max(1, math.ceil(float(np.linalg.norm(high - low)) / LINE_STEP))
        for point in low + (high - low) * (np.arange(1, n + 1)[:, None] / n):
            step = self.arm.cartesian_path(q, point[None], axis)
            if step is None or float(np.abs(step[0] - q).max()) > MAX_IK_JUMP:
                break
            q = np.asarray(step[0])
        return q

    def _hover(self, scene: Scene, pick: _Pick) -> MoveReport:
        return self._free_move("hover", _required(pick.q_hover, "the hover configuration (set by plan)"))

    def _descend(self, scene: Scene, pick: _Pick) -> MoveReport:
        """Straight down to the pre-grasp point, checked against the scene before it is run."""
        self._move, t0 = "descend", self.arm.sim_time
        if pick.descend is None:
            return self._report("descend", t_start=t0)
        hit = self._line_collision(pick.descend)
        if hit is not None:
            return self._report("descend", "unreachable", Failure("descend", hit.link, body=hit.body), t_start=t0)
        self._sweep(pick.descend)
        return self._report("descend", t_start=t0)

    def _approach(self, scene: Scene, pick: _Pick) -> MoveReport:
        """Guarded line along -n with dynamics, ended by the cup pressing on something."""
        g, arm = self.grasp, self.arm
        self._move, t0 = "approach", arm.sim_time

        def touched(contacts: list[Contact]) -> Contact | None:
            return next((c for c in contacts if c.link == arm.cup_link and c.normal_force > g.touch_force), None)

        with self._among_the_pile():
            res = self._execute(_required(pick.approach, "the approach line (set by plan)"), stop=touched,
                                allowed_links={arm.cup_link, arm.tip_link})
        if res.collision is not None:
            return self._report("approach", "collision", Failure("approach", res.link, body=res.collision.body),
                                res.steps, t0)
        if res.stopped_by is None:
            return self._report("approach", "no_contact", Failure("approach", "suction_cup"), res.steps, t0)
        contact: Contact = res.stopped_by
        parcel = next((ps for ps in scene.parcels if ps.body_id == contact.body), None)
        if parcel is None:  # the cup came down on the bin or a fixture
            return self._report("approach", "collision", Failure("approach", "suction_cup", body=contact.body),
                                res.steps, t0)
        pick.parcel = parcel
        return self._report("approach", steps=res.steps, t_start=t0)

    def _seal(self, scene: Scene, pick: _Pick) -> MoveReport:
        """The cup rests (driven, holding its place) while the vacuum builds, then the seal is judged
        at the actual lip pose."""
        g, arm = self.grasp, self.arm
        self._move, t0 = "seal", arm.sim_time
        with self._among_the_pile():
            res = self._execute(hold_trajectory(arm.q, g.seal_dwell, g.lift_dt), allowed_links={arm.cup_link, arm.tip_link})
        tip, orn = arm.tip_pose()
        axis = Rotation.from_quat(orn).as_matrix()[:, 2]
        parcel = pick.held
        seal, hit, reason = self._seal_at(parcel, self._seated_lip(parcel.body_id, tip, axis), axis)
        pick.seal, pick.contact_point, pick.contact_axis = seal, hit, axis
        if seal < g.seal_threshold:
            return self._report("seal", "no_seal", Failure("seal", "suction_cup", reason, parcel.body_id),
                                res.steps, t0)
        return self._report("seal", steps=res.steps, t_start=t0)

    def _seated_lip(self, body: int, tip: np.ndarray, axis: np.ndarray) -> np.ndarray:
        """Where the lip sits on the parcel's collision hull along the cup axis: as far along it as the
        cup's face (``lip_face``: rim and disk) goes before its first point meets the hull.

        The rigid cup and the hull's collision margin leave the lip frame 2-3 mm short of the hull
        at rest (numerics, not a physical gap); the bellows lip lies on the hull. What remains
        between the hull and the true mesh (a mailer's wrinkles) is the real gap the seal judges.
        The face, not the axis alone: on a hull tilted to the cup the uphill rim touches first, and
        the axis meets the hull further down (7 mm on a mailer's wrinkle tilted 17 deg), beyond the
        band, so the margin's 2-3 mm stayed in the seal as a gap (0.006 there; 0.54 seated).
        """
        u, w = tangent_frames(-axis[None])
        starts = tip + self._lip_face[:, :1] * u + self._lip_face[:, 1:] * w
        hits = p.rayTestBatch((starts - 0.05 * axis).tolist(), (starts + LIP_SEAT_BAND * axis).tolist(),
                              physicsClientId=self.sim.client)
        on_body = [k for k, hit in enumerate(hits) if hit[0] == body]
        if not on_body:
            return tip
        depth = (np.array([hits[k][3] for k in on_body]) - starts[on_body]) @ axis
        shift = float(depth.min()) + self.sim.config.collision_margin
        return tip + shift * axis if abs(shift) <= LIP_SEAT_BAND else tip

    def _seal_at(self, parcel: ParcelState, tip: np.ndarray, axis: np.ndarray
                 ) -> tuple[float, np.ndarray | None, str | None]:
        """(seal quality, where the cup axis meets the true mesh, why it failed) at the lip pose.

        The bellows cup's ``contact_seal`` (suction/cup_seal.py) judges the actual lip position and
        axis, including any gap to the true surface; the reason is its verdict ('edge', 'tilt', 'gap',
        ...), or 'weak' for a seal that closes below ``seal_threshold``.
        """
        pos, orn = self.sim.body_pose(parcel.body_id)
        parcel.position, parcel.orientation = pos, orn
        mesh: trimesh.Trimesh = parcel.world_mesh()
        origin = tip - 0.05 * axis
        locations, _, _ = mesh.ray.intersects_location(origin[None], axis[None], multiple_hits=False)
        hit = locations[np.argmin(np.linalg.norm(locations - origin, axis=1))] if len(locations) else None
        scorer = SuctionScorer([mesh], parcel.world_com()[None], config=self._contact_config)
        found = scorer.contact_seal(tip[None], axis[None], np.zeros(1, dtype=np.int64))
        seal = float(found.quality[0])
        reason = str(found.reason_names()[0])
        if seal >= self.grasp.seal_threshold:
            return seal, hit, None
        return seal, hit, "weak" if reason == "sealed" else reason

    def _attach(self, pick: _Pick) -> None:
        """Fixed constraint from the cup lip to the parcel at their present relative pose; the wrench
        is read from the cup's model (``HoldMonitor``), never from this constraint."""
        c, arm, parcel = self.sim.client, self.arm, pick.held
        body = parcel.body_id
        # before the filter change below, which drops the body's contact manifolds until the next step
        touching = contact_forces(c, body, {arm.body})
        pick.supports = {int(b) for b in touching.bodies}
        pick.relief = self._break_away(touching)
        tip, orn = arm.tip_pose()
        bpos, born = p.getBasePositionAndOrientation(body, physicsClientId=c)  # COM frame
        inv_p, inv_o = p.invertTransform(bpos, born)
        child_p, child_o = p.multiplyTransforms(inv_p, inv_o, tip.tolist(), orn.tolist())
        for link in range(-1, p.getNumJoints(arm.body, physicsClientId=c)):
            p.setCollisionFilterPair(arm.body, body, link, -1, 0, physicsClientId=c)
        pick.cid = p.createConstraint(arm.body, arm.tip_link, body, -1, p.JOINT_FIXED, [0, 0, 0], [0, 0, 0],
                                      child_p, childFrameOrientation=child_o, physicsClientId=c)
        p.changeConstraint(pick.cid, maxForce=1e5, physicsClientId=c)
        self._held = body
        asset = parcel.asset
        pick.monitor = HoldMonitor(self.grasp.cup, self.suction.cup_radius, self.suction.material_k,
                                   self.sim.config.gravity, asset.mass, mesh_inertia(asset.mesh, asset.mass),
                                   _required(pick.seal, "the seal quality (set by seal)"))
        pick.x_axis = self.kin.tip_x(arm.q)
        tool_p, tool_R = self.kin.tool_pose(arm.q)
        com, R_body = self._body_state(body)
        pick.com_in_tool, pick.R_in_tool = tool_R.T @ (com - tool_p), tool_R.T @ R_body

    def _detach(self, pick: _Pick) -> None:
        if pick.cid is None:
            return
        c = self.sim.client
        p.removeConstraint(pick.cid, physicsClientId=c)
        pick.cid = None
        body = pick.held.body_id
        if self.sim.has_body(body):
            for link in range(-1, p.getNumJoints(self.arm.body, physicsClientId=c)):
                p.setCollisionFilterPair(self.arm.body, body, link, -1, 1, physicsClientId=c)
        self._held = None

    def _body_state(self, body: int) -> tuple[np.ndarray, np.ndarray]:
        """A body's COM (world) and rotation matrix, as simulated."""
        pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=self.sim.client)  # COM frame
        return np.asarray(pos), np.asarray(p.getMatrixFromQuaternion(orn)).reshape(3, 3)

    @staticmethod
    def _held_pose(pick: _Pick, tool: ToolState) -> tuple[np.ndarray, np.ndarray]:
        """COM and rotation of the held parcel where the grasp puts it: rigid in the tool frame as
        attached (the simulated constraint's position lag is numerics, not a changing lever)."""
        return tool.tip + tool.R @ pick.com_in_tool, tool.R @ pick.R_in_tool

    def _carry_step(self, pick: _Pick, move: str, exempt: set[int], dt: float) -> Callable[[], object]:
        """The per-step hold check of a carrying move.

        A held parcel pressing harder than ``ArmConfig.collision_force`` (the arm links' own rule) on a
        body other than the ``exempt`` ones (those it touched when attached, during the lift) has struck
        it, and so has one whose seal breaks while it touches such a body: collision, that body named.
        The cup's wrench counts every contact but the exempt bodies' bearing ones (pushing up from
        below): while the parcel still rests there, how the load splits between the cup and its
        support is statically indeterminate, so the cup is taken to carry it all. For as long as it
        still bears on them, the exempt bodies' sideways pushes (walls and neighbours that pressed it
        at rest) are left out as well (``cup_loads``): at rest the supports' friction reacted them, and
        dropping the supports' reaction but keeping those pushes charged the cup with a load that
        nothing exerts. Walls did so at 1-3 N (a tube resting on a neighbour's flank is pressed into
        the corner; torsion drops at the first millimetre of the lift), and so did leaning neighbours
        (a torsion ratio of 3 at the first step of a lift, before the tool had moved). Once the parcel
        is off its supports, every contact counts in full. A ring condition
        violated for ``CupSpec.violation_time`` in a row (steps of ``dt``) breaks the seal: dropped.
        """
        strike, client, body = self.arm.config.collision_force, self.sim.client, pick.held.body_id
        monitor = _required(pick.monitor, "the hold monitor (set when the parcel is attached)")

        def check() -> tuple[str, Failure] | None:
            contacts = contact_forces(client, body, {self.arm.body})
            foreign = (contacts.normal_force > 0.0) & ~contacts.from_bodies(exempt)
            hardest = None if not np.any(foreign) else int(
                contacts.bodies[np.flatnonzero(foreign)[np.argmax(contacts.normal_force[foreign])]])
            if np.any(foreign & (contacts.normal_force > strike)):
                return "collision", Failure(move, "held parcel", body=hardest)
            loads = cup_loads(contacts, exempt)
            # pose and velocity measured, acceleration as commanded (the executed trajectory's)
            qdd = _required(self.arm.command, "the arm's servoed command (set by Gen3Arm.execute)")[2]
            tool = ToolState(*self.kin.tool_motion(self.arm.q, self.arm.qd, qdd))
            cause = monitor.update(tool, *self._held_pose(pick, tool), loads.points, loads.forces, dt=dt)
            if cause is None:
                return None
            if hardest is not None:  # the seal broke while the parcel was pressing on something: it struck it
                return "collision", Failure(move, "held parcel", cause, hardest)
            return "dropped", Failure(move, "suction_cup", cause, body)

        return check

    def _dozing_once_clear(self, check: Callable[[], object], held: int, pile: list[int],
                           doze: Callable[[list[int]], list[int]], dt: float) -> Callable[[], object]:
        """``check``, and the resting pile put to sleep once the held parcel has touched none of ``pile`` for
        ``SimConfig.rest_window``, and again every window after while it stays clear (a neighbour that
        fell into the gap sleeps once it rests). Nearly nine lift steps in ten come after the parcel has left
        the pile (the oracle's picks in a 30-parcel heap); waiting a window first leaves awake whatever the
        parting set moving (a leaning neighbour falling is past the sleep tolerance by then)."""
        window = self.sim.rest_steps(dt)
        others, client = set(pile), self.sim.client
        clear = 0

        def step() -> object:
            nonlocal clear
            out = check()
            if out:
                return out
            touching = any(c[2] in others for c in p.getContactPoints(bodyA=held, physicsClientId=client))
            clear = 0 if touching else clear + 1
            if clear and clear % window == 0:
                doze(pile)
            return None

        return step

    def _carry(self, scene: Scene, pick: _Pick, move: str, end: np.ndarray, exempt: set[int],
               via: np.ndarray | None = None) -> MoveReport:
        """Carry the held parcel along the straight tip line to ``end`` at the contact axis and yaw,
        timed so that no predicted ring load exceeds ``carry_load_target`` (payload-aware motion)."""
        g, arm = self.grasp, self.arm
        self._move, t0 = move, arm.sim_time
        tool = ToolState(*self.kin.tool_motion(arm.q, np.zeros_like(arm.q), np.zeros_like(arm.q)))
        monitor = _required(pick.monitor, "the hold monitor (set when the parcel is attached)")
        a_max = monitor.allowed_acceleration(tool, *self._held_pose(pick, tool), g.carry_load_target,
                                             g.min_carry_acceleration)
        # the lift runs with the pile awake at the finer lift_dt (a neighbour sliding off must not tunnel)
        dt = g.lift_dt if move == "lift" else g.carry_dt
        if move == "transport":  # the chord, round the base where it dips inside the arm's reach, or turned down
            traj, why = self._transport_line(arm.q, end, pick, a_max)
        else:
            points = [end] if via is None else [via, end]
            traj, why = self._carry_legs(arm.q, points, pick, a_max, dt)
            if traj is None and move == "lift":
                traj, why = self._turned_lift(scene, arm.q, points, pick, a_max, dt, why)
        if traj is None:
            return self._report(move, "unreachable", Failure(move, condition=why), t_start=t0)
        if move == "transport":  # the held parcel is part of the check: it must clear the rim and the pile
            hit = self._line_collision(traj, Attachment.current(arm, pick.held.body_id))
            if hit is not None:
                return self._report(move, "unreachable", Failure(move, hit.link, body=hit.body), t_start=t0)
        if move == "lift":
            pick.lift = traj
        # the rest of the pile sleeps (Simulator.sleep_scope) until something strikes it: in transport from the
        # start, in the lift once the held parcel has left it (_dozing_once_clear)
        pile = [ps.body_id for ps in scene.parcels if ps.body_id != pick.held.body_id]
        with self.sim.physics_overrides(timestep=dt, solver_iterations=g.carry_solver_iterations), \
                self.sim.sleep_scope() as doze:
            check = self._carry_step(pick, move, exempt, dt)
            if move == "transport":
                doze(pile)
            else:
                check = self._dozing_once_clear(check, pick.held.body_id, pile, doze, dt)
            res = self._execute(traj, on_step=check)
        if res.collision is not None:
            return self._report(move, "collision", Failure(move, res.link, body=res.collision.body), res.steps, t0)
        if res.stopped_by is not None:
            outcome, failure = res.stopped_by
            return self._report(move, outcome, failure, res.steps, t0)
        return self._report(move, steps=res.steps, t_start=t0)

    def _carry_line(self, q0: np.ndarray, end: np.ndarray, pick: _Pick, a_max: float, dt: float | None = None
                    ) -> tuple[Trajectory | None, str | None]:
        """A carrying line at the contact axis, the cup's yaw held; failing that with the yaw free (the
        held yaw may need an IK branch switch: the cup may then turn, and the wrench has I alpha)."""
        g = self.grasp
        step = g.carry_dt if dt is None else dt
        axis = (_required(pick.contact_axis, "the contact axis (set by seal)") if pick.carry_axis is None
                else pick.carry_axis)
        traj, why = self._line(q0, end, axis, step, g.carry_speed, a_max, pick.x_axis)
        if traj is None:
            traj, why = self._line(q0, end, axis, step, g.carry_speed, a_max)
        return traj, why

    def _transport_line(self, q0: np.ndarray, end: np.ndarray, pick: _Pick, a_max: float
                        ) -> tuple[Trajectory | None, str | None]:
        """The transport: the chord at the contact axis, else round the base (``_carry_around``); for a
        tilted pick that neither solves, the tool is first turned about the lip to straight down
        (``_turn_down``), as a cell reorients a side-picked parcel once it is clear of the pile, and the
        chord or the detour is solved top-down from there."""
        traj, why = self._carry_line(q0, end, pick, a_max)
        if traj is None:
            traj, why = self._carry_around(q0, end, pick, a_max, why)
        if traj is not None:
            return traj, None
        turn, why_turn = self._turn_down(q0, pick, a_max)
        if turn is None:
            return None, why if why_turn is None else f"{why} (turned down: {why_turn})"
        def chord_or_around(q: np.ndarray) -> tuple[Trajectory | None, str | None]:
            rest, why_rest = self._carry_line(q, end, pick, a_max)
            return (rest, None) if rest is not None else self._carry_around(q, end, pick, a_max, why_rest)

        rest, why_rest = self._top_down_after(turn, pick, chord_or_around)
        return (concatenate([turn, rest]), None) if rest is not None else (None, f"{why} (turned down: {why_rest})")

    def _top_down_after(self, turn: Trajectory, pick: _Pick,
                        solve: Callable[[np.ndarray], tuple[Trajectory | None, str | None]]
                        ) -> tuple[Trajectory | None, str | None]:
        """The rest of the carry after ``turn`` (``_turn_down``), solved from its end by ``solve`` with the tool
        straight down; the carrying axis stays down when that solves, and is restored when it does not."""
        held = pick.carry_axis, pick.x_axis
        pick.carry_axis, pick.x_axis = np.array([0.0, 0.0, -1.0]), self.kin.tip_x(turn.q[-1])
        rest, why = solve(turn.q[-1])
        if rest is None:
            pick.carry_axis, pick.x_axis = held
        return rest, why

    def _turn_down(self, q0: np.ndarray, pick: _Pick, a_max: float, dt: float | None = None
                   ) -> tuple[Trajectory | None, str | None]:
        """The tool turned about the lip, tip held, from the carrying axis (the contact axis until turned) to
        straight down in steps of at most ``TURN_STEP``, timed at ``dt`` (``carry_dt`` if not given) so that
        the held parcel's centre of mass moves within ``a_max`` and the carrying speed (``omega |d|``,
        ``alpha |d|``); (None, None) when the tool is already top-down, (None, why) when no IK follows."""
        g, arm = self.grasp, self.arm
        step_dt = g.carry_dt if dt is None else dt
        axis = np.asarray(pick.contact_axis if pick.carry_axis is None else pick.carry_axis, dtype=np.float64)
        down = np.array([0.0, 0.0, -1.0])
        angle = float(np.arccos(np.clip(axis @ down, -1.0, 1.0)))
        if angle < TURN_STEP:
            return None, None
        about = np.cross(axis, down)
        about /= np.linalg.norm(about)
        tip = self.kin.tool_pose(q0)[0]
        path, q = [np.asarray(q0, dtype=np.float64)], q0
        n = math.ceil(angle / TURN_STEP)
        for k in range(1, n + 1):
            step = arm.cartesian_path(q, tip[None], Rotation.from_rotvec(about * angle * k / n).apply(axis))
            if step is None:
                return None, "ik failed turning the tool down"
            q = np.asarray(step[0])
            path.append(q)
        joints = np.asarray(path)
        jump = float(np.abs(np.diff(joints, axis=0)).max())
        if jump > MAX_IK_JUMP:
            return None, f"ik jumped {jump:.2f} rad turning the tool down"
        com_in_tool = _required(pick.com_in_tool, "the held parcel's centre of mass (set when attached)")
        lever = max(float(np.linalg.norm(com_in_tool)), 1e-3)

        def com_peaks(traj: Trajectory) -> tuple[float, float]:  # omega |d| and alpha |d|
            motion = self._sampled_motion(traj)
            return (max(float(np.linalg.norm(m[3])) for m in motion) * lever,
                    max(float(np.linalg.norm(m[5])) for m in motion) * lever)

        return self._timed_within(joints, step_dt, com_peaks, g.carry_speed, a_max), None

    def _turned_lift(self, scene: Scene, q0: np.ndarray, points: list[np.ndarray], pick: _Pick, a_max: float,
                     dt: float, why: str | None) -> tuple[Trajectory | None, str | None]:
        """The lift of a tilted pick that no IK raises to the carrying height at its contact axis: up that axis
        until the held parcel's underside clears every neighbour within its footprint (plus ``clearance``),
        the tool turned down about the lip there (``_turn_down``), then straight up to ``points[-1]``.

        Holding the tilt all the way up is what a wrist cannot always do: in the oracle's 30-parcel heap,
        8 of 52 failures were lifts of faces tilted ~17 deg whose wrist joint (6) reached its limit 30 cm up,
        on both IK branches the plan tries, where the same point is reached top-down. (None, why) when the
        pick is top-down, when the neighbours stand as high as the carrying height, or a leg does not solve.
        """
        g = self.grasp
        if float(_required(pick.contact_axis, "the contact axis (set by seal)")[2]) < -math.cos(TURN_STEP):
            return None, why  # already top-down: nothing to turn
        body = pick.held.body_id
        lo, hi = self.sim.aabb(body)
        tip = self.kin.tool_pose(q0)[0]
        end = np.asarray(points[-1], dtype=np.float64)
        radius = 0.5 * float(np.linalg.norm(hi[:2] - lo[:2])) + g.clearance
        clear = self._obstacle_top(scene, end[:2], radius, exclude=body) + g.clearance + (tip[2] - float(lo[2]))
        turn_z = max(clear, float(points[0][2]) if len(points) > 1 else float(tip[2]))
        if turn_z >= end[2]:
            return None, why
        # never a rise of zero: clear is at least clearance above the tip (the underside is above the floor),
        # and the break-away's via only break_away_rise
        rise, why_rise = self._carry_legs(q0, [*points[:-1], np.array([end[0], end[1], turn_z])], pick, a_max, dt)
        if rise is None:
            return None, f"{why} (turned down at {turn_z:.2f} m: {why_rise})"
        turn, why_turn = self._turn_down(rise.q[-1], pick, a_max, dt)
        if turn is None:
            return None, why if why_turn is None else f"{why} (turned down at {turn_z:.2f} m: {why_turn})"
        up, why_up = self._top_down_after(turn, pick, lambda q: self._carry_line(q, end, pick, a_max, dt))
        if up is None:
            return None, f"{why} (turned down at {turn_z:.2f} m: {why_up})"
        return concatenate([rise, turn, up]), None

    def _carry_around(self, q0: np.ndarray, end: np.ndarray, pick: _Pick, a_max: float, why: str | None
                      ) -> tuple[Trajectory | None, str | None]:
        """Transport in two straight legs through a via point that keeps the tool out in the arm's reach.

        The straight chord from a far corner of the tote to the drop zone passes close to the base, where
        a top-down tool needs the shoulder and wrist near their singular poses (IK jumps or fails). The via
        point lies at the mean azimuth about the base axis of the two ends and at the larger of their
        distances from it, at carrying height: the path a cell's teach-in would take round the column.
        Each leg is timed rest-to-rest."""
        base = np.asarray(self.arm.config.base_position[:2], dtype=np.float64)
        start = self.kin.tool_pose(q0)[0]
        rel = np.array([start[:2] - base, end[:2] - base])
        heading = np.arctan2(*np.sum(rel / np.linalg.norm(rel, axis=1, keepdims=True), axis=0)[::-1])
        reach = float(np.linalg.norm(rel, axis=1).max())
        via = np.array([*(base + reach * np.array([np.cos(heading), np.sin(heading)])), max(start[2], end[2])])
        traj, why_legs = self._carry_legs(q0, [via, end], pick, a_max)
        return (traj, None) if traj is not None else (None, f"{why} (round the base: {why_legs})")

    def _carry_legs(self, q0: np.ndarray, points: list[np.ndarray], pick: _Pick, a_max: float,
                    dt: float | None = None) -> tuple[Trajectory | None, str | None]:
        """Carrying lines through ``points`` in turn (``_carry_line``), each timed rest-to-rest."""
        legs, q = [], q0
        for point in points:
            leg, why = self._carry_line(q, point, pick, a_max, dt)
            if leg is None:
                return None, why
            legs.append(leg)
            q = leg.q[-1]
        return concatenate(legs), None

    def _break_away(self, touching: Contacts) -> np.ndarray | None:
        """The horizontal tip offset that takes the parcel off every body pressing it sideways at
        attachment, walls and neighbours alike (``GraspConfig.break_away`` along the direction farthest
        from all their horizontal contact normals, which point into the parcel: ``away_from_all``), or
        None when it touches none sideways or they surround it (no direction leaves every one).

        The pile presses a parcel against the walls and its neighbours; once it is lifted nothing does,
        and a real bellows cup, compliant sideways by millimetres, lets it relax off them. The simulated
        attachment is rigid: the arm's tracking drift of 0.1-0.8 mm under load then presses the parcel
        into a rigid wall at 2-4 N for the whole lift, a few centimetres off the cup axis (torsion drops
        measured on stacked piles, with the wall the only body pushing). A move off the walls alone drove
        it into a neighbour on the other side instead (0.5 N growing to 2.8 N over 4 mm of rise, 10 cm off
        the axis: the torsion drops of the cylindrical and mixed stacked grid). The tool makes the relief
        move itself."""
        lateral = np.abs(touching.normals[:, 2]) < SIDEWAYS_NORMAL_Z if len(touching.bodies) else np.zeros(0, bool)
        direction = away_from_all(touching.normals[lateral, :2])
        if direction is None:
            return None
        return np.array([*(self.grasp.break_away * direction), 0.0])

    def _lift_height(self, scene: Scene, body: int, tip_z: float) -> float:
        """Tip height for carrying parcel ``body`` held at tip height ``tip_z``: the pile top (every other
        parcel and fixture) or the rim, whichever is higher, plus the clearance and the parcel's extent
        below the lip; at least ``min_lift`` above ``tip_z``."""
        spec = scene.bin
        top = spec.floor_z + spec.wall_height
        for b in self._obstacles(scene):
            if b != body and self.sim.has_body(b):
                top = max(top, float(self.sim.aabb(b)[1][2]))
        below = tip_z - float(self.sim.aabb(body)[0][2])
        return max(top + self.grasp.clearance + below, tip_z + self.grasp.min_lift)

    def _lift(self, scene: Scene, pick: _Pick) -> MoveReport:
        self._attach(pick)
        tip = self.kin.tool_pose(self.arm.q)[0]
        top = np.array([tip[0], tip[1], self._lift_height(scene, pick.held.body_id, float(tip[2]))])
        if pick.relief is None:
            return self._carry(scene, pick, "lift", top, pick.supports)
        # break away: off what presses it sideways while rising the first break_away_rise, then straight up
        via = tip + pick.relief + np.array([0.0, 0.0, min(self.grasp.break_away_rise, top[2] - tip[2])])
        return self._carry(scene, pick, "lift", top + pick.relief, pick.supports, via)

    def _set_down(self, pick: _Pick) -> None:
        """A parcel that cannot be carried on is lowered back along the lift before it is let go (as a
        cell would put it back rather than drop it onto the pile); the outcome stays ``unreachable``."""
        lift = pick.lift
        if lift is None or float(np.abs(lift.q[-1] - self.arm.q).max()) > self.arm.config.start_tolerance:
            return
        down = Trajectory(lift.t, lift.q[::-1].copy(), -lift.qd[::-1], lift.qdd[::-1].copy(), lift.dt)
        self._move = "retreat"
        with self.sim.physics_overrides(timestep=down.dt, solver_iterations=self.grasp.carry_solver_iterations):
            self._execute(down)

    def _transport(self, scene: Scene, pick: _Pick) -> MoveReport:
        tip = self.kin.tool_pose(self.arm.q)[0]
        drop = np.array(self.grasp.drop_zone, dtype=np.float64)
        drop[2] = max(drop[2], tip[2])
        return self._carry(scene, pick, "transport", drop, set())

    def _release(self, pick: _Pick) -> None:
        t0 = self.arm.sim_time
        self._detach(pick)
        self.sim.remove(pick.held.body_id)
        self._report("release", t_start=t0)

