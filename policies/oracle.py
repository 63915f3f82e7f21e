"""The oracle: the privileged upper bound of every clearance table, and the only reader of ground truth.

It is NOT a deployable policy. It reads the env's privileged ``obs_mode="state_dict"`` observation
(true poses, asset ids, masses, centres of mass; ``parcelpick_env/envs/observation.py``) and the env's
physical cup from ``info['suction']``; the policy registry refuses that channel to any other policy.
What a perfect perception stack would pick, so the gap between it and a learned policy is the policy's,
and what it fails is the cell's (physics, motion), not perception's.

How it picks, per parcel, on the true meshes:

1. Probe rays straight down on rings around the vertical through the parcel's centre of mass, cast on
   the whole scene (every parcel's true mesh and the bin): a probe counts only where the first surface
   it hits is this parcel, i.e. its top face is uncovered there. The hit is the candidate point and the
   hit triangle's normal, facing the probe, its outward normal. A parcel with no admissible top candidate
   (one standing on end, or leaning on a wall) is probed again along ``side_tilts_deg`` from vertical at
   ``side_azimuths`` headings, aimed at its COM: the uncovered side faces and ends.
2. Predict the cell's own verdict for every candidate (``predicted_grasp``), as physics will reach it:
   the cup comes down along ``-n`` and rests on the parcel's convex hull (what pybullet collides), so the
   bellows ``contact_seal`` is judged at that seat on the true mesh (a wrinkled mailer's valley under its
   hull is a real gap); a seat on another parcel's hull means the cup lands there instead (rejected).
   The cup's leak-reduced pull at that seal (``CupSpec.rated_force``) then gives the Dex-Net ring ratios
   of the parcel hanging still (``suction_ring_ratios``, the env's own function, with the real mass at
   the real COM and every lateral load put on one ring axis: the worst yaw). The scorer's
   tool-collision probe (``collision_scores``) is sized to the physical tool and the planner's clearance
   (``physical_tool``) and run against the parcels' convex hulls. Visibility is 1.
3. Keep the admissible ones (tool free, seal at least ``seal_floor``, the env's threshold, every ring
   ratio below 1 at rest). Sound picks (seal at least ``min_seal`` and every ratio within the carry's
   load target) come before weaker ones, and level faces (normal within ``max_tilt_deg`` of vertical)
   before tilted ones: the cell picks top-down, and a tilted approach loads the lip in shear and sends
   the arm to awkward poses. Then rank the parcels highest first (tops within ``height_band`` tie, and
   then the one nearest the bin centre comes first: the mount reaches the middle most easily); within a
   parcel, the smallest lever arm (horizontal distance to the COM) first. Above all these, parcels not
   yet tried come first (a parcel whose pick failed, ``info['outcome']``, goes behind the untried ones
   for the rest of the episode), then free parcels before pinned ones (another parcel lies on them,
   ``pinned_parcels``), then parcels no neighbour touches over their upper half (``leaned_on``), then
   robust seals before ones within ``seal_margin`` of the threshold.
4. Reachability (``ArmReach``): the arm's own numpy IK, chained from the pre-grasp point through the
   contact up to the carrying height; the first ranked candidate it reaches is proposed, the unreachable
   ones checked go to the back (never out).

``scores`` in the returned ``Candidates`` encode that rank (1 for the first, falling linearly); the
physical scores of the returned candidates are kept in ``last_scores`` and their parcels in
``last_object_ids``. ``predict`` reads only ``obs`` and ``info``, never the env object.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np
import open3d as o3d
import trimesh
from scipy.spatial.transform import Rotation

from parcelpick_env.assets.library import AssetLibrary
from parcelpick_env.envs.config import EnvConfig
from parcelpick_env.envs.observation import asset_from_index, bin_from_vector
from parcelpick_env.robot.arm import ArmConfig
from parcelpick_env.robot.gen3 import JOINTS, LINKS, SuctionToolSpec
from parcelpick_env.robot.kinematics import Gen3Kinematics
from parcelpick_env.robot.gen3 import RADII as GEN3_RADII
from parcelpick_env.robot.planning import PlannerConfig
from parcelpick_env.suction.collision import collision_scores
from parcelpick_env.suction.config import SuctionConfig
from parcelpick_env.suction.cup import CupSpec, suction_ring_ratios
from parcelpick_env.suction.geometry import O3D_INVALID_ID, build_scene, ring_pattern, tangent_frames
from parcelpick_env.suction.scorer import SuctionScorer, SuctionScores
from parcelpick_env.suction.wrench import wrench_scores
from policies.base import Candidates, Policy

STATE_KEYS: tuple[str, ...] = ("parcel_mask", "parcel_position", "parcel_quaternion", "parcel_com",
                               "parcel_mass", "parcel_asset_index", "parcel_extents", "bin")
PROBE_ABOVE = 0.10  # m: probe rays start this far above the highest parcel
WRIST_LENGTH = 0.15  # m of the arm's wrist above the tool flange that must clear the scene too
WRIST_LINKS = ("spherical_wrist_2_link", "bracelet_link")  # the links on the tool axis in a top-down pose
SEAT_ABOVE = 0.05  # m: the cup's descent onto the hull is traced from this far out along n


@dataclass(frozen=True)
class OracleConfig:
    """Where the oracle looks and what it calls a sound pick."""

    probe_radii: tuple[float, ...] = (0.0, 0.005, 0.01, 0.015, 0.02, 0.03, 0.04, 0.05, 0.065, 0.08)  # m from the COM
    probe_spacing: float = 0.005  # m between probes on a ring
    min_seal: float = 0.9  # a sound seal on the true mesh, preferred to any weaker one
    seal_floor: float = EnvConfig().grasp.seal_threshold  # a weaker seal than this holds nothing: never picked
    max_tilt_deg: float = 20.0  # a face this close to level is picked top-down; steeper ones only as a fallback
    height_band: float = 0.02  # m: parcel tops this close are equally high
    # m: a parcel outside the library (no asset index) whose COM is this close to that of a failed pick counts
    # as tried; library parcels are recognised by their asset index (a dropped parcel lands elsewhere)
    retry_radius: float = 0.02
    side_tilts_deg: tuple[float, ...] = (30.0, 55.0, 80.0)  # fallback probe directions from vertical
    # fallback approach tilts on a face: the cup comes in this far off the face normal, leaning away from the
    # nearest bin wall, so the tool and wrist clear a wall the parcel lies against (the bellows absorbs the
    # tilt up to its bend limit, at a lower seal; the prediction scores it)
    lean_tilts_deg: tuple[float, ...] = (10.0, 18.0)
    side_azimuths: int = 8  # headings per fallback tilt
    max_face_tilt_deg: float = 60.0  # faces steeper than this are never proposed: the tool and wrist (0.3 m)
    # would reach across the pile or into a wall, and the arm mounted beside the tote cannot hold them
    seal_margin: float = 0.05  # a seal this close to the threshold is a last resort: physics moves it by ~0.01
    reach_checks: int = 40  # ranked candidates checked for reachability (IK along the pick) per decision
    reach_step: float = 0.05  # m between IK checks along the lift line

    def __post_init__(self) -> None:
        radii = np.asarray(self.probe_radii, dtype=np.float64)
        if radii.ndim != 1 or len(radii) == 0 or np.any(radii < 0) or not np.all(np.isfinite(radii)):
            raise ValueError(f"OracleConfig.probe_radii must be finite radii >= 0, got {self.probe_radii!r}")
        for name in ("probe_spacing", "height_band", "retry_radius"):
            if not getattr(self, name) > 0:
                raise ValueError(f"OracleConfig.{name} must be > 0, got {getattr(self, name)!r}")
        if not 0.0 <= self.max_tilt_deg <= 90.0:
            raise ValueError(f"OracleConfig.max_tilt_deg must be in [0, 90], got {self.max_tilt_deg!r}")
        if not 0.0 <= self.seal_floor <= self.min_seal <= 1.0:
            raise ValueError(f"OracleConfig needs 0 <= seal_floor <= min_seal <= 1, got {self.seal_floor!r}, "
                             f"{self.min_seal!r}")

    def probe_directions(self) -> np.ndarray:
        """(D, 3) unit fallback probe directions (pointing into the parcel, downward)."""
        tilt = np.radians(np.repeat(np.asarray(self.side_tilts_deg, dtype=np.float64), self.side_azimuths))
        heading = np.tile(2 * np.pi * np.arange(self.side_azimuths) / self.side_azimuths, len(self.side_tilts_deg))
        return np.stack([np.sin(tilt) * np.cos(heading), np.sin(tilt) * np.sin(heading), -np.cos(tilt)], axis=1)

    def probe_offsets(self) -> np.ndarray:
        """(K, 2) horizontal probe offsets from the COM vertical."""
        counts = [max(6, int(np.ceil(2 * np.pi * r / self.probe_spacing))) for r in self.probe_radii]
        return ring_pattern(self.probe_radii, counts)


@dataclass
class GroundTruth:
    """The true scene a ``state_dict`` observation describes, as the scorer wants it."""

    meshes: list[trimesh.Trimesh]  # world frame, one per real parcel row
    coms: np.ndarray  # (P, 3)
    masses: np.ndarray  # (P,)
    obstacles: list[trimesh.Trimesh]  # the bin's floor and walls
    bin_centre: np.ndarray  # (2,)
    obstacles_top: float = 0.0  # m: the bin rim's height
    asset_index: np.ndarray | None = None  # (P,) library index of each parcel, < 0 outside the library


def ground_truth(obs: Mapping[str, Any], library: AssetLibrary) -> GroundTruth:
    """Rebuild the true meshes of a ``state_dict`` observation: library assets by index, and the oriented
    box (``parcel_extents``) for an asset outside the library (a custom scene's cartons are exactly that)."""
    missing = [k for k in STATE_KEYS if k not in obs]
    if missing:
        raise ValueError(f"OraclePolicy needs the privileged obs_mode='state_dict' observation (stored AP "
                         f"scenes do not carry it yet); missing {missing}")
    mask = np.asarray(obs["parcel_mask"]).astype(bool)
    rows = np.flatnonzero(mask)
    position = np.asarray(obs["parcel_position"], dtype=np.float64)[rows]
    quaternion = np.asarray(obs["parcel_quaternion"], dtype=np.float64)[rows]
    index = np.asarray(obs["parcel_asset_index"]).astype(np.int64)[rows]
    extents = np.asarray(obs["parcel_extents"], dtype=np.float64)[rows]
    rotation = Rotation.from_quat(quaternion).as_matrix() if len(rows) else np.zeros((0, 3, 3))
    meshes = []
    for k in range(len(rows)):
        local = (asset_from_index(library, int(index[k])).mesh if index[k] >= 0
                 else trimesh.creation.box(extents=extents[k]))
        transform = np.eye(4)
        transform[:3, :3], transform[:3, 3] = rotation[k], position[k]
        meshes.append(local.copy().apply_transform(transform))
    spec = bin_from_vector(obs["bin"])
    return GroundTruth(meshes=meshes, coms=np.asarray(obs["parcel_com"], dtype=np.float64)[rows],
                       masses=np.asarray(obs["parcel_mass"], dtype=np.float64)[rows], obstacles=spec.meshes(),
                       bin_centre=np.asarray(spec.center_xy, dtype=np.float64),
                       obstacles_top=float(spec.floor_z + spec.wall_height), asset_index=index)


def uncovered_top_points(truth: GroundTruth, offsets: np.ndarray, num_threads: int = 0,
                         direction: np.ndarray | None = None, parcels: np.ndarray | None = None
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Probes along ``direction`` (default straight down) on rings about the line through each parcel's
    COM (only ``parcels`` if given) whose first hit in the whole scene is that parcel.

    Returns points (M, 3), true face normals facing the probe (outward on the face it sees) (M, 3) and
    the parcel of each (M,).
    """
    rows = np.arange(len(truth.meshes)) if parcels is None else np.asarray(parcels, dtype=np.int64)
    if len(rows) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    d = np.array([0.0, 0.0, -1.0]) if direction is None else np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    u, w = tangent_frames(-d[None])
    owner = np.repeat(rows, len(offsets))
    plane = np.tile(offsets, (len(rows), 1))
    lines = truth.coms[owner] + plane[:, :1] * u + plane[:, 1:] * w  # points on the probe lines
    # start every probe above the whole scene along -d: beyond every parcel and the bin
    everything = np.concatenate([m.bounds for m in truth.meshes + truth.obstacles])
    reach = float(np.linalg.norm(everything.max(axis=0) - everything.min(axis=0))) + PROBE_ABOVE
    top = max(float(m.bounds[1, 2]) for m in truth.meshes) + PROBE_ABOVE
    back = (top - lines[:, 2]) / -d[2] if d[2] < -0.5 else np.full(len(lines), reach)
    origins = lines - back[:, None] * d
    rays = np.concatenate([origins, np.tile(d, (len(owner), 1))], axis=1).astype(np.float32)
    scene = build_scene(truth.meshes + truth.obstacles)  # parcel k is geometry k
    hits = scene.cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=num_threads)
    ids = hits["geometry_ids"].numpy().astype(np.int64)
    ids[ids == O3D_INVALID_ID] = -1
    keep = ids == owner
    t = hits["t_hit"].numpy().astype(np.float64)[keep]
    points = origins[keep] + np.outer(t, d)
    normals = hits["primitive_normals"].numpy().astype(np.float64)[keep]
    normals *= np.where(normals @ d > 0, -1.0, 1.0)[:, None]  # face the probe: outward on the face it sees
    norm = np.linalg.norm(normals, axis=1, keepdims=True)
    good = norm[:, 0] > 1e-9
    return points[good], normals[good] / norm[good], owner[keep][good]


def pinned_parcels(truth: GroundTruth, offsets: np.ndarray, num_threads: int = 0) -> np.ndarray:
    """(P,) bool: parcels another parcel lies on, anywhere over the probe rings about their COM vertical
    (a downward probe passes through the parcel but first meets another one). Lifting such a parcel
    drags the one on top of it, so it is picked after the free ones."""
    count = len(truth.meshes)
    if count == 0:
        return np.zeros(0, dtype=bool)
    top = max(float(m.bounds[1, 2]) for m in truth.meshes) + PROBE_ABOVE
    owner = np.repeat(np.arange(count), len(offsets))
    origins = np.empty((len(owner), 3))
    origins[:, :2] = np.repeat(truth.coms[:, :2], len(offsets), axis=0) + np.tile(offsets, (count, 1))
    origins[:, 2] = top
    rays = o3d.core.Tensor.from_numpy(
        np.concatenate([origins, np.tile([0.0, 0.0, -1.0], (len(owner), 1))], axis=1).astype(np.float32))
    first = build_scene(truth.meshes).cast_rays(rays, nthreads=num_threads)["geometry_ids"].numpy().astype(np.int64)
    first[first == O3D_INVALID_ID] = -1
    pinned = np.zeros(count, dtype=bool)
    for k in range(count):  # one small ray scene per parcel: does the probe pass through it at all?
        rows = slice(k * len(offsets), (k + 1) * len(offsets))
        through = np.isfinite(build_scene([truth.meshes[k]]).cast_rays(rays[rows], nthreads=num_threads)["t_hit"].numpy())
        pinned[k] = bool(np.any(through & (first[rows] >= 0) & (first[rows] != k)))
    return pinned


def leaned_on(truth: GroundTruth, gap: float = 0.005, samples: int = 200) -> np.ndarray:
    """(P,) bool: parcels another parcel's hull comes within ``gap`` of over their upper half (above the
    COM). There a neighbour leans on it or presses its side, and as the parcel rises the contact drags on
    the lift with a lever about the cup (the lift drops seen on stacked piles were such side contacts).
    Surface samples pushed ``gap`` outward are tested for lying inside any hull (its own hull is convex,
    so they lie outside it)."""
    count = len(truth.meshes)
    if count < 2:
        return np.zeros(count, dtype=bool)
    hulls = [m.convex_hull for m in truth.meshes]
    points, owner = [], []
    for k, hull in enumerate(hulls):
        where, face = trimesh.sample.sample_surface(hull, samples, seed=k)
        upper = where[:, 2] > truth.coms[k, 2]
        points.append(where[upper] + gap * hull.face_normals[face[upper]])
        owner.append(np.full(int(upper.sum()), k))
    query = o3d.core.Tensor.from_numpy(np.concatenate(points).astype(np.float32))
    inside = build_scene(hulls).compute_occupancy(query).numpy() > 0.5
    out = np.zeros(count, dtype=bool)
    out[np.unique(np.concatenate(owner)[inside])] = True
    return out


@dataclass
class PredictedGrasp:
    """What the cell will find at each candidate, predicted on the true scene (``predicted_grasp``)."""

    seal: np.ndarray  # (N,) bellows contact seal where the cup comes to rest on the parcel's hull
    ratios: np.ndarray  # (N, 6) Dex-Net ring ratios hanging still at that seal's pull (CONDITIONS order)
    collision: np.ndarray  # (N,) 1 if the physical tool along n clears every hull, the bin and the floor

    @property
    def worst(self) -> np.ndarray:
        return self.ratios.max(axis=1)


def hull_seats(hulls: o3d.t.geometry.RaycastingScene, points: np.ndarray, normals: np.ndarray,
               owner: np.ndarray, num_threads: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Where the lip comes to rest coming down along ``-n`` onto the parcels' convex hulls (what physics
    collides), and whether that is the candidate's own parcel (another hull in the way: it is not)."""
    origins = points + SEAT_ABOVE * normals
    rays = np.concatenate([origins, -normals], axis=1).astype(np.float32)
    hits = hulls.cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=num_threads)
    ids = hits["geometry_ids"].numpy().astype(np.int64)
    t = hits["t_hit"].numpy().astype(np.float64)
    own = (ids == owner) & np.isfinite(t)
    tips = np.where(own[:, None], origins - np.where(own, t, 0.0)[:, None] * normals, points)
    return tips, own


def leaned_approaches(points: np.ndarray, normals: np.ndarray, owner: np.ndarray, bin_centre: np.ndarray,
                      tilts_deg: Sequence[float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The same contact points, each approached off its face normal by every tilt in ``tilts_deg``, turned
    towards the bin centre about the horizontal axis across that direction (the approach axis is -normal)."""
    inward = np.zeros_like(points)
    inward[:, :2] = bin_centre - points[:, :2]
    inward /= np.maximum(np.linalg.norm(inward, axis=1, keepdims=True), 1e-9)
    out = []
    for tilt in np.radians(np.asarray(tilts_deg, dtype=np.float64)):
        tilted = np.cos(tilt) * normals + np.sin(tilt) * inward  # the tool leans towards the centre
        out.append(tilted / np.linalg.norm(tilted, axis=1, keepdims=True))
    k = len(out)
    return np.tile(points, (k, 1)), np.concatenate(out) if out else np.zeros((0, 3)), np.tile(owner, k)


def predicted_grasp(truth: GroundTruth, points: np.ndarray, normals: np.ndarray, owner: np.ndarray,
                    suction: SuctionConfig, cup: CupSpec) -> PredictedGrasp:
    """The seal, the ring ratios at rest and the tool clearance the cell will meet at each candidate."""
    hulls = build_scene([m.convex_hull for m in truth.meshes] + truth.obstacles)  # what physics collides
    tips, own = hull_seats(hulls, points, normals, owner, suction.num_threads)
    contact = dataclasses.replace(suction, seal_model="bellows")  # the env judges the physical cup's seal
    axes = -normals
    seal = SuctionScorer(truth.meshes, truth.coms, truth.obstacles, contact).contact_seal(tips, axes, owner).quality
    seal = np.where(own, seal, 0.0).astype(np.float32)
    # the parcel hanging still: the cup pulls m g straight up, about the lip at the seat
    force = np.outer(truth.masses[owner] * suction.gravity, [0.0, 0.0, 1.0])
    torque = np.cross(truth.coms[owner] - tips, force)
    f_z, t_z = np.sum(force * axes, axis=1), np.sum(torque * axes, axis=1)
    lateral = np.linalg.norm(force - f_z[:, None] * axes, axis=1)
    bending = np.linalg.norm(torque - t_z[:, None] * axes, axis=1)
    zero = np.zeros(len(points))
    ratios = suction_ring_ratios(np.stack([lateral, zero, f_z], axis=1), np.stack([bending, zero, t_z], axis=1),
                                 cup.friction, suction.cup_radius, suction.material_k,
                                 cup.rated_force(suction.cup_radius, seal))
    collision = collision_scores(hulls, points, normals, physical_tool(suction))
    return PredictedGrasp(seal=seal, ratios=np.asarray(ratios).reshape(len(points), -1), collision=collision)


def physical_tool(suction: SuctionConfig, tool: SuctionToolSpec = SuctionToolSpec(),
                  margin: float = PlannerConfig().margin) -> SuctionConfig:
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


class ArmReach:
    """Whether the cell's arm reaches a pick: the arm's own numpy kinematics (``Gen3Kinematics.refine``, the
    same damped least squares the env's IK refines with) at the mount, joint limits and IK tolerances of
    ``ArmConfig``, chained along the pick from the contact up to the carrying height (every ``step``), tool
    on the approach axis. A deterministic local solve: a reachable pose it misses only moves a candidate
    back in the ranking, never out of it."""

    def __init__(self, arm: ArmConfig | None = None, tool: SuctionToolSpec = SuctionToolSpec()) -> None:
        arm = arm or ArmConfig()
        self.kin = Gen3Kinematics(arm.base_position, arm.base_yaw, tool.length)
        self.lower = np.array([j[4] for j in JOINTS])
        self.upper = np.array([j[5] for j in JOINTS])
        self.seed = np.asarray(arm.ik_seed, dtype=np.float64)
        self.tol_p, self.tol_a = arm.ik_position_tol, arm.ik_angle_tol

    def reaches(self, points: np.ndarray, axis: np.ndarray) -> bool:
        """Every point in turn (seeded by the previous answer), the tool axis along ``axis``."""
        q = self.seed
        for k, point in enumerate(np.asarray(points, dtype=np.float64)):
            q = self.kin.refine(q, point, axis, self.seed, self.lower, self.upper, self.tol_p, self.tol_a,
                                iterations=150 if k == 0 else 60)
            if q is None:
                return False
        return True


class OraclePolicy(Policy):
    """Privileged upper bound: true top faces near the centre of mass, scored by the shared scorer."""

    name = "oracle"
    obs_mode = "state_dict"  # the privileged channel; the registry allows it to this policy only
    privileged = True

    def __init__(self, config: OracleConfig | None = None, suction: SuctionConfig | None = None,
                 asset_seed: int | None = None) -> None:
        if config is not None and not isinstance(config, OracleConfig):
            raise ValueError(f"config must be an OracleConfig, got {type(config).__name__}")
        if suction is not None and not isinstance(suction, SuctionConfig):
            raise ValueError(f"suction must be a SuctionConfig, got {type(suction).__name__}")
        defaults = EnvConfig()
        self.config = config or OracleConfig()
        # Used only when info does not carry the env's own cup and library seed (the env always does).
        self.suction = suction or defaults.suction
        self.asset_seed = defaults.asset_seed if asset_seed is None else int(asset_seed)
        self._offsets = self.config.probe_offsets()
        self.cup: CupSpec = defaults.grasp.cup  # the cell's vacuum and lip (docs/cell.md)
        self.grasp = defaults.grasp  # the cell's pick geometry: pre-grasp distance, carrying clearance
        self.reach = ArmReach(defaults.arm)
        self.load_target = defaults.grasp.carry_load_target  # a sound pick hangs within the carry's load share
        self.last_scores: SuctionScores | None = None
        self.last_ratios: np.ndarray | None = None  # (K, 6) predicted ring ratios at rest of the returned picks
        self.last_object_ids: np.ndarray | None = None
        self._aimed_com: tuple[int, np.ndarray] | None = None  # (asset index, COM) of the last pick's parcel
        self._failed_coms: list[tuple[int, np.ndarray]] = []  # the same, of parcels whose pick failed

    def reset(self, seed: int | None = None) -> None:
        """A new episode: forget which picks failed."""
        self._aimed_com = None
        self._failed_coms = []

    def _note_outcome(self, info: Mapping[str, Any]) -> None:
        """A failed attempt (``info['outcome']``, which every policy sees) puts that parcel behind the others,
        so a deterministic oracle does not repeat a pick the cell could not do."""
        outcome = info.get("outcome")
        if self._aimed_com is not None and outcome is not None and outcome != "success":
            self._failed_coms.append(self._aimed_com)
        self._aimed_com = None

    def _context(self, info: Mapping[str, Any] | None) -> tuple[SuctionConfig, AssetLibrary]:
        info = info or {}
        suction = info.get("suction", self.suction)
        if not isinstance(suction, SuctionConfig):
            raise ValueError(f"info['suction'] must be a SuctionConfig, got {type(suction).__name__}")
        return suction, AssetLibrary.default(int(info.get("asset_seed", self.asset_seed)))

    def predict(self, obs: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None,
                top_k: int = 50) -> Candidates:
        if top_k < 1:
            raise ValueError(f"top_k must be >= 1, got {top_k}")
        suction, library = self._context(info)
        self._note_outcome(info or {})
        truth = ground_truth(obs, library)
        points, normals, owner = uncovered_top_points(truth, self._offsets, suction.num_threads)
        grasp = predicted_grasp(truth, points, normals, owner, suction, self.cup)
        # parcels with no admissible top candidate: their uncovered side faces and ends
        bare = np.setdiff1d(np.arange(len(truth.meshes)), owner[self._admissible(grasp, normals)])
        if len(bare):
            found = [uncovered_top_points(truth, self._offsets, suction.num_threads, d, bare)
                     for d in self.config.probe_directions()]
            faces = np.isin(owner, bare)
            found.append(leaned_approaches(points[faces], normals[faces], owner[faces], truth.bin_centre,
                                           self.config.lean_tilts_deg))
            side = tuple(np.concatenate([f[i] for f in found]) for i in range(3))
            side_grasp = predicted_grasp(truth, *side, suction, self.cup)
            points, normals, owner = (np.concatenate([a, b]) for a, b in zip((points, normals, owner), side))
            grasp = PredictedGrasp(*(np.concatenate([getattr(grasp, f.name), getattr(side_grasp, f.name)])
                                     for f in dataclasses.fields(PredictedGrasp)))
        if len(points) == 0:
            raise ValueError("the oracle finds no uncovered face on any parcel")
        wrench = self._real_mass_wrench(points, normals, owner, truth, suction)
        visibility = np.ones(len(points), dtype=np.float32)  # the oracle sees every parcel whole
        scores = SuctionScores(seal=grasp.seal, wrench=wrench, collision=grasp.collision, visibility=visibility,
                               total=(grasp.seal * wrench * grasp.collision).astype(np.float32))
        order = self._rank(points, normals, owner, grasp, truth)
        if len(order) == 0:
            raise ValueError("the oracle finds no admissible pick (seal, tool clearance and ring conditions all "
                             "hold) on any uncovered face")
        order = self._reachable_first(order, points, normals, owner, truth)[:top_k]
        self.last_scores = type(scores)(*(getattr(scores, f.name)[order] for f in dataclasses.fields(scores)))
        self.last_ratios = grasp.ratios[order]
        self.last_object_ids = owner[order]
        k = int(owner[order[0]])
        index = -1 if truth.asset_index is None else int(truth.asset_index[k])
        self._aimed_com = (index, truth.coms[k].copy())
        rank = 1.0 - np.arange(len(order)) / len(order)
        return Candidates(points=points[order].astype(np.float32), normals=normals[order].astype(np.float32),
                          scores=rank.astype(np.float32))

    def _admissible(self, grasp: PredictedGrasp, normals: np.ndarray) -> np.ndarray:
        """Candidates the cell can hold: the tool is free, the seal reaches ``seal_floor`` (the env's
        threshold), every ring condition holds the parcel hanging still, and the face is not steeper than
        ``max_face_tilt_deg``."""
        c = self.config
        upright = normals[:, 2] >= np.cos(np.radians(c.max_face_tilt_deg))
        return np.flatnonzero((grasp.seal >= c.seal_floor) & (grasp.collision > 0) & (grasp.worst < 1.0) & upright)

    def _pick_line(self, point: np.ndarray, normal: np.ndarray, parcel: int, truth: GroundTruth) -> np.ndarray:
        """Tip positions the pick passes: pre-grasp, contact, straight up to the carrying height (the env's
        rule: the held parcel's underside ``clearance`` above the rim and the rest of the pile), then over
        to the drop zone."""
        g = self.grasp
        others = [m.bounds[1, 2] for k, m in enumerate(truth.meshes) if k != parcel]
        rim = float(truth.obstacles_top)
        carry = max([rim, *others]) + g.clearance + (point[2] - truth.meshes[parcel].bounds[0, 2])
        carry = max(carry, point[2] + g.min_lift)
        heights = np.arange(point[2], carry, self.config.reach_step)[1:]
        up = np.column_stack([np.full(len(heights) + 1, point[0]), np.full(len(heights) + 1, point[1]),
                              np.append(heights, carry)])
        # then over to the drop zone at that height, tool still on the approach axis (a tilted pick is
        # carried tilted; the env's detour round the base is not modelled, so this may only demote a pick)
        drop = np.array([g.drop_zone[0], g.drop_zone[1], max(g.drop_zone[2], carry)])
        legs = max(1, int(np.ceil(np.linalg.norm(drop - up[-1]) / (2 * self.config.reach_step))))
        over = up[-1] + (drop - up[-1]) * (np.arange(1, legs + 1)[:, None] / legs)
        return np.vstack([point + g.pregrasp_distance * normal, point, up, over])

    def _reachable_first(self, order: np.ndarray, points: np.ndarray, normals: np.ndarray, owner: np.ndarray,
                         truth: GroundTruth) -> np.ndarray:
        """The ranked candidates with the first one the arm reaches (``ArmReach``, checking at most
        ``reach_checks``) moved to the front, and those found unreachable moved to the back."""
        unreachable = []
        for i in order[:self.config.reach_checks]:
            if self.reach.reaches(self._pick_line(points[i], normals[i], int(owner[i]), truth), -normals[i]):
                rest = order[(order != i) & ~np.isin(order, unreachable)]
                return np.concatenate([[i], rest, np.asarray(unreachable, dtype=order.dtype)])
            unreachable.append(i)
        return order

    @staticmethod
    def _real_mass_wrench(points: np.ndarray, normals: np.ndarray, owner: np.ndarray, truth: GroundTruth,
                          suction: SuctionConfig) -> np.ndarray:
        """The scorer's wrench condition, with each parcel's real mass in place of the unit mass."""
        out = np.zeros(len(points), dtype=np.float32)
        for k in np.unique(owner):
            rows = owner == k
            real = dataclasses.replace(suction, unit_mass=float(truth.masses[k]))
            out[rows] = wrench_scores(points[rows], normals[rows], np.broadcast_to(truth.coms[k], (rows.sum(), 3)),
                                      real)
        return out

    def _rank(self, points: np.ndarray, normals: np.ndarray, owner: np.ndarray, grasp: PredictedGrasp,
              truth: GroundTruth) -> np.ndarray:
        """Indices of the admissible candidates: parcels not yet tried before tried ones, free parcels
        before pinned ones (``pinned_parcels``), robust seals before ones within ``seal_margin`` of the
        threshold; then sound picks
        (seal at least ``min_seal``, ring ratios within the carry's load target) before weaker ones, level
        candidates before tilted ones, highest parcels first, central ones first, and small lever arms first."""
        c = self.config
        admissible = self._admissible(grasp, normals)
        if len(admissible) == 0:
            return admissible
        parcels = owner[admissible]
        top = np.full(len(truth.meshes), -np.inf)
        np.maximum.at(top, parcels, points[admissible, 2])
        tier = np.round(top / c.height_band)
        centrality = np.linalg.norm(truth.coms[:, :2] - truth.bin_centre, axis=1)
        lever = np.linalg.norm(points[admissible, :2] - truth.coms[parcels, :2], axis=1)
        level = normals[admissible, 2] >= np.cos(np.radians(c.max_tilt_deg))
        tried = np.zeros(len(truth.meshes), dtype=np.int64)
        indices = np.full(len(truth.meshes), -1) if truth.asset_index is None else truth.asset_index
        for index, com in self._failed_coms:
            tried += (indices == index) if index >= 0 else (np.linalg.norm(truth.coms - com, axis=1) < c.retry_radius)
        pinned = pinned_parcels(truth, self._offsets)
        leaned = leaned_on(truth)
        sound = (grasp.seal[admissible] >= c.min_seal) & (grasp.worst[admissible] <= self.load_target)
        marginal = grasp.seal[admissible] < c.seal_floor + c.seal_margin
        # np.lexsort sorts by the last key first
        return admissible[np.lexsort((lever, centrality[parcels], -tier[parcels], ~level, ~sound, marginal,
                                      leaned[parcels], pinned[parcels], tried[parcels]))]
