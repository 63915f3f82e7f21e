"""One physical pick attempt: physics, not the label, decides whether a parcel is delivered.

The sequence (DESIGN.md, 'Physical grasp check inside the environment'):

1. plan: verified IK for the hover point above the rim, the pre-grasp point ``p + d_pre n`` and the
   approach line down to ``p - overshoot n``; any failure is ``unreachable``;
2. free-space moves home -> hover -> pre-grasp, collision-checked at every control waypoint;
3. guarded approach along ``-n`` with dynamics, stopped at the first cup contact
   (nothing before the overshoot: ``no_contact``; the cup on the bin or any other link pressing on
   the scene: ``collision``);
4. seal at the actual contact: the cup axis is ray-cast onto the contacted parcel's true mesh and the
   shared ``SuctionScorer`` scores the seal there along the actual axis (``no_seal`` below threshold);
5. attach with a fixed constraint at the contact, lift clear of the rim and carry to the drop zone,
   reading the constraint's reaction wrench every step and checking Dex-Net 3.0's suction-ring
   conditions; a violation held for ``violation_steps`` steps releases the parcel (``dropped``, with
   the condition named);
6. at the drop zone the parcel is released and leaves the scene (``success``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pybullet as p
import trimesh

from parcelpick_env.envs.config import GraspConfig
from parcelpick_env.robot.arm import Contact, Gen3Arm
from parcelpick_env.scene.scene import ParcelState, Scene
from parcelpick_env.sim.simulator import Simulator
from parcelpick_env.suction.config import SuctionConfig
from parcelpick_env.suction.scorer import SuctionScorer

OUTCOMES: tuple[str, ...] = ("success", "unreachable", "no_contact", "no_seal", "dropped", "collision",
                             "invalid_action")
CONDITIONS: tuple[str, ...] = ("friction_x", "friction_y", "friction_torsion", "material_x", "material_y",
                               "suction")
SQRT2, SQRT3 = math.sqrt(2.0), math.sqrt(3.0)
PATH_STEP = 0.03  # m between IK waypoints on Cartesian lines (joint-interpolated in between)
LIFT_STEP = 0.06  # m between IK waypoints on the vertical lift


def suction_ring_ratios(force: np.ndarray, torque: np.ndarray, mu: float, r: float, k: float,
                        vacuum: float) -> np.ndarray:
    """Load / capacity of each Dex-Net 3.0 suction-ring condition, in ``CONDITIONS`` order (>1 fails).

    ``force``/``torque`` are what the cup exerts on the parcel in the cup frame (z along the approach,
    into the parcel); ``f_N = f_z + V`` is the ring's normal force including the vacuum pull.
    """
    fx, fy, fz = (float(v) for v in force)
    tx, ty, tz = (float(v) for v in torque)
    f_n = fz + vacuum
    friction_cap = mu * f_n
    material_cap = math.pi * r * k

    def ratio(load: float, cap: float) -> float:
        if cap <= 0.0:
            return math.inf if load > 0.0 or cap < 0.0 else 0.0
        return load / cap

    return np.array([
        ratio(SQRT3 * abs(fx), friction_cap),
        ratio(SQRT3 * abs(fy), friction_cap),
        ratio(SQRT3 * abs(tz), r * friction_cap),
        ratio(SQRT2 * abs(tx), material_cap),
        ratio(SQRT2 * abs(ty), material_cap),
        ratio(max(-fz, 0.0), vacuum),  # f_z >= -V
    ])


@dataclass
class PickResult:
    outcome: str
    failure_cause: str | None = None
    object_id: int | None = None
    body_id: int | None = None
    contact_point: np.ndarray | None = None  # where the cup axis meets the true mesh
    contact_axis: np.ndarray | None = None  # actual cup approach axis at contact
    seal: float | None = None
    peak_ratios: dict[str, float] = field(default_factory=dict)  # load / capacity per condition
    failure_phase: str | None = None  # 'lift' or 'transport' for a dropped parcel
    sim_time: float = 0.0
    dynamic_steps: int = 0
    trace: list[dict[str, Any]] = field(default_factory=list)


class _HoldMonitor:
    """Reads the reaction wrench each step and breaks the seal after a sustained violation."""

    def __init__(self, cid: int, client: int, grasp: GraspConfig, suction: SuctionConfig) -> None:
        self.cid, self.client = cid, client
        self.mu, self.r, self.k = grasp.cup_friction, suction.cup_radius, suction.material_k
        self.vacuum = grasp.vacuum_force(suction.cup_radius)
        self.limit = grasp.violation_steps
        self.run = 0
        self.peak = np.zeros(len(CONDITIONS))
        self.cause: str | None = None
        self.phase = "lift"  # where the hold is: 'lift' or 'transport'
        self.failed_in: str | None = None

    def __call__(self) -> str | None:
        state = np.asarray(p.getConstraintState(self.cid, physicsClientId=self.client), dtype=np.float64)
        # pybullet reports the force on the child (parcel) in the parent (cup) frame; the torque's sign
        # is the opposite convention, which the |.| in every torque condition ignores.
        ratios = suction_ring_ratios(state[:3], state[3:6], self.mu, self.r, self.k, self.vacuum)
        self.peak = np.maximum(self.peak, np.nan_to_num(ratios, posinf=1e9))
        if np.any(ratios > 1.0):
            self.run += 1
            if self.run >= self.limit:
                # the vacuum losing first makes f_N <= 0 and so every friction ratio infinite: name
                # the root cause
                worst = np.nan_to_num(ratios, posinf=1e9)
                self.cause = "suction" if ratios[-1] > 1.0 else CONDITIONS[int(np.argmax(worst))]
                self.failed_in = self.phase
                return self.cause
        else:
            self.run = 0
        return None


class PickExecutor:
    """Runs pick attempts with one arm in one simulator."""

    def __init__(self, sim: Simulator, arm: Gen3Arm, grasp: GraspConfig, suction: SuctionConfig) -> None:
        self.sim, self.arm, self.grasp, self.suction = sim, arm, grasp, suction
        self.ready_q = np.asarray(arm.config.home, dtype=np.float64)
        self._trace: list[dict[str, Any]] = []
        self._next_trace = 0.0
        self._held: int | None = None

    def set_ready_seed(self, q: np.ndarray) -> None:
        """A configuration above the bin centre: seeds IK for the hover point, and every free-space
        move between home and the bin passes through it (clear of the walls)."""
        self.ready_q = np.asarray(q, dtype=np.float64)

    # ------------------------------------------------------------------------------------ helpers
    def _record(self) -> None:
        t = self.arm.sim_time
        if t + 1e-9 < self._next_trace:
            return
        self._next_trace = t + self.grasp.trace_interval
        entry: dict[str, Any] = {"t": t, "q": self.arm.q.copy(), "tip": self.arm.kin.forward(self.arm.q)[0]}
        if self._held is not None:
            entry["held"] = self._held
            entry["held_pose"] = self.sim.body_pose(self._held)
        self._trace.append(entry)

    def _line(self, start: np.ndarray, end: np.ndarray, step: float = PATH_STEP) -> np.ndarray:
        n = max(1, math.ceil(np.linalg.norm(end - start) / step))
        return start + (end - start) * (np.arange(1, n + 1)[:, None] / n)

    def _step(self) -> None:
        self.sim.step(1)
        self._record()

    def _drive(self, waypoints, duration: float, dt: float | None = None, **kwargs):
        dt = self.sim.config.timestep if dt is None else dt
        res = self.arm.drive(waypoints, self._step, dt, min_duration=duration, **kwargs)
        self._dynamic_steps += res.steps
        return res

    def _retreat(self, *waypoints: np.ndarray) -> None:
        """Back out through the planned free-space points to home (not collision-checked)."""
        path = [q for q in waypoints if q is not None] + [self.ready_q, np.asarray(self.arm.config.home, dtype=np.float64)]
        self.arm.sweep(path, self.grasp.control_dt_free, check=False, on_step=self._record)

    def _result(self, outcome: str, **kwargs) -> PickResult:
        return PickResult(outcome, sim_time=self.arm.sim_time - self._t0, dynamic_steps=self._dynamic_steps,
                          trace=self._trace, **kwargs)

    # ------------------------------------------------------------------------------------ attempt
    def attempt(self, scene: Scene, point: np.ndarray, normal: np.ndarray) -> PickResult:
        """One attempt at suction point ``point`` with outward unit ``normal`` (both world frame)."""
        g, arm = self.grasp, self.arm
        self._trace, self._next_trace, self._held = [], arm.sim_time, None
        self._t0, self._dynamic_steps = arm.sim_time, 0
        self._record()
        point = np.asarray(point, dtype=np.float64)
        normal = np.asarray(normal, dtype=np.float64)
        normal = normal / np.linalg.norm(normal)
        axis = -normal
        rim = scene.bin.floor_z + scene.bin.wall_height
        parcels = {ps.body_id: ps for ps in scene.parcels}

        # -- plan everything before moving
        pre = point + g.pregrasp_distance * normal
        hover = pre.copy()
        hover[2] = max(pre[2], rim + g.hover_clearance)
        end = point - g.overshoot * normal
        q_hover = arm.ik(hover, axis, seed=self.ready_q)
        if q_hover is None:
            return self._result("unreachable", failure_cause="hover")
        q_down = arm.cartesian_path(q_hover, self._line(hover, pre), axis) if hover[2] > pre[2] + 1e-6 else [q_hover]
        if q_down is None:
            return self._result("unreachable", failure_cause="pregrasp")
        q_pre = q_down[-1]
        q_approach = arm.cartesian_path(q_pre, self._line(pre, end), axis)
        if q_approach is None:
            return self._result("unreachable", failure_cause="approach")

        # -- free space: home -> ready (above the bin) -> hover -> pre-grasp; a hover above the ready
        # height (a pile topping the rim) is approached directly
        via = [] if hover[2] > arm.kin.forward(self.ready_q)[0][2] - 0.05 else [self.ready_q]
        for path in (via + [q_hover], q_down):
            res = arm.sweep(path, g.control_dt_free, on_step=self._record)
            if not res.completed:
                self._retreat(q_hover)
                return self._result("collision", failure_cause=f"free-space: {arm.link_names.get(res.collision.link, 'base')}")

        # -- guarded approach along -n
        def cup_contact(contacts: list[Contact]) -> Contact | None:
            return next((c for c in contacts if c.link == arm.cup_link), None)

        length = g.pregrasp_distance + g.overshoot
        res = self._drive(q_approach, math.pi / 2 * length / g.approach_speed, stop=cup_contact,
                          allowed_links={arm.cup_link, arm.tip_link})
        if res.collision is not None:
            self._retreat(q_pre, q_hover)
            return self._result("collision", failure_cause=f"approach: {arm.link_names.get(res.collision.link, 'base')}")
        if res.completed:
            self._retreat(q_pre, q_hover)
            return self._result("no_contact")
        contact: Contact = res.stopped_by
        parcel = parcels.get(contact.body)
        if parcel is None:
            self._retreat(q_pre, q_hover)
            return self._result("collision", failure_cause="cup hit the bin")

        # -- the cup rests on the surface while the vacuum builds, then the seal is judged there
        dwell = max(1, round(g.seal_dwell / self.sim.config.timestep))
        arm.hold(dwell, self._step, self.sim.config.timestep)
        self._dynamic_steps += dwell
        tip, _ = arm.tip_pose()
        cup_axis = arm.tip_axis()
        seal, hit = self._seal_at(parcel, tip, cup_axis)
        info = dict(object_id=parcel.object_id, body_id=parcel.body_id, contact_point=hit,
                    contact_axis=cup_axis, seal=seal)
        if seal < g.seal_threshold:
            self._retreat(q_pre, q_hover)
            return self._result("no_seal", **info)

        # -- attach, lift, carry
        cid = self._attach(parcel.body_id)
        monitor = _HoldMonitor(cid, self.sim.client, g, self.suction)
        # a coarser step and fewer solver iterations while carrying (documented speed trade-off)
        with self.sim.physics_overrides(timestep=g.carry_dt, solver_iterations=g.carry_solver_iterations):
            outcome = self._carry(parcel, cup_axis, rim, monitor)
        info["peak_ratios"] = dict(zip(CONDITIONS, map(float, monitor.peak)))
        self._release(cid, parcel.body_id)
        if outcome == "success":
            self.sim.remove(parcel.body_id)
            self._retreat()
            return self._result("success", **info)
        self._retreat()
        if outcome == "dropped":
            return self._result("dropped", failure_cause=monitor.cause, failure_phase=monitor.failed_in, **info)
        return self._result(outcome[0], failure_cause=outcome[1], **info)

    def _seal_at(self, parcel: ParcelState, tip: np.ndarray, axis: np.ndarray) -> tuple[float, np.ndarray | None]:
        """Seal where the cup axis meets the parcel's true mesh (0 when the axis misses it)."""
        pos, orn = self.sim.body_pose(parcel.body_id)
        parcel.position, parcel.orientation = pos, orn
        mesh: trimesh.Trimesh = parcel.world_mesh()
        origin = tip - 0.05 * axis
        locations, _, _ = mesh.ray.intersects_location(origin[None], axis[None], multiple_hits=False)
        if len(locations) == 0:
            return 0.0, None
        hit = locations[np.argmin(np.linalg.norm(locations - origin, axis=1))]
        scorer = SuctionScorer([mesh], parcel.world_com()[None], config=self.suction)
        seal = float(scorer.seal(hit[None], (-axis)[None], np.zeros(1, dtype=np.int64))[0])
        return seal, hit

    def _attach(self, body: int) -> int:
        """Fixed constraint from the cup lip to the parcel at their current relative pose."""
        c = self.sim.client
        tip, orn = self.arm.tip_pose()
        bpos, born = p.getBasePositionAndOrientation(body, physicsClientId=c)  # COM frame
        inv_p, inv_o = p.invertTransform(bpos, born)
        child_p, child_o = p.multiplyTransforms(inv_p, inv_o, tip.tolist(), orn.tolist())
        for link in range(-1, p.getNumJoints(self.arm.body, physicsClientId=c)):
            p.setCollisionFilterPair(self.arm.body, body, link, -1, 0, physicsClientId=c)
        cid = p.createConstraint(self.arm.body, self.arm.tip_link, body, -1, p.JOINT_FIXED, [0, 0, 0],
                                 [0, 0, 0], child_p, childFrameOrientation=child_o, physicsClientId=c)
        p.changeConstraint(cid, maxForce=1e5, physicsClientId=c)
        self._held = body
        return cid

    def _release(self, cid: int, body: int) -> None:
        c = self.sim.client
        p.removeConstraint(cid, physicsClientId=c)
        for link in range(-1, p.getNumJoints(self.arm.body, physicsClientId=c)):
            p.setCollisionFilterPair(self.arm.body, body, link, -1, 1, physicsClientId=c)
        self._held = None

    def _carry(self, parcel: ParcelState, axis: np.ndarray, rim: float, monitor: _HoldMonitor):
        """Lift clear of the rim, then carry to the drop zone; 'success', 'dropped' or (outcome, cause)."""
        g, arm = self.grasp, self.arm
        tip, _ = arm.tip_pose()
        lowest = self.sim.aabb(parcel.body_id)[0][2]
        lift = max(rim + g.clearance - lowest, 0.05)
        top = tip + np.array([0.0, 0.0, lift])
        q_lift = arm.cartesian_path(arm.q, self._line(tip, top, LIFT_STEP), axis)
        drop = np.array(g.drop_zone, dtype=np.float64)
        drop[2] = max(drop[2], top[2])
        q_drop = None
        if q_lift is not None:
            # keep the cup's yaw: turning a held parcel about the cup axis loads the ring in torsion
            q_drop = arm.ik(drop, axis, seed=q_lift[-1], x_axis=arm.kin.tip_x(q_lift[-1]))
            if q_drop is None:
                q_drop = arm.ik(drop, axis, seed=q_lift[-1])
            if q_drop is None:
                q_drop = arm.ik(drop, np.array([0.0, 0.0, -1.0]), seed=q_lift[-1])
        if q_lift is None or q_drop is None:
            return ("unreachable", "lift" if q_lift is None else "drop zone")
        res = self._drive(q_lift, math.pi / 2 * lift / g.lift_speed, dt=g.carry_dt, on_step=monitor)
        if res.stopped_by:
            return "dropped"
        if res.collision is not None:
            return ("collision", f"lift: {arm.link_names.get(res.collision.link, 'base')}")
        monitor.phase = "transport"
        res = self._drive([q_drop], 0.0, dt=g.carry_dt, on_step=monitor)
        if res.stopped_by:
            return "dropped"
        if res.collision is not None:
            return ("collision", f"transport: {arm.link_names.get(res.collision.link, 'base')}")
        return "success"
