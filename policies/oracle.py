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
2. Predict the cell's own verdict for every candidate (the ``physical`` definition, ``SuctionScorer.physical``,
   ``parcelpick_env/suction/physical.py``), as physics will reach it:
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
   parcel, the smallest lever arm (horizontal distance to the COM) first. Above all these, free parcels
   come before pinned ones (another parcel's hull lies on them or hangs over their footprint anywhere,
   ``pinned_parcels``: lifting them lifts or strikes it, so they wait even behind a parcel whose pick
   failed), then parcels not yet tried (a parcel whose pick failed, ``info['outcome']``, goes behind the
   untried ones for the rest of the episode), then parcels no neighbour's hull touches over their upper
   half (``leaned_on``), then robust seals before marginal ones: within ``seal_margin`` of the threshold, or
   below it with the lip ``seal_standoff`` (1 mm) further out than its seat (a seal held across a mailer's
   hull gap); a parcel's marginal candidates go best backed-off seal first.
   Where no candidate is admissible even on the steep last-resort faces, the oracle still tries: the tool-free
   candidates, sealing ones first, then the smallest worst ring ratio, approaches that already failed last
   (``_best_guesses``), as a real cell would rather than stand idle.
4. Reachability: the arm's own numpy IK (``ArmReach``), chained from the pre-grasp point through the contact
   up to the carrying height and over to the drop zone, and the cell's own plan, asked of a twin of the tote,
   arm and pile (``policies/cell_twin.py``: hover, descent, approach and lift as ``PickExecutor`` plans them,
   and the lift by the cell's line rule); the first ranked candidate that passes is proposed, the unreachable
   ones checked go to the back (never out). Where none of the first ``reach_checks`` passes, the first
   ``confirm_checks`` are asked of the cell's plan alone, then the best candidate of every other parcel in
   rank order, then ``spread_checks`` candidates spread over the approaches offered.
5. Rehearsal: the pick so chosen is run whole on the twin, dynamics and all (``CellTwin.rehearse``: seal, hold
   and the neighbours' drag in the lift, which no geometric model above predicts); where it does not hold there
   cleanly (every ring ratio at most ``clean_peak``), the best candidate of each other parcel, then approaches
   spread over those offered, until one does (at most ``rehearsals``; the least loaded success if none is
   clean). A perfect policy knows the physics too. On the posed twin, what it still fails is where the cell's
   physics does not repeat itself from the same poses (the twin's contacts start fresh); so by default
   (``exact_rehearsals``) the rehearsals of a decision on the observed pile run on the shadow of the cell instead
   (``policies/shadow_cell.py``: the env's own code, built from ``info['env_config']``, reset to the episode's
   pile and stepped with every action taken, checked to the bit against the observation), whose verdict is the
   env's. Then it fails only where nothing it rehearsed holds.
6. Parting (by default, the env in ``action_mode="pose_push"``; ``parting_pushes=False`` gives the pick-only
   oracle, in ``pose``): where nothing it rehearsed holds (or, with ``confirmations``, what held as synced did not
   hold on every twin with the pile's poses jittered), up to ``push_trials`` pushes (``policies/parting.py``)
   are rehearsed on the twin, and the first after which a pick holds on the pile the twin is left with is made
   instead of the pick (``act``, ``_parting_push``); on the shadow of the cell, each push is looked past there
   (``_look_past``), and where none opens the pile, the failed pick made is the first of the decision's after
   which a pick holds (``opening_picks``, ``_opening_pick``). A perfect picker in a real cell parts a pile it cannot pick
   from; without it the 30-parcel heap ends in dead ends no pick can open (results/ORACLE.md, 'A parting move').

``scores`` in the returned ``Candidates`` encode that rank (1 for the first, falling linearly); the
physical scores of the returned candidates are kept in ``last_scores`` and their parcels in
``last_object_ids``. ``predict`` reads only ``obs`` and ``info``, never the env object.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np
import open3d as o3d
import trimesh
from scipy.spatial.transform import Rotation

from parcelpick_env.assets.library import AssetLibrary
from parcelpick_env.envs.config import EnvConfig
from parcelpick_env.envs.grasp import PickResult
from parcelpick_env.envs.observation import asset_from_index, bin_from_vector
from parcelpick_env.envs.push import is_push_action, pick_action
from parcelpick_env.farthest_points import farthest_point_indices
from parcelpick_env.robot.arm import ArmConfig
from parcelpick_env.robot.gen3 import JOINT_LOWER, JOINT_UPPER, SuctionToolSpec
from parcelpick_env.robot.kinematics import Gen3Kinematics
from parcelpick_env.suction.config import SuctionConfig
from parcelpick_env.suction.cup import CupSpec
from parcelpick_env.suction.geometry import O3D_INVALID_ID, build_scene, ring_pattern, tangent_frames
from parcelpick_env.suction.physical import PhysicalGrasp
from parcelpick_env.suction.scorer import SuctionScorer, SuctionScores
from parcelpick_env.suction.wrench import wrench_scores
from policies.base import Candidates, Policy
from policies.cell_twin import CellTwin, PoseJitter
from policies.failed_picks import FailedPicks
from policies.parting import push_candidates
from policies.shadow_cell import ShadowCell

# a pick the oracle proposed: its point, its normal and its parcel's (asset index, COM), the tag a failure is noted by
Aim = tuple[np.ndarray, np.ndarray, tuple[int, np.ndarray]]

STATE_KEYS: tuple[str, ...] = ("parcel_mask", "parcel_position", "parcel_quaternion", "parcel_com",
                               "parcel_mass", "parcel_asset_index", "parcel_extents", "parcel_friction", "bin")
PROBE_ABOVE = 0.10  # m: probe rays start this far above the highest parcel
# The AP evaluator's privileged channel (eval/ap.py --policy oracle): a stored scene's labelled points and their
# stored label score, from which the label oracle submits the best-labelled points.
LABEL_KEYS: tuple[str, ...] = ("labelled_points", "labelled_normals", "label_score")


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
    retry_angle_deg: float = 20.0  # a candidate this close to a failed pick (retry_radius) and its normal is that pick
    side_tilts_deg: tuple[float, ...] = (30.0, 55.0, 80.0)  # fallback probe directions from vertical
    # fallback approach tilts on a face: the cup comes in this far off the face normal, leaning away from the
    # nearest bin wall, so the tool and wrist clear a wall the parcel lies against (the bellows absorbs the
    # tilt up to its bend limit, at a lower seal; the prediction scores it)
    lean_tilts_deg: tuple[float, ...] = (10.0, 18.0)
    side_azimuths: int = 8  # headings per fallback tilt
    max_face_tilt_deg: float = 60.0  # faces steeper than this are never proposed: the tool and wrist (0.3 m)
    # would reach across the pile or into a wall, and the arm mounted beside the tote cannot hold them
    # ... unless nothing else is admissible: the last parcels standing on edge against a wall (a slim carton, a
    # mailer) often seal only on a side face; proposing it lets the cell try (its IK and planner decide) where
    # the oracle would otherwise give up (invalid_action), the cause of every no-pick end on the stacked grid
    last_resort_face_tilt_deg: float = 85.0
    seal_margin: float = 0.05  # a seal this close to the threshold is a last resort: physics moves it by ~0.01
    # ... and so is one that falls below the threshold with the lip this far further out than its seat: a seal held
    # across a mailer's hull gap (2.6 mm of the 3 mm the leak closes) fell to 0 in the cell, whose seat lies about
    # half a millimetre either way of the predicted one as the parcel settles under the cup (3 no_seal on the grids)
    seal_standoff: float = 0.001  # m
    reach_checks: int = 40  # ranked candidates checked for reachability (IK along the pick) per decision
    # where all of those fail, this many of the first are asked again of the cell's own plan alone (its twin), and
    # if it refuses them too, the best candidate of each other parcel is checked in rank order (``_reachable_first``)
    confirm_checks: int = 2
    # and where every check above refuses, this many candidates spread over the approaches offered (farthest
    # points of each candidate's point moved ``spread_reach`` out along its normal) are asked of the cell's plan,
    # the first it accepts going first: the last parcel of a mixed stacked pile, a thin mailer on edge, offered
    # a hover clear of the tote's wall to 3 of about 240 of its 963 candidates, all far down its ranking
    spread_checks: int = 48
    spread_reach: float = 0.10  # m
    # the pick so chosen is rehearsed on the twin, dynamics and all (``CellTwin.rehearse``); where it does not hold
    # cleanly there, the best candidate of each other parcel in rank order, then candidates spread over the
    # approaches offered, those the cell's plan accepts, until one does or this many were rehearsed (0: none). The
    # twin's verdict matched the cell's on 210 of the 214 picks of the cylindrical and mixed stacked grid, and
    # foresaw 13 of their 15 failures (eval/twin_agreement.py)
    rehearsals: int = 16
    # where no rehearsal holds (a dead end of the heap) and the policy parts piles (parting_pushes, the default;
    # the env then runs in action_mode="pose_push"): this many parting pushes (policies/parting.py) are rehearsed
    # on the twin, and the first after which one of its picks holds there is taken instead of the pick
    push_trials: int = 16
    # where none of the ``rehearsals`` holds, up to this many more: candidates that seal with the tool clear but that
    # ``_admissible`` rejects (a ring ratio of 1 or more hanging still, or a face steeper than ``max_face_tilt_deg``),
    # the least loaded of each parcel in turn (``_last_resort``). That model is conservative: in a heap's dead end a
    # 0.22 kg parcel taken by a vertical face held, and so did 2 of 6 picks of a 1.34 kg parcel lying 30 deg askew,
    # its faces at a ratio of 1.3 (docs/cell.md). 0: none
    last_resort_rehearsals: int = 16
    clean_peak: float = 1.0  # a rehearsed success whose ring ratios never passed this holds cleanly: taken at once
    # a success other than a clean first one (the decision's first rehearsal, no ring ratio above 1) is rehearsed on
    # this many twins with every parcel's pose jittered (``CellTwin.rehearse``, ``PoseJitter``: ``jitter_position``
    # m and ``jitter_angle_deg`` standard deviations); the success held on the most of them, then the least loaded,
    # is taken, and one held on all of them cleanly ends the search (0: none, every success taken as rehearsed). A
    # pick held on fewer than all is fragile: with parting pushes the oracle looks for a push first, as at a dead end.
    # Measured on the heap, not the default (results/ORACLE.md, 'Rehearsals confirmed on jittered twins')
    confirmations: int = 0
    # rehearse, and look past parting pushes, on the shadow of the cell (``policies/shadow_cell.py``: the env's own
    # code on the env's pile, with its contact history, followed step by step) where it follows the env, and on the
    # posed twin otherwise. The plan's refusals, the lift tests and the jittered confirmations stay on the twin
    exact_rehearsals: bool = True
    # at a dead end on the shadow (no rehearsal holds, no parting push opens the pile), the failing pick made is the
    # first of the decision's failed rehearsals after which, looked past on the shadow, a pick holds: a pick that
    # must fail anyway is spent where its fall opens the pile (never the one that would end the episode)
    opening_picks: bool = True
    # at a dead end on the shadow where no opening pick holds either: this many parting pushes an episode are made
    # anyway, the one (of those run cleanly) whose pile's decision came nearest to holding (the lowest peak ring
    # ratio of its rehearsals; the first where none lifted, e.g. a last parcel that seals nowhere), so that the next
    # decision, with its own pushes, meets another pile: two pushes in a row, searched one at a time (a push is no
    # attempt, and the env allows ``EnvConfig.max_pushes``). 0: none
    onward_pushes: int = 2
    jitter_position: float = 0.0005
    jitter_angle_deg: float = 0.3
    reach_step: float = 0.05  # m between IK checks along the lift line

    def __post_init__(self) -> None:
        radii = np.asarray(self.probe_radii, dtype=np.float64)
        if radii.ndim != 1 or len(radii) == 0 or np.any(radii < 0) or not np.all(np.isfinite(radii)):
            raise ValueError(f"OracleConfig.probe_radii must be finite radii >= 0, got {self.probe_radii!r}")
        for name in ("probe_spacing", "height_band", "retry_radius", "seal_standoff"):
            if not getattr(self, name) > 0:
                raise ValueError(f"OracleConfig.{name} must be > 0, got {getattr(self, name)!r}")
        if not 0.0 <= self.max_tilt_deg <= 90.0:
            raise ValueError(f"OracleConfig.max_tilt_deg must be in [0, 90], got {self.max_tilt_deg!r}")
        if not 0.0 <= self.max_face_tilt_deg <= self.last_resort_face_tilt_deg <= 90.0:
            raise ValueError(f"OracleConfig needs 0 <= max_face_tilt_deg <= last_resort_face_tilt_deg <= 90, got "
                             f"{self.max_face_tilt_deg!r}, {self.last_resort_face_tilt_deg!r}")
        if (self.reach_checks < 1 or self.confirm_checks < 0 or self.spread_checks < 0 or not self.spread_reach >= 0
                or self.rehearsals < 0 or not self.clean_peak > 0 or self.push_trials < 0 or self.confirmations < 0
                or self.last_resort_rehearsals < 0 or self.onward_pushes < 0):
            raise ValueError(f"OracleConfig needs reach_checks >= 1, confirm_checks >= 0, spread_checks >= 0, "
                             f"spread_reach >= 0, rehearsals >= 0, clean_peak > 0, push_trials >= 0, "
                             f"confirmations >= 0, last_resort_rehearsals >= 0 and onward_pushes >= 0, got "
                             f"{self.reach_checks!r}, {self.confirm_checks!r}, {self.spread_checks!r}, "
                             f"{self.spread_reach!r}, {self.rehearsals!r}, {self.clean_peak!r}, {self.push_trials!r}, "
                             f"{self.confirmations!r}, {self.last_resort_rehearsals!r}, {self.onward_pushes!r}")
        if not (self.jitter_position >= 0 and self.jitter_angle_deg >= 0):
            raise ValueError(f"OracleConfig needs jitter_position >= 0 and jitter_angle_deg >= 0, got "
                             f"{self.jitter_position!r}, {self.jitter_angle_deg!r}")
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


@dataclass(frozen=True)
class HullContacts:
    """Where the parcels' collision hulls touch (within ``gap``), one row per touching surface sample: the
    parcel whose surface it is (``parcel``), the other one (``other``), the point on ``parcel``'s hull and
    that hull's outward face normal there. Physics collides these hulls, so these are the contacts the
    pile rests on and the ones a rising parcel drags through."""

    parcel: np.ndarray  # (C,)
    other: np.ndarray  # (C,)
    points: np.ndarray  # (C, 3)
    normals: np.ndarray  # (C, 3)


def hull_samples(hull: trimesh.Trimesh, spacing: float, seed: int) -> np.ndarray:
    """Points on a convex hull's surface: its vertices, its edges every ``spacing`` and its faces at about
    one point per ``spacing`` squared (random, seeded). Pile contacts are mostly a corner or an edge of one
    hull on a face of the other, so vertices and edges are sampled exactly and faces only to catch flats."""
    edges = hull.vertices[hull.edges_unique]
    length = np.linalg.norm(edges[:, 1] - edges[:, 0], axis=1)
    steps = np.maximum(1, np.ceil(length / spacing).astype(np.int64))
    edge_of = np.repeat(np.arange(len(edges)), steps)
    frac = (np.arange(len(edge_of)) - np.repeat(np.cumsum(steps) - steps, steps)) / steps[edge_of]
    on_edges = edges[edge_of, 0] + frac[:, None] * (edges[edge_of, 1] - edges[edge_of, 0])
    faces, _ = trimesh.sample.sample_surface(hull, max(1, int(hull.area / spacing**2)), seed=seed)
    return np.concatenate([hull.vertices, on_edges, faces])


def hull_contacts(truth: GroundTruth, gap: float = 0.004, spacing: float = 0.005,
                  num_threads: int = 0) -> HullContacts:
    """Every place two parcels' convex hulls come within ``gap`` (``HullContacts``).

    For each pair whose bounds come that close, the surface samples of one (``hull_samples``) are queried for
    their closest point on the other's hull (Open3D, exact point-to-triangle distance); both orders are
    taken, so a corner of either on a face of the other is found. Edge samples ``spacing`` apart catch an
    edge crossing an edge within ``spacing`` / 2 of the crossing.
    """
    hulls = [m.convex_hull for m in truth.meshes]
    count = len(hulls)
    samples = [hull_samples(h, spacing, seed=k) for k, h in enumerate(hulls)]
    lo = np.array([h.bounds[0] for h in hulls]).reshape(-1, 3)
    hi = np.array([h.bounds[1] for h in hulls]).reshape(-1, 3)
    rows: list[tuple[np.ndarray, ...]] = []
    for k in range(count):
        near = np.flatnonzero(np.all((lo <= hi[k] + gap) & (hi >= lo[k] - gap), axis=1))
        near = near[near != k]
        if len(near) == 0:
            continue
        query = np.concatenate([samples[j] for j in near])
        other = np.repeat(near, [len(samples[j]) for j in near])
        # a sample more than ``gap`` outside this hull's box is more than ``gap`` from the hull: only the rest is
        # queried (the same contacts, in the same order; most of a neighbour's samples lie far from this hull)
        close = np.all((query >= lo[k] - gap) & (query <= hi[k] + gap), axis=1)
        if not np.any(close):
            continue
        query, other = query[close], other[close]
        found = build_scene([hulls[k]]).compute_closest_points(
            o3d.core.Tensor.from_numpy(query.astype(np.float32)), nthreads=num_threads)
        closest = found["points"].numpy().astype(np.float64)
        touch = np.linalg.norm(query - closest, axis=1) <= gap
        if np.any(touch):
            face = found["primitive_ids"].numpy().astype(np.int64)[touch]
            rows.append((np.full(int(touch.sum()), k), other[touch], closest[touch], hulls[k].face_normals[face]))
    if not rows:
        return HullContacts(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))
    return HullContacts(*(np.concatenate(parts) for parts in zip(*rows)))


# A contact on a parcel's hull face tilted less than 60 deg from level bears another parcel's weight from above.
PINNED_NORMAL_Z = 0.5
FOOTPRINT_SPACING = 0.01  # m between the downward probes over a parcel's footprint


def overhung_parcels(truth: GroundTruth, spacing: float = FOOTPRINT_SPACING, num_threads: int = 0) -> np.ndarray:
    """(P,) bool: parcels with another parcel's hull anywhere above them: a downward probe on a grid over the
    parcel's whole footprint (``spacing``) that passes through its hull meets another hull first. The lift
    raises a parcel straight up through the prism above its footprint, so it strikes or carries whatever
    lies there, touching or not (a mailer 2 cm above a carton's corner was struck 2 cm into the lift)."""
    hulls = [m.convex_hull for m in truth.meshes]
    count = len(hulls)
    out = np.zeros(count, dtype=bool)
    if count < 2:
        return out
    top = max(float(h.bounds[1, 2]) for h in hulls) + PROBE_ABOVE
    origins, owner = [], []
    for k, hull in enumerate(hulls):
        (x0, y0), (x1, y1) = hull.bounds[0, :2], hull.bounds[1, :2]
        xs = np.arange(x0 + spacing / 2, x1, spacing)
        ys = np.arange(y0 + spacing / 2, y1, spacing)
        grid = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
        origins.append(np.column_stack([grid, np.full(len(grid), top)]))
        owner.append(np.full(len(grid), k))
    origin, owner_ = np.concatenate(origins), np.concatenate(owner)
    rays = o3d.core.Tensor.from_numpy(
        np.concatenate([origin, np.tile([0.0, 0.0, -1.0], (len(origin), 1))], axis=1).astype(np.float32))
    first = build_scene(hulls).cast_rays(rays, nthreads=num_threads)["geometry_ids"].numpy().astype(np.int64)
    first[first == O3D_INVALID_ID] = -1
    for k in range(count):  # one small ray scene per parcel: does the probe pass through it at all?
        rows = np.flatnonzero(owner_ == k)
        through = np.isfinite(build_scene([hulls[k]]).cast_rays(rays[rows], nthreads=num_threads)["t_hit"].numpy())
        out[k] = bool(np.any(through & (first[rows] >= 0) & (first[rows] != k)))
    return out


def pinned_parcels(truth: GroundTruth, contacts: HullContacts | None = None, num_threads: int = 0) -> np.ndarray:
    """(P,) bool: parcels another parcel lies on or hangs over, anywhere over their whole hull: a contact on
    their upward-facing faces (normal within 60 deg of up, ``PINNED_NORMAL_Z``) or another hull in the prism
    above their footprint (``overhung_parcels``). Lifting such a parcel lifts, drags or strikes the one on top,
    so it is picked after the free ones. The whole hull counts: a tube whose far end, 14 cm from its centre of
    mass, carried another parcel was dragged at 4 N and dropped on torsion (probes within 8 cm of the centre
    of mass had missed it)."""
    contacts = hull_contacts(truth, num_threads=num_threads) if contacts is None else contacts
    out = overhung_parcels(truth, num_threads=num_threads)
    out[np.unique(contacts.parcel[contacts.normals[:, 2] >= PINNED_NORMAL_Z])] = True
    return out


def leaned_on(truth: GroundTruth, contacts: HullContacts | None = None) -> np.ndarray:
    """(P,) bool: parcels another parcel's hull touches above their centre of mass. There a neighbour leans
    on it or presses its side, and as the parcel rises the contact drags on the lift with a lever about the
    cup (the lift drops seen on stacked piles were such side contacts)."""
    contacts = hull_contacts(truth) if contacts is None else contacts
    out = np.zeros(len(truth.meshes), dtype=bool)
    out[np.unique(contacts.parcel[contacts.points[:, 2] > truth.coms[contacts.parcel, 2]])] = True
    return out


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


def truth_scorer(truth: GroundTruth, suction: SuctionConfig) -> SuctionScorer:
    """The shared scorer on the true scene with the env's physical cup (``SuctionScorer.physical``)."""
    return SuctionScorer(truth.meshes, truth.coms, truth.obstacles, dataclasses.replace(suction, seal_model="bellows"),
                         masses=truth.masses)


def best_labelled(obs: Mapping[str, Any], top_k: int) -> Candidates:
    """The label oracle: a stored scene's ``top_k`` best-labelled points (``LABEL_KEYS``), best first; ties keep
    the stored order. What the labels allow a perfect learner to submit, the ceiling of the AP tables."""
    points = np.asarray(obs["labelled_points"], dtype=np.float32).reshape(-1, 3)
    normals = np.asarray(obs["labelled_normals"], dtype=np.float32).reshape(-1, 3)
    score = np.asarray(obs["label_score"], dtype=np.float32).reshape(-1)
    if not len(points) == len(normals) == len(score):
        raise ValueError(f"label oracle: {len(points)} labelled points, {len(normals)} normals, {len(score)} scores")
    order = np.argsort(-score, kind="stable")[:top_k]
    return Candidates(points=points[order], normals=normals[order], scores=score[order])


class ArmReach:
    """Whether the cell's arm reaches a pick, fast: the arm's own numpy kinematics (``Gen3Kinematics.refine``,
    the same damped least squares the env's IK refines with) at the mount, joint limits and IK tolerances of
    ``ArmConfig``, chained along the pick from the contact up to the carrying height and over to the drop zone
    (every ``step``), tool on the approach axis. A local solve from the Kinova home: it misses reachable poses
    (on the Table V grid, 10 decisions found none of their 40 checked candidates reachable, and the cell made
    the first one every time), so the oracle then asks the cell's own plan on its twin (``CellTwin``)."""

    def __init__(self, arm: ArmConfig | None = None, tool: SuctionToolSpec = SuctionToolSpec()) -> None:
        self.config = arm or ArmConfig()
        self.kin = Gen3Kinematics(self.config.base_position, self.config.base_yaw, tool.length)
        self.lower, self.upper = JOINT_LOWER, JOINT_UPPER
        self.seed = np.asarray(self.config.ik_seed, dtype=np.float64)
        self.tol_p, self.tol_a = self.config.ik_position_tol, self.config.ik_angle_tol

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
                 asset_seed: int | None = None, parting_pushes: bool = True, confirmations: int | None = None,
                 exact: bool | None = None, last_resort: int | None = None, onward: int | None = None) -> None:
        """``confirmations``, where given, replaces ``config``'s (``--policy-arg confirmations=2``: each success
        but a clean first one is rehearsed again on two jittered twins; ``OracleConfig.confirmations``), and so
        do ``exact`` (``--policy-arg exact=false``: every rehearsal on the posed twin, none on the shadow of the
        cell; ``OracleConfig.exact_rehearsals``), ``last_resort`` (``--policy-arg last_resort=0``: no rehearsal
        of what the hold model rejects; ``OracleConfig.last_resort_rehearsals``) and ``onward`` (``--policy-arg
        onward=0``: no push made at a dead end without a pick foreseen to hold after it;
        ``OracleConfig.onward_pushes``)."""
        if config is not None and not isinstance(config, OracleConfig):
            raise ValueError(f"config must be an OracleConfig, got {type(config).__name__}")
        if not isinstance(parting_pushes, bool):
            raise ValueError(f"parting_pushes must be true or false, got {parting_pushes!r}")
        for name, count in (("confirmations", confirmations), ("last_resort", last_resort), ("onward", onward)):
            if count is not None and (isinstance(count, bool) or not isinstance(count, int)):
                raise ValueError(f"{name} must be a whole number >= 0, got {count!r}")
        if exact is not None and not isinstance(exact, bool):
            raise ValueError(f"exact must be true or false, got {exact!r}")
        # with parting pushes the oracle acts in the env's action_mode="pose_push" (eval/clearance.py makes it so;
        # an env made by hand must be too: Policy.action_mode)
        self.parting_pushes = parting_pushes
        self.action_mode = "pose_push" if parting_pushes else "pose"
        if suction is not None and not isinstance(suction, SuctionConfig):
            raise ValueError(f"suction must be a SuctionConfig, got {type(suction).__name__}")
        defaults = EnvConfig()
        self.config = config or OracleConfig()
        if confirmations is not None:
            self.config = dataclasses.replace(self.config, confirmations=confirmations)
        if exact is not None:
            self.config = dataclasses.replace(self.config, exact_rehearsals=exact)
        if last_resort is not None:
            self.config = dataclasses.replace(self.config, last_resort_rehearsals=last_resort)
        if onward is not None:
            self.config = dataclasses.replace(self.config, onward_pushes=onward)
        # Used only when info does not carry the env's own cup and library seed (the env always does).
        self.suction = suction or defaults.suction
        self.asset_seed = defaults.asset_seed if asset_seed is None else int(asset_seed)
        self._offsets = self.config.probe_offsets()
        self.cup: CupSpec = defaults.grasp.cup  # the cell's vacuum and lip (docs/cell.md)
        self.grasp = defaults.grasp  # the cell's pick geometry: pre-grasp distance, carrying clearance
        self.reach = ArmReach(defaults.arm)
        self.twin = CellTwin(defaults)  # the cell's own plan, on a copy of the tote, arm and pile
        self.shadow = ShadowCell()  # the env itself, followed step by step: exact rehearsals (act only)
        self._exact = False  # this decision rehearses on the shadow (set by act, for the observed pile only)
        self.last_exact = False  # the last decision's rehearsals ran on the shadow
        self.load_target = defaults.grasp.carry_load_target  # a sound pick hangs within the carry's load share
        self.last_scores: SuctionScores | None = None
        self.last_ratios: np.ndarray | None = None  # (K, 6) predicted ring ratios at rest of the returned picks
        self.last_object_ids: np.ndarray | None = None
        self.last_rehearsals: list[str] = []  # the outcome of each rehearsal of the last decision, in order
        self.last_push_rehearsals: list[str] = []  # the outcome of each push rehearsed at the last dead end
        # ... and of each failed pick looked past on the shadow there, before one opened the pile (opening_picks)
        self.last_opening_rehearsals: list[str] = []
        self.last_onward = False  # the last action is an onward push (``OracleConfig.onward_pushes``)
        self._onward: np.ndarray | None = None  # the last dead end's onward push, if it offered one
        self._onward_left = self.config.onward_pushes  # this episode's
        self.last_nearest = np.inf  # the lowest peak ring ratio of the last decision's rehearsals
        self.last_lossy = False  # the last decision's pick held, but knocks a parcel out of the tote (the shadow)
        self._rehearsed: list[int] = []  # the last decision's rehearsed candidates, in order (_rehearsed_first)
        self._failed_picks: list[tuple[np.ndarray, Aim]] = []  # its failed rehearsals: (pose action, aim)
        # of each success of the last decision that was rehearsed again on jittered twins: how many held there
        self.last_confirmations: list[int] = []
        self.last_fragile = False  # the last decision's pick held as synced but not on every jittered twin
        self._jitter_rng = np.random.default_rng(0)  # the twins' pose jitter; reseeded by reset(seed)
        self._aimed: Aim | None = None  # the last proposed pick
        self.failed = FailedPicks(forget_on_success=False, at_contact=False)  # the approaches that failed

    def reset(self, seed: int | None = None) -> None:
        """A new episode: forget which picks failed (and reseed the rehearsals' pose jitter)."""
        self._aimed = None
        self._jitter_rng = np.random.default_rng(seed)
        self._onward_left = self.config.onward_pushes
        self.failed.clear()
        self.shadow.new_episode()

    def _note_outcome(self, info: Mapping[str, Any]) -> None:
        """A failed attempt (``info['outcome']``, which every policy sees) puts that parcel behind the others,
        so a deterministic oracle does not repeat a pick the cell could not do; and the failed approach itself
        (point and normal) behind the parcel's other approaches, so the last parcel left is tried another way."""
        if self._aimed is not None:  # each failure is tagged with its parcel: (asset index, COM)
            point, normal, parcel = self._aimed
            self.failed.note(info, point, normal, tag=parcel)
        self._aimed = None

    def act(self, obs: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None) -> np.ndarray:
        """The best pick, as a ``pose`` action; with ``parting_pushes``, a ``pose_push`` action: that pick, or a
        parting push where no rehearsal of the pick decision held (or each that held knocked a parcel out) and a
        rehearsed push leaves a pile where one does (``_parting_push``), or, at a dead end, an onward push. With
        ``exact_rehearsals``, the shadow of the cell first takes the step the env took, and the decision's
        rehearsals run on it where its pile is the observed one."""
        self.last_opening_rehearsals, self.last_onward = [], False
        exact = self.config.exact_rehearsals and self.shadow.track(obs, info or {})
        self._exact = exact
        try:
            pick = self.predict(obs, info, top_k=1).best_action()
        finally:
            self._exact = False
        exact = exact and self.last_exact
        move = self._parting_push(obs, info, exact) if self.parting_pushes else None
        opening = pick
        if move is None and exact and self.config.opening_picks:
            opening = self._opening_pick(info or {}, pick)
        if move is None and opening is pick and self._onward is not None and self._onward_left > 0:
            move, self._aimed, self.last_onward = self._onward, None, True  # a push: no pick to note
            self._onward_left -= 1
        if move is None:
            move = pick_action(opening, self.action_mode)
        if self.config.exact_rehearsals:
            self.shadow.expect(move)
        return move

    def _parting_push(self, obs: Mapping[str, np.ndarray], info: Mapping[str, Any] | None,
                      exact: bool = False) -> np.ndarray | None:
        """A ``pose_push`` push action, or None. Only where the last decision rehearsed picks and none held (or,
        with ``confirmations``, its pick is fragile): then up to ``push_trials`` pushes (``policies/parting.py``)
        are rehearsed on the twin, and after each that runs and keeps every parcel in the tote, the oracle decides
        again on the pile the twin was left with; the first push after which one of those rehearsals holds (and is
        not fragile) is taken. Otherwise the decision stands as made. With ``exact`` (the shadow of the cell follows
        the env), each push and the decision after it run on the shadow instead (``_look_past``), whose verdict
        is the env's; the twin takes over if the shadow fails. There, where none holds, the push run cleanly after
        which the decision came nearest to holding (the first, where no rehearsal after any lifted: a last parcel
        that seals nowhere or that the arm cannot reach) is kept as the dead end's onward push
        (``OracleConfig.onward_pushes``). Where the pick holds but every success rehearsed knocks a parcel out of the
        tote (``last_lossy``, on the shadow), the pushes are looked past too, and one is taken only where a pick then
        holds losing none; else the lossy pick stands."""
        self.last_push_rehearsals, self._onward = [], None
        info = info or {}
        holds = self._decision_holds()
        lossy = self.last_lossy and holds
        if not self.last_rehearsals or (holds and not lossy) or int(info.get("pushes_left", 1)) < 1:
            return None
        if lossy and not exact:
            return None  # the twin counts no parcel lost: it cannot tell a lossless pile from a lossy one
        decision = (self._aimed, self.last_rehearsals, self.last_confirmations, self.last_fragile, self.last_scores,
                    self.last_ratios, self.last_object_ids, self.last_exact, self._rehearsed, self._failed_picks,
                    self.last_nearest, self.last_lossy)
        suction, library = self._context(info)
        truth = ground_truth(obs, library)
        lo, hi = bin_from_vector(obs["bin"]).workspace(margin=EnvConfig().action_margin)  # the env's action box
        nearest = np.inf
        for push in push_candidates(truth, pinned_parcels(truth), suction.cup_radius, self.config.push_trials,
                                    (lo, hi)):
            action = np.concatenate([push.start, push.direction, [-1.0]]).astype(np.float32)
            if exact:
                answer = self.shadow.foresee(functools.partial(self._look_past, action=action))
                if answer is not None:
                    self.last_push_rehearsals.append(answer["outcome"])
                    if answer["holds"] and not (lossy and answer.get("lossy", True)):
                        self._aimed = None  # a push is no pick: the cell's failed-pick memory is not told of it
                        return action
                    if lossy:
                        continue  # no onward push where a pick holds
                    if "nearest" in answer and (self._onward is None or answer["nearest"] < nearest):
                        nearest, self._onward = answer["nearest"], action  # ran cleanly; the first if none drops
                    continue
                exact = False  # the shadow's child failed: the twin from here on
                if lossy:
                    break  # the twin cannot tell a lossless pile from a lossy one: the lossy pick stands
            self.twin.sync(obs, library)
            result, after = self.twin.rehearse_push(push.start, push.direction)
            self.last_push_rehearsals.append(result.outcome)
            if after is None:
                continue
            self._aimed = None  # nothing to note for a rehearsal's decision
            try:
                self.predict(after, info, top_k=1)
            except ValueError:
                continue
            if self._decision_holds():
                self._aimed = None  # a push is no pick: the cell's failed-pick memory is not told of it
                return action
        (self._aimed, self.last_rehearsals, self.last_confirmations, self.last_fragile, self.last_scores,
         self.last_ratios, self.last_object_ids, self.last_exact, self._rehearsed, self._failed_picks,
         self.last_nearest, self.last_lossy) = decision
        return None

    def _opening_pick(self, info: Mapping[str, Any], pick: np.ndarray) -> np.ndarray:
        """At a dead end on the shadow (``opening_picks``): the first of the decision's failed rehearsals after
        which, looked past on the shadow (``_look_past``), a pick holds, as a ``pose`` action; else ``pick``. Not
        where a failure would end the episode."""
        self.last_opening_rehearsals = []
        config = info.get("env_config")
        if self._decision_holds() or not isinstance(config, EnvConfig) \
                or int(info.get("consecutive_failures", 0)) + 1 >= config.max_consecutive_failures:
            return pick
        for action, aim in self._failed_picks:
            answer = self.shadow.foresee(functools.partial(self._look_past, action=pick_action(action, self.action_mode)))
            if answer is None:
                break
            self.last_opening_rehearsals.append(answer["outcome"])
            if answer["holds"]:
                self._aimed = aim
                return action
        return pick

    def _look_past(self, env: Any, action: np.ndarray) -> dict[str, Any]:
        """Run in the shadow's child (``ShadowCell.foresee``): the action (a parting push, or a pick that fails) as
        the env steps it, then this oracle's decision on the pile it leaves, its rehearsals on the shadow there;
        whether a pick holds. A push that does not run, an action that loses a parcel from the tote, and one that
        ends the episode open nothing."""
        before = len(env.scene.parcels)
        obs, _, terminated, truncated, info = env.step(action)
        answer = {"outcome": str(info["outcome"]), "holds": False}
        if (is_push_action(action) and info["outcome"] != "pushed") or int(info["parcels_remaining"]) < before \
                or terminated or truncated:
            return answer
        self._aimed, self._exact = None, True
        try:
            self.predict(obs, info, top_k=1)
        except ValueError:
            return answer
        answer["holds"], answer["rehearsals"] = self._decision_holds(), list(self.last_rehearsals)
        answer["nearest"], answer["lossy"] = self.last_nearest, self.last_lossy
        return answer

    def _decision_holds(self) -> bool:
        """Whether the last decision's pick held in a rehearsal, and (with ``confirmations``) is not fragile."""
        return "success" in self.last_rehearsals and not self.last_fragile

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
        self.last_rehearsals = []  # filled by _rehearsed_first; empty where this decision raises before it
        self.last_nearest, self.last_lossy = np.inf, False
        self._rehearsed = []  # the candidates rehearsed, in that order (_rehearsed_first)
        self._failed_picks = []
        self.last_exact = self._exact
        self.last_confirmations = []
        self.last_fragile = False  # set by _rehearsed_first
        if all(key in obs for key in LABEL_KEYS):
            return best_labelled(obs, top_k)
        truth = ground_truth(obs, library)
        self.twin.sync(obs, library)
        points, normals, owner = uncovered_top_points(truth, self._offsets, suction.num_threads)
        scorer = truth_scorer(truth, suction)
        grasp = scorer.physical(points, normals, owner, self.cup)
        # parcels with no admissible top candidate: their uncovered side faces and ends
        bare = np.setdiff1d(np.arange(len(truth.meshes)), owner[self._admissible(grasp, normals)])
        if len(bare):
            found = [uncovered_top_points(truth, self._offsets, suction.num_threads, d, bare)
                     for d in self.config.probe_directions()]
            faces = np.isin(owner, bare)
            found.append(leaned_approaches(points[faces], normals[faces], owner[faces], truth.bin_centre,
                                           self.config.lean_tilts_deg))
            side = tuple(np.concatenate([f[i] for f in found]) for i in range(3))
            side_grasp = scorer.physical(*side, self.cup)
            points, normals, owner = (np.concatenate([a, b]) for a, b in zip((points, normals, owner), side))
            grasp = PhysicalGrasp.concatenate([grasp, side_grasp])
        if len(points) == 0:
            raise ValueError("the oracle finds no uncovered face on any parcel")
        wrench = self._real_mass_wrench(points, normals, owner, truth, suction)
        visibility = np.ones(len(points), dtype=np.float32)  # the oracle sees every parcel whole
        scores = SuctionScores(seal=grasp.seal, wrench=wrench, collision=grasp.collision, visibility=visibility,
                               total=(grasp.seal * wrench * grasp.collision).astype(np.float32))
        order = self._rank(points, normals, owner, grasp, truth, scorer)
        if len(order) == 0:  # nothing within max_face_tilt_deg: steeper side faces as a last resort
            order = self._rank(points, normals, owner, grasp, truth, scorer, self.config.last_resort_face_tilt_deg)
        if len(order) == 0:  # nothing the cell is predicted to hold: its best guess beats a wasted cycle
            order = self._best_guesses(points, normals, grasp)
        if len(order) == 0:
            raise ValueError("the oracle finds no uncovered face that the tool can reach")
        order = self._reachable_first(order, points, normals, owner, truth)
        order = self._rehearsed_first(order, points, normals, owner, self._last_resort(order, owner, grasp))[:top_k]
        self.last_scores = type(scores)(*(getattr(scores, f.name)[order] for f in dataclasses.fields(scores)))
        self.last_ratios = grasp.ratios[order]
        self.last_object_ids = owner[order]
        def aim(i: int) -> Aim:
            k = int(owner[i])
            index = -1 if truth.asset_index is None else int(truth.asset_index[k])
            return points[i].copy(), normals[i].copy(), (index, truth.coms[k].copy())

        self._aimed = aim(int(order[0]))
        self._failed_picks = [(np.concatenate([points[i], normals[i]]).astype(np.float32), aim(i))
                              for i, outcome in zip(self._rehearsed, self.last_rehearsals) if outcome != "success"]
        rank = 1.0 - np.arange(len(order)) / len(order)
        return Candidates(points=points[order].astype(np.float32), normals=normals[order].astype(np.float32),
                          scores=rank.astype(np.float32))

    def _admissible(self, grasp: PhysicalGrasp, normals: np.ndarray, max_face_tilt_deg: float | None = None
                    ) -> np.ndarray:
        """Candidates the cell can hold: the tool is free, the seal reaches ``seal_floor`` (the env's
        threshold), every ring condition holds the parcel hanging still, and the face is not steeper than
        ``max_face_tilt_deg`` (the config's unless given)."""
        c = self.config
        tilt = c.max_face_tilt_deg if max_face_tilt_deg is None else max_face_tilt_deg
        upright = normals[:, 2] >= np.cos(np.radians(tilt))
        return np.flatnonzero((grasp.seal >= c.seal_floor) & (grasp.collision > 0) & (grasp.worst < 1.0) & upright)

    def _best_guesses(self, points: np.ndarray, normals: np.ndarray, grasp: PhysicalGrasp) -> np.ndarray:
        """Where no candidate is admissible: the tool-free ones, sealing ones first, then the smallest worst ring
        ratio (the nearest to holding), with approaches that already failed last. A real cell would try these
        rather than stand idle: the prediction takes the worst yaw and the parcel hanging still."""
        free = np.flatnonzero(grasp.collision > 0)
        repeated = self.failed.count_near(points[free], self.config.retry_radius, normals[free],
                                          self.config.retry_angle_deg) > 0
        worst = np.nan_to_num(grasp.worst[free], nan=np.inf)
        return free[np.lexsort((worst, grasp.seal[free] < self.config.seal_floor, repeated))]

    def _carry_height(self, point: np.ndarray, parcel: int, truth: GroundTruth) -> float:
        """The tip's carrying height (the env's rule: the held parcel's underside ``clearance`` above the rim
        and the rest of the pile, at least ``min_lift`` up)."""
        g = self.grasp
        others = [m.bounds[1, 2] for k, m in enumerate(truth.meshes) if k != parcel]
        below = point[2] - truth.meshes[parcel].bounds[0, 2]  # the held parcel's extent under the contact
        carry = max([float(truth.obstacles_top), *others]) + g.clearance + below
        return float(max(carry, point[2] + g.min_lift))

    def _pick_line(self, point: np.ndarray, normal: np.ndarray, parcel: int, truth: GroundTruth) -> np.ndarray:
        """Tip positions the pick passes: pre-grasp, contact, straight up to the carrying height
        (``_carry_height``), then over to the drop zone."""
        g = self.grasp
        carry = self._carry_height(point, parcel, truth)
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
        """The ranked candidates with the first one the cell can do moved to the front, and those found
        unreachable moved to the back.

        A pick passes where the fast check (``ArmReach.reaches``, along the whole pick to the drop zone) and
        the cell's own plan on its twin accept it (``CellTwin.refusal``: hover, descent, approach and lift on
        the IK branch the cell would take; ``CellTwin.lifts``: the lift by the cell's line rule); at most
        ``reach_checks`` in rank order. Where none does, the first ``confirm_checks`` are asked of the cell's
        plan alone: the fast check misses poses the cell
        reaches, and holds a tilted pick's axis over to the drop zone, where the cell turns the tool down (the
        Table V grid's 10 such decisions were all successes, 4 of them picks tilted 31-55 deg whose tilted
        transport no IK solves). Where that refuses too, the best candidate of each parcel not yet checked, in
        rank order (the first checks usually cover one parcel: its many probes near the centre of mass), and
        then ``spread_checks`` candidates spread over the approaches offered, by the cell's plan alone (the last
        parcel of a pile may offer a reachable approach only far down the ranking). If nothing is found, the
        ranking stands."""
        c = self.config

        def line(i: int) -> np.ndarray:
            return self._pick_line(points[i], normals[i], int(owner[i]), truth)

        def planned(i: int) -> bool:
            return (self.twin.lifts(points[i], normals[i], self._carry_height(points[i], int(owner[i]), truth))
                    and self.twin.refusal(points[i], normals[i]) is None)

        def first(i: int, refused: Sequence[int]) -> np.ndarray:
            refused = [j for j in refused if j != i]
            rest = order[(order != i) & ~np.isin(order, refused)]
            return np.concatenate([[i], rest, np.asarray(refused, dtype=order.dtype)])

        checked = [int(i) for i in order[:c.reach_checks]]
        unreachable: list[int] = []
        for i in checked:
            if self.reach.reaches(line(i), -normals[i]) and planned(i):
                return first(i, unreachable)
            unreachable.append(i)
        if not checked:
            return order
        for i in checked[:c.confirm_checks]:
            if planned(i):
                return first(i, unreachable)
        for i in self._each_parcels_best(order, owner, set(owner[checked].tolist()))[:c.reach_checks]:
            if self.reach.reaches(line(i), -normals[i]) and planned(i):
                return first(i, unreachable)
            unreachable.append(i)
        for i in self._spread(order, points, normals, c.spread_checks):
            if i not in checked[:c.confirm_checks] and planned(i):
                return first(i, unreachable)
        return order

    @staticmethod
    def _each_parcels_best(order: np.ndarray, owner: np.ndarray, skip: set[int]) -> list[int]:
        """Each parcel's best-ranked candidate, in rank order, but those of the parcels in ``skip``."""
        _, best = np.unique(owner[order], return_index=True)
        return [int(i) for i in order[np.sort(best)] if int(owner[i]) not in skip]

    def _spread(self, order: np.ndarray, points: np.ndarray, normals: np.ndarray, n: int) -> list[int]:
        """``n`` of the ranked candidates spread in place and direction, farthest first: farthest points of each
        candidate's point moved ``spread_reach`` out along its normal (the pre-grasp side), so every face and
        tilt offered is asked, best-ranked first."""
        if n <= 0 or len(order) == 0:
            return []
        approach = points[order] + self.config.spread_reach * normals[order]
        return [int(i) for i in order[farthest_point_indices(approach, min(n, len(order)))]]

    def _rehearsed_first(self, order: np.ndarray, points: np.ndarray, normals: np.ndarray, owner: np.ndarray,
                         last_resort: Sequence[int] = ()) -> np.ndarray:
        """The ranked candidates with the first one that holds cleanly in a rehearsal on the twin moved to the front.

        Rehearsed in turn (``CellTwin.rehearse``, the env's whole attempt on a copy of the pile), at most
        ``rehearsals``: the chosen pick, the best candidate of each other parcel in rank order, then candidates
        spread over the approaches offered (as ``_reachable_first``'s last pass); those the cell's plan refuses
        (``CellTwin.refusal``, no dynamics) are passed over and do not count (in the 30-parcel heap most other
        parcels' best candidates are refused, and spent the rehearsals). The oracle's pick-geometry
        model cannot see a neighbour's drag, which decides the lift of a covered parcel in a stacked pile (the
        torsion drops of every stacked cell); the twin simulates it. A success is taken at once where no ring
        ratio ever passed ``clean_peak``; one that outlived a brief violation (shorter than the cup's
        ``violation_time``) is marginal, and in the heap the env dropped such picks where the twin had held them,
        so the rehearsals go on, and the least loaded success is taken if none is clean. A success on the shadow that
        knocks a parcel out of the tote (R_object charges it: 5 parcels of the heap's 1,200) is not clean either;
        one that loses fewer goes first. Where none succeeds, the ``last_resort`` candidates (outside the ranking)
        are rehearsed the same way, at most ``last_resort_rehearsals``, and one that succeeds goes first. Where
        none does, the ranking stands."""
        c = self.config
        if c.rehearsals == 0 or len(order) == 0:
            return order
        others = self._each_parcels_best(order, owner, {int(owner[order[0]])})
        spread = self._spread(order, points, normals, c.rehearsals)
        chosen = self._rehearse_in_turn([int(order[0]), *others, *spread], points, normals, c.rehearsals, True)
        if chosen is None and c.last_resort_rehearsals:
            chosen = self._rehearse_in_turn(list(last_resort), points, normals, c.last_resort_rehearsals, False)
        return order if chosen is None else np.concatenate([[chosen], order[order != chosen]])

    def _rehearse_in_turn(self, queue: Sequence[int], points: np.ndarray, normals: np.ndarray, limit: int,
                          first_regardless: bool) -> int | None:
        """``_rehearsed_first``'s pass over ``queue``: each candidate the cell's plan accepts (the first whatever,
        where ``first_regardless``: it is the fallback) rehearsed until one succeeds cleanly or ``limit`` were;
        the best success (most jittered twins held, fewest parcels lost, least loaded), or None. Sets
        ``last_fragile``."""
        c = self.config
        jitter = PoseJitter(self._jitter_rng, c.jitter_position, c.jitter_angle_deg)
        chosen, best, count = None, (-1, 0, -np.inf), 0  # (jittered twins held, -parcels lost, -peak) of the best
        for n, i in enumerate(dict.fromkeys(queue)):
            if (n > 0 or not first_regardless) and self.twin.refusal(points[i], normals[i]) is not None:
                continue  # the cell would not move for it
            result, lost = self._rehearse(points[i], normals[i])
            self._rehearsed.append(i)
            self.last_rehearsals.append(result.outcome)
            self.last_nearest = min(self.last_nearest, max(result.peak_ratios.values(), default=np.inf))
            count += 1
            if result.outcome == "success":
                peak = max(result.peak_ratios.values(), default=0.0)
                clean = peak <= c.clean_peak
                held = c.confirmations
                if c.confirmations and not (clean and len(self.last_rehearsals) == 1):
                    held = sum(self.twin.rehearse(points[i], normals[i], jitter).outcome == "success"
                               for _ in range(c.confirmations))
                    self.last_confirmations.append(held)
                if (held, -lost, -peak) > best:
                    chosen, best = i, (held, -lost, -peak)
                if clean and held == c.confirmations and lost == 0:
                    break
            if count == limit:
                break
        self.last_fragile = chosen is not None and best[0] < c.confirmations
        self.last_lossy = chosen is not None and best[1] < 0
        return chosen

    def _last_resort(self, order: np.ndarray, owner: np.ndarray, grasp: PhysicalGrasp) -> list[int]:
        """Candidates outside ``order`` that seal (``seal_floor``) with the tool clear, but that the hold model
        rejects: the least loaded (``PhysicalGrasp.worst``) of every parcel, then every parcel's second, and so on;
        at most ``spread_checks`` (each is asked of the cell's plan before it is rehearsed)."""
        pool = np.setdiff1d(np.flatnonzero((grasp.seal >= self.config.seal_floor) & (grasp.collision > 0)), order)
        pool = pool[np.argsort(grasp.worst[pool], kind="stable")]
        parcels = owner[pool]
        grouped = np.argsort(parcels, kind="stable")  # each parcel's candidates together, least loaded first
        starts = np.r_[0, np.flatnonzero(np.diff(parcels[grouped])) + 1]
        place = np.empty(len(pool), dtype=np.int64)  # each candidate's place among its parcel's
        place[grouped] = np.arange(len(pool)) - np.repeat(starts, np.diff(np.r_[starts, len(pool)]))
        return [int(i) for i in pool[np.lexsort((np.arange(len(pool)), place))][:self.config.spread_checks]]

    def _rehearse(self, point: np.ndarray, normal: np.ndarray) -> tuple[PickResult, int]:
        """The pick as the cell runs it, and the parcels it knocks out of the tote: on the shadow where this decision
        is exact, else on the posed twin (which does not settle the pile after the pick, so it counts none)."""
        if self._exact:
            rehearsed = self.shadow.rehearse(point, normal)
            if rehearsed is not None:
                return rehearsed
            self._exact = self.last_exact = False  # its child failed: the twin from here on
        return self.twin.rehearse(point, normal), 0

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

    def _rank(self, points: np.ndarray, normals: np.ndarray, owner: np.ndarray, grasp: PhysicalGrasp,
              truth: GroundTruth, scorer: SuctionScorer, max_face_tilt_deg: float | None = None) -> np.ndarray:
        """Indices of the admissible candidates: free parcels before pinned ones (``pinned_parcels``; a
        parcel dropped back onto another must come off it first, even though its pick failed), parcels not
        yet tried before tried ones, approaches not yet failed before failed ones (a point within
        ``retry_radius`` and ``retry_angle_deg`` of a failed pick), parcels not leaned on (``leaned_on``)
        first, robust seals before marginal ones (within ``seal_margin`` of the threshold, or below it with the
        lip ``seal_standoff`` further out); then sound picks (seal at least ``min_seal``, ring ratios
        within the carry's load target) before weaker ones, level candidates before tilted ones, highest
        parcels first, central ones first, among a parcel's marginal candidates the best seal backed off first,
        and small lever arms first."""
        c = self.config
        admissible = self._admissible(grasp, normals, max_face_tilt_deg)
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
        for index, com in self.failed.tags:  # the parcels whose pick failed
            tried += (indices == index) if index >= 0 else (np.linalg.norm(truth.coms - com, axis=1) < c.retry_radius)
        # approaches that already failed
        repeated = self.failed.count_near(points[admissible], c.retry_radius, normals[admissible], c.retry_angle_deg)
        contacts = hull_contacts(truth)
        pinned = pinned_parcels(truth, contacts)
        leaned = leaned_on(truth, contacts)
        sound = (grasp.seal[admissible] >= c.min_seal) & (grasp.worst[admissible] <= self.load_target)
        # the seal with the lip seal_standoff further out than its seat: what the last millimetre is worth
        backed_off = scorer.contact_seal(grasp.seats[admissible] + c.seal_standoff * normals[admissible],
                                         -normals[admissible], parcels).quality
        marginal = (grasp.seal[admissible] < c.seal_floor + c.seal_margin) | (backed_off < c.seal_floor)
        # among a parcel's last-resort candidates, the one whose seal depends least on the last millimetre first
        fragile = np.where(marginal, -backed_off, 0.0)
        # np.lexsort sorts by the last key first
        return admissible[np.lexsort((lever, fragile, centrality[parcels], -tier[parcels], ~level, ~sound, marginal,
                                      leaned[parcels], repeated, tried[parcels], pinned[parcels]))]
