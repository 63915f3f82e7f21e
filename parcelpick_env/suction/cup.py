"""The physical cup: a 40 mm bellows cup on a vacuum ejector, and whether it holds a parcel.

The cup (docs/cell.md, 'Cup and vacuum'): one 1.5-fold bellows cup of 40 mm lip diameter (r = 20 mm,
``parcelpick_env.suction.config.CELL_CUP_RADIUS``), the common single-cup choice for cartons and
polybags, on an ejector giving a working vacuum of about 60 kPa below ambient.

Vacuum force (the law): the theoretical holding force is ``F = dP * A`` with ``A = pi r^2``. A lip
that conforms badly leaks; the ejector and the leak then act as two conductances in series, so the
cup settles at ``dP(s) = dP0 / (1 + beta (1 - s))`` where ``s`` in [0, 1] is the contact seal quality
(1: the lip conforms everywhere) and ``beta`` the ratio of a fully open lip's conductance to the
ejector's. Vendors divide ``F`` by a safety factor ``S`` (1.5 to 2) for the load they rate; the
ring conditions below use that rated force ``V = dP(s) * A / S``.

Wrench at the cup (Newton-Euler of the held parcel, never the attachment constraint's impulses):
the cup must supply whatever makes the parcel follow the tool, less what other bodies push:

    F = m (a_c - g) - sum F_i
    tau_tip = I_w alpha + omega x (I_w omega) + (c - tip) x m (a_c - g) - sum (p_i - tip) x F_i

with ``a_c = a + alpha x d + omega x (omega x d)`` the COM acceleration of a parcel rigidly held at
``d = c - tip`` and ``(p_i, F_i)`` the real contact forces on it. Both are expressed in the cup frame
(z along the approach, into the parcel) and checked against Dex-Net 3.0's suction-ring conditions.
"""

from __future__ import annotations

import dataclasses
import math
import weakref
from dataclasses import dataclass, field

import numpy as np
import pybullet as p
import trimesh

from parcelpick_env.config_checks import require, require_positive_numbers
from parcelpick_env.robot.kinematics import cross_rows

CONDITIONS: tuple[str, ...] = ("friction_x", "friction_y", "friction_torsion", "material_x", "material_y",
                               "suction")
SQRT2, SQRT3 = math.sqrt(2.0), math.sqrt(3.0)
# A support contact whose normal has any upward component bears part of the body's weight (a tube in the
# groove between two others rests on both flanks, at 40-60 deg from vertical: a 45 deg cut split such a
# support into one bearing flank and one "load" flank, and the uncancelled flank read as a shear on the cup).
BEARING_COS = 0.0
# Carrying is timed so that no ring load exceeds this share of its capacity (GraspConfig.carry_load_target);
# the heaviest parcel the cell admits hangs at this share of the rated pull (assets/generator.MAX_MASS).
CARRY_LOAD_TARGET = 0.45


@dataclass(frozen=True)
class CupSpec:
    """Vacuum and lip of the physical cup (its radius and material constant ``k`` come from the env's
    ``SuctionConfig``, shared with the seal check, so they are defined once)."""

    vacuum_kpa: float = 60.0  # dP0: working vacuum of the ejector at a perfect seal
    safety_factor: float = 1.5  # vendors' S on F = dP * A (1.5 horizontal/slow, 2 and up for fast or vertical)
    leak_ratio: float = 3.0  # beta: open-lip conductance over the ejector's; dP(s) = dP0 / (1 + beta (1 - s))
    friction: float = 0.5  # mu of the lip on cardboard and film
    violation_time: float = 0.05  # s a ring condition violated in a row breaks the seal (3 steps of the 60 Hz carry)

    def __post_init__(self) -> None:
        require_positive_numbers(self, ("vacuum_kpa", "friction", "violation_time"))
        require(self.safety_factor >= 1.0, "CupSpec", f"safety_factor must be >= 1, got {self.safety_factor}")
        require(self.leak_ratio >= 0.0, "CupSpec", f"leak_ratio must be >= 0, got {self.leak_ratio}")

    def vacuum_pa(self, seal: float | np.ndarray) -> float | np.ndarray:
        """Cup vacuum (Pa below ambient) at contact seal quality ``seal`` (the leakage law above);
        a float for a float, an array for an array of seals."""
        s = np.clip(seal, 0.0, 1.0)
        out = self.vacuum_kpa * 1e3 / (1.0 + self.leak_ratio * (1.0 - s))
        return float(out) if np.ndim(out) == 0 else out

    def rated_force(self, radius: float, seal: float | np.ndarray = 1.0) -> float | np.ndarray:
        """V = dP(s) * pi r^2 / S, newtons: the pull the ring conditions may count on."""
        return self.vacuum_pa(seal) * math.pi * radius**2 / self.safety_factor


def suction_ring_ratios(force: np.ndarray, torque: np.ndarray, mu: float, r: float, k: float,
                        vacuum: float | np.ndarray) -> np.ndarray:
    """Load / capacity of each Dex-Net 3.0 suction-ring condition, in ``CONDITIONS`` order (>1 fails).

    ``force``/``torque`` are what the cup exerts on the parcel in the cup frame (z along the approach,
    into the parcel; torque about the lip centre); ``f_N = f_z + V`` is the ring's normal force
    including the vacuum pull. One wrench ((3,) each, scalar ``vacuum``) gives (6,); a batch ((N, 3),
    ``vacuum`` scalar or (N,)) gives (N, 6), so a planner can rank many candidate grasps at once.
    """
    force, torque = np.asarray(force, dtype=np.float64), np.asarray(torque, dtype=np.float64)
    vacuum = np.asarray(vacuum, dtype=np.float64)
    if force.shape == (3,) and torque.shape == (3,) and vacuum.ndim == 0:
        return _ring_ratios_one(force, torque, mu, r, k, float(vacuum))
    fx, fy, fz = force[..., 0], force[..., 1], force[..., 2]
    tx, ty, tz = torque[..., 0], torque[..., 1], torque[..., 2]
    friction_cap = mu * (fz + vacuum)
    material_cap = math.pi * r * k
    # all six at once (one division, not six small ones: this runs at every step of a carry)
    loads = np.stack([SQRT3 * np.abs(fx), SQRT3 * np.abs(fy), SQRT3 * np.abs(tz),
                      SQRT2 * np.abs(tx), SQRT2 * np.abs(ty), np.maximum(-fz, 0.0)], axis=-1)  # f_z >= -V
    caps = np.stack(np.broadcast_arrays(friction_cap, friction_cap, r * friction_cap, material_cap, material_cap,
                                        vacuum), axis=-1)
    has_cap = caps > 0.0
    out = loads / np.where(has_cap, caps, 1.0)
    # no capacity: infinite if loaded (or the ring is pulled off), else nothing to carry
    return np.where(has_cap, out, np.where((loads > 0.0) | (caps < 0.0), np.inf, 0.0))


def _ring_ratios_one(force: np.ndarray, torque: np.ndarray, mu: float, r: float, k: float, vacuum: float
                     ) -> np.ndarray:
    """``suction_ring_ratios`` of one wrench, the hold check's case at every carry step: the same operations on
    Python floats (IEEE doubles, so the same bits) without the batch's stacking and broadcasting."""
    fx, fy, fz = force.tolist()
    tx, ty, tz = torque.tolist()
    friction_cap = mu * (fz + vacuum)
    material_cap = math.pi * r * k
    loads = (SQRT3 * abs(fx), SQRT3 * abs(fy), SQRT3 * abs(tz), SQRT2 * abs(tx), SQRT2 * abs(ty),
             -fz if -fz > 0.0 or math.isnan(fz) else 0.0)  # np.maximum(-fz, 0): NaN kept, never -0.0
    caps = (friction_cap, friction_cap, r * friction_cap, material_cap, material_cap, vacuum)
    return np.array([load / cap if cap > 0.0 else (math.inf if load > 0.0 or cap < 0.0 else 0.0)
                     for load, cap in zip(loads, caps)])


# ----------------------------------------------------------------------------------- the held body
_INERTIA_CACHE: "weakref.WeakKeyDictionary[trimesh.Trimesh, np.ndarray]" = weakref.WeakKeyDictionary()


def mesh_inertia(mesh: trimesh.Trimesh, mass: float) -> np.ndarray:
    """(3, 3) inertia about the centroid, body frame, of ``mesh`` as a uniform solid of ``mass`` kg.

    trimesh integrates the closed surface (unit density); an open mesh (a wrinkled mailer) uses its
    convex hull, which bounds the same solid.
    """
    if not mass > 0:
        raise ValueError(f"mass must be > 0, got {mass!r}")
    unit = _INERTIA_CACHE.get(mesh)
    if unit is None:
        solid = mesh if mesh.is_watertight and mesh.volume > 0 else mesh.convex_hull
        unit = np.asarray(solid.moment_inertia, dtype=np.float64) / float(solid.mass)
        _INERTIA_CACHE[mesh] = unit
    return unit * float(mass)


@dataclass(frozen=True)
class Contacts:
    """Contact forces on one body, world frame, one row per contact point."""

    points: np.ndarray  # (k, 3)
    forces: np.ndarray  # (k, 3): normal plus friction, on the body
    bodies: np.ndarray  # (k,) the other body of each contact
    normals: np.ndarray  # (k, 3) unit contact normals, pointing into the body
    normal_force: np.ndarray  # (k,) newtons

    def without(self, keep: np.ndarray) -> "Contacts":
        return Contacts(self.points[keep], self.forces[keep], self.bodies[keep], self.normals[keep],
                        self.normal_force[keep])

    def from_bodies(self, bodies: set[int]) -> np.ndarray:
        """Mask of contacts with any of ``bodies`` (a comprehension, not np.isin: a handful of contacts, at
        every carry step; 60 -> 25 us a ``cup_loads`` call, benchmarks/RESULTS.md)."""
        return np.array([b in bodies for b in self.bodies], dtype=bool)

    def bearing(self, bodies: set[int], min_up: float = BEARING_COS) -> np.ndarray:
        """Mask of contacts from ``bodies`` that push the body up (normal with an upward component,
        ``BEARING_COS``): the surfaces it is resting on."""
        return self.from_bodies(bodies) & (self.normals[:, 2] > min_up)


def contact_forces(client: int, body: int, ignore: frozenset[int] | set[int] = frozenset()) -> Contacts:
    """Real contact forces on ``body`` from every other body but ``ignore`` (world frame).

    pybullet orients the contact normal for the queried body, but reports the two friction
    components as the force on the lower-id body of the pair whichever is queried (checked in
    tests/test_holding.py on an incline, both creation orders); the sign is fixed here.
    """
    rows = [c for c in p.getContactPoints(bodyA=body, physicsClientId=client) if c[2] not in ignore]
    if not rows:
        z = np.zeros((0, 3))
        return Contacts(z, z, np.zeros(0, dtype=np.int64), z, np.zeros(0))
    other = np.array([c[2] for c in rows], dtype=np.int64)
    points = np.array([c[5] for c in rows], dtype=np.float64)
    normals = np.array([c[7] for c in rows], dtype=np.float64)
    fn = np.array([c[9] for c in rows], dtype=np.float64)
    friction = (np.array([c[10] for c in rows])[:, None] * np.array([c[11] for c in rows], dtype=np.float64)
                + np.array([c[12] for c in rows])[:, None] * np.array([c[13] for c in rows], dtype=np.float64))
    sign = np.where(body < other, 1.0, -1.0)[:, None]
    return Contacts(points, normals * fn[:, None] + sign * friction, other, normals, fn)


@dataclass(frozen=True)
class ToolState:
    """Kinematics of the cup lip at one instant, world frame: position, rotation (columns: cup x, y,
    z = approach axis), linear and angular velocity and acceleration."""

    tip: np.ndarray
    R: np.ndarray
    v: np.ndarray = field(default_factory=lambda: np.zeros(3))
    omega: np.ndarray = field(default_factory=lambda: np.zeros(3))
    a: np.ndarray = field(default_factory=lambda: np.zeros(3))
    alpha: np.ndarray = field(default_factory=lambda: np.zeros(3))


def cup_wrench(mass: float, com: np.ndarray, inertia_world: np.ndarray, tool: ToolState, gravity: float,
               contact_points: np.ndarray | None = None, contact_forces_w: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """(force, torque) the cup exerts on a rigidly held parcel, cup frame, torque about the lip centre.

    Newton-Euler along the tool's motion (module docstring), with the real contact forces on the
    parcel subtracted; ``com`` and ``inertia_world`` are the parcel's COM and inertia in the world.
    """
    d = np.asarray(com, dtype=np.float64) - tool.tip
    a_com = tool.a + cross_rows(tool.alpha, d) + cross_rows(tool.omega, cross_rows(tool.omega, d))
    inertial = mass * (a_com - np.array([0.0, 0.0, -gravity]))
    force = inertial.copy()
    torque = inertia_world @ tool.alpha + cross_rows(tool.omega, inertia_world @ tool.omega) + cross_rows(d, inertial)
    if contact_forces_w is not None and len(contact_forces_w):
        force -= contact_forces_w.sum(axis=0)
        torque -= cross_rows(contact_points - tool.tip, contact_forces_w).sum(axis=0)
    return tool.R.T @ force, tool.R.T @ torque


class HoldMonitor:
    """Checks the ring conditions each step of a hold and breaks the seal after a sustained violation.

    ``update(tool, com, R_body, contacts)`` returns the failed condition's name once a violation has
    lasted ``CupSpec.violation_time`` (the steps' ``dt`` summed), else None; ``peak`` keeps the largest ratio of each
    condition and ``trace`` every step's (force, torque, ratios).
    """

    def __init__(self, cup: CupSpec, radius: float, material_k: float, gravity: float, mass: float,
                 inertia_body: np.ndarray, seal: float) -> None:
        self.cup, self.r, self.k, self.g = cup, radius, material_k, gravity
        self.mass, self.inertia_body = float(mass), np.asarray(inertia_body, dtype=np.float64)
        self.vacuum = cup.rated_force(radius, seal)
        self.run = 0.0  # s the current violation has lasted
        self.peak = np.zeros(len(CONDITIONS))
        self.trace: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.cause: str | None = None

    def ratios(self, tool: ToolState, com: np.ndarray, R_body: np.ndarray,
               contact_points: np.ndarray | None = None, contact_forces_w: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        inertia_world = R_body @ self.inertia_body @ R_body.T
        force, torque = cup_wrench(self.mass, com, inertia_world, tool, self.g, contact_points, contact_forces_w)
        return force, torque, suction_ring_ratios(force, torque, self.cup.friction, self.r, self.k, self.vacuum)

    def update(self, tool: ToolState, com: np.ndarray, R_body: np.ndarray,
               contact_points: np.ndarray | None = None, contact_forces_w: np.ndarray | None = None, *,
               dt: float) -> str | None:
        force, torque, ratios = self.ratios(tool, com, R_body, contact_points, contact_forces_w)
        self.trace.append((force, torque, ratios))
        finite = np.nan_to_num(ratios, posinf=1e9)
        self.peak = np.maximum(self.peak, finite)
        if not np.any(ratios > 1.0):
            self.run = 0.0
            return None
        self.run += dt
        if self.run < self.cup.violation_time - 1e-9:  # 3 steps of 1/60 s sum to 0.05 s within rounding
            return None
        # the vacuum losing first makes f_N <= 0 and so every friction ratio infinite: name the root cause
        self.cause = "suction" if ratios[-1] > 1.0 else CONDITIONS[int(np.argmax(finite))]
        return self.cause

    def allowed_acceleration(self, tool: ToolState, com: np.ndarray, R_body: np.ndarray, target: float,
                             floor: float) -> float:
        """The tool acceleration (m/s^2, any world axis, either sign) at which the first ring condition
        reaches ``target`` from the load at ``tool``, linearised by a 1 m/s^2 probe per direction; at
        least ``floor`` so that a parcel already loaded past ``target`` is still moved (and judged)."""
        _, _, r0 = self.ratios(tool, com, R_body)
        r0 = np.nan_to_num(r0, posinf=1e9)
        best = math.inf
        for d in np.vstack([np.eye(3), -np.eye(3)]):
            _, _, r1 = self.ratios(dataclasses.replace(tool, a=tool.a + d), com, R_body)
            slope = np.nan_to_num(r1, posinf=1e9) - r0
            rising = slope > 1e-9
            if np.any(rising):
                best = min(best, float(np.min((target - r0[rising]) / slope[rising])))
        return max(best, floor)

    @property
    def peak_ratios(self) -> dict[str, float]:
        return dict(zip(CONDITIONS, map(float, self.peak)))
