"""The ``physical`` suction quality: would this pick hold in this project's cell, hanging still?

The paper's and SuctionNet's scores assume a 10 mm cup, a unit mass and a thin probe for the tool. The cell
has one 40 mm bellows cup on a 60 kPa ejector (``suction/cup.py``), parcels of real mass, and an arm whose
flange and wrist must clear the pile. This module predicts what the env will find, quasi-statically, from the
true scene (docs/labels.md, "The physical definition"):

1. **Seat.** The cup comes down along ``-n`` and rests on the parcel's convex hull, which is what pybullet
   collides (``hull_seats``): the lip stops where the first point of the cup's face (``lip_face``, its rim and
   disk) meets a hull, as the env's rigid cup does. If another parcel's hull is met first, the cup lands there:
   no seal.
2. **Seal.** The bellows contact seal (``cup_seal.bellows_seal``) of the lip at that seat on the TRUE mesh, so a
   wrinkled mailer's valley under its hull is a real gap, as in the env.
3. **Holding.** The parcel hanging still under the cup: the cup pulls ``m g`` straight up about the lip, with
   the real mass at the real COM. The ring conditions of Dex-Net 3.0 (``cup.suction_ring_ratios``, the env's own
   function) at the leak-reduced rated pull of that seal, with every lateral load on one ring axis (the worst
   yaw). The pick holds where every ratio is below 1; ``1 - worst ratio`` is its margin.
4. **Tool.** The scorer's collision probe (``collision.collision_scores``) sized to the physical tool and the
   motion planner's clearance (``physical_tool``), against the parcels' hulls, the bin and the floor.

The carry is timed by the env so that no ring load exceeds ``CARRY_LOAD_TARGET`` of its capacity, so the
hanging-still margin is what decides a hold, except where a neighbour drags on the lift (not modelled here).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from parcelpick_env.robot.gen3 import LINKS, SuctionToolSpec
from parcelpick_env.robot.gen3 import RADII as GEN3_RADII
from parcelpick_env.robot.planning import PlannerConfig
from parcelpick_env.sim.config import SimConfig
from parcelpick_env.suction.config import SuctionConfig
from parcelpick_env.suction.cup import CupSpec, suction_ring_ratios
from parcelpick_env.suction.geometry import frame_rays, tangent_frames
from parcelpick_env.suction.seal import seal_ray_pattern

SEAT_ABOVE = 0.05  # m: the cup's descent onto the hull is traced from this far out along n
WRIST_LENGTH = 0.15  # m of the arm's wrist above the tool flange that must clear the scene too
WRIST_LINKS = ("spherical_wrist_2_link", "bracelet_link")  # the links on the tool axis in a top-down pose


@dataclass
class PhysicalGrasp:
    """What the cell will find at each candidate (module docstring), one row per candidate."""

    seal: np.ndarray  # (N,) bellows contact seal where the cup comes to rest on the parcel's hull
    ratios: np.ndarray  # (N, 6) Dex-Net ring ratios hanging still at that seal's pull (cup.CONDITIONS order)
    collision: np.ndarray  # (N,) 1 if the physical tool along n clears every hull, the bin and the floor
    seats: np.ndarray  # (N, 3) where the lip comes to rest (``hull_seats``; the candidate point if not on its parcel)

    @property
    def worst(self) -> np.ndarray:
        """(N,) the largest ring ratio: above 1 the parcel falls."""
        return self.ratios.max(axis=1) if len(self.ratios) else np.zeros(0)

    def channels(self, seal_threshold: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The ``physical`` label channels (seal, wrench, collision), each (N,) float32 in [0, 1]:

        - seal: the contact seal, 0 below ``seal_threshold`` (the env holds nothing there);
        - wrench: the holding margin ``1 - worst ratio``, 0 where the parcel falls;
        - collision: the physical tool's clearance.

        Their product is 0 exactly where the env is predicted to fail the pick.
        """
        seal = np.where(self.seal >= seal_threshold, self.seal, 0.0)
        margin = np.clip(1.0 - np.nan_to_num(self.worst, nan=np.inf, posinf=np.inf), 0.0, 1.0)
        return seal.astype(np.float32), margin.astype(np.float32), np.asarray(self.collision, dtype=np.float32)

    @classmethod
    def concatenate(cls, parts: list["PhysicalGrasp"]) -> "PhysicalGrasp":
        return cls(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in dataclasses.fields(cls)))


def lip_face(config: SuctionConfig) -> np.ndarray:
    """(K, 2) points of the cup's face in the lip plane, about the lip centre: the bellows seal's rim and disk
    rays (``seal.seal_ray_pattern``). A rigid cup coming down along its axis first touches at one of them."""
    return seal_ray_pattern(dataclasses.replace(config, seal_model="bellows"))[:, :2]


def hull_seats(hulls: o3d.t.geometry.RaycastingScene, points: np.ndarray, normals: np.ndarray,
               owner: np.ndarray, face: np.ndarray, num_threads: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Where the lip comes to rest coming down along ``-n`` onto the parcels' convex hulls (geometry ``k`` of
    ``hulls`` is parcel ``k``'s hull), and whether that is the candidate's own parcel.

    The cup's face (``face``, ``lip_face``) stops at its first touch: on a hull tilted to the cup that is the
    uphill rim, short of where the axis meets the hull (a mailer's wrinkle tilted 17 deg to the cup: 7 mm short;
    seating the lip on the axis there pressed it 6 mm into the hull and predicted a seal of 0.31 that the cell,
    whose cup stops at the rim, found at 0.006)."""
    coefficients = np.zeros((len(face), 6))
    coefficients[:, :2], coefficients[:, 2], coefficients[:, 5] = face, SEAT_ABOVE, -1.0
    hits = hulls.cast_rays(frame_rays(points, normals, *tangent_frames(normals), coefficients), nthreads=num_threads)
    t = hits["t_hit"].numpy().astype(np.float64).reshape(len(points), len(face))
    ids = hits["geometry_ids"].numpy().astype(np.int64).reshape(len(points), len(face))
    first = np.argmin(t, axis=1)
    rows = np.arange(len(points))
    t_first = t[rows, first]
    own = (ids[rows, first] == owner) & np.isfinite(t_first)
    tips = np.where(own[:, None], points + (SEAT_ABOVE - np.where(own, t_first, 0.0))[:, None] * normals, points)
    return tips, own


def hanging_ratios(tips: np.ndarray, axes: np.ndarray, coms: np.ndarray, masses: np.ndarray, seal: np.ndarray,
                   suction: SuctionConfig, cup: CupSpec) -> np.ndarray:
    """(N, 6) ring ratios of each parcel hanging still from a cup at ``tips`` along unit ``axes`` (into the
    parcel): the cup pulls ``m g`` straight up, about the lip, at the rated pull of contact seal ``seal``."""
    force = np.outer(masses * suction.gravity, [0.0, 0.0, 1.0])
    torque = np.cross(coms - tips, force)
    f_z, t_z = np.sum(force * axes, axis=1), np.sum(torque * axes, axis=1)
    lateral = np.linalg.norm(force - f_z[:, None] * axes, axis=1)
    bending = np.linalg.norm(torque - t_z[:, None] * axes, axis=1)
    zero = np.zeros(len(tips))
    ratios = suction_ring_ratios(np.stack([lateral, zero, f_z], axis=1), np.stack([bending, zero, t_z], axis=1),
                                 cup.friction, suction.cup_radius, suction.material_k,
                                 cup.rated_force(suction.cup_radius, seal))
    return np.asarray(ratios).reshape(len(tips), -1)


# m of true geometry the planner keeps: it measures between shapes that pybullet inflates by their collision margin
# (the cup's and the parcel's), so its 10 mm are 12 mm between the true surfaces (measured: a cup 10.5 mm from a
# parcel's hull is reported 8.6 mm away, and a pick the probe cleared at 10 mm was blocked in its descent)
PLANNER_CLEARANCE = PlannerConfig().margin + 2 * SimConfig().collision_margin


def physical_tool(suction: SuctionConfig, tool: SuctionToolSpec = SuctionToolSpec(),
                  margin: float = PLANNER_CLEARANCE) -> SuctionConfig:
    """The env's cup config with the collision probe widened to the physical tool plus the clearance the
    motion planner keeps: as wide as the cup's lip from the lip to the flange, then the widest of the
    flange and the wrist links above it (the URDF's own figures; the labels' 10 mm probe is narrower than
    the env's cup and ignores the flange and the wrist)."""
    flange = tool.cup_length + tool.rod_length  # lip to flange, along the tool axis
    wrist = max(tool.flange_radius, *(GEN3_RADII[LINKS.index(name)] for name in WRIST_LINKS))
    return dataclasses.replace(suction, tool_radius=max(suction.tool_radius, suction.cup_radius) + margin,
                               tool_far=max(suction.tool_far, flange),
                               body_radius=max(suction.body_radius, wrist) + margin,
                               body_near=flange, body_far=flange + WRIST_LENGTH)
