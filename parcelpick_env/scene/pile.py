"""Building a settled pile of parcels in a bin, deterministically from a seed (docs/piles.md).

``stacked`` works like a parcel induction chute: temporary chute walls continue the bin's inner
walls up to ``PileConfig.chute_height`` (or higher, to clear the start slots) and every parcel
starts inside them, lying on a face with a random yaw and a random tumble (``stack_tilt_deg``), in
a slot chosen greedily as the lowest of ``STACK_CANDIDATES`` random spots where its rotated bounding
box overlaps no earlier one. A wave (``WAVE_SIZE`` parcels at most; larger requests come in equal
waves) is released together, so the lower ones land first and the upper ones fall onto them. Once
the last wave has settled the chute is taken away and the pile settles again under the nominal
solver: parcels heaped above the rim may slide out then; they are removed and counted as ``lost``.

``scattered`` lays parcels flat-side down (mostly) on the bin floor without footprint overlap, about
square to the walls (``scatter_yaw_jitter_deg``), largest footprint first. Each footprint (the
convex hull of the rotated mesh, projected on the floor) may go anywhere in the region where it
fits, computed exactly as the inner floor minus the Minkowski sums of the footprints already placed
(no rejection sampling: a spot is found whenever one exists for the yaw; the yaw turned 90 degrees
and square yaws are tried next). It takes the corner of that region nearest a randomly chosen bin
corner, so it lies against walls or neighbours and the free floor stays in one piece. Up to
``SCATTER_CAPACITY`` parcels always fit the default tote (tested); beyond it a parcel that finds no
room is ``skipped``: the shortfall is reported in ``scene.meta`` and the env's ``info``.

A stacked tote holds about 0.6 of its volume in convex hulls (0.57-0.67 measured), however full the
request: what is asked beyond that heaps above the rim and slides out (docs/piles.md, 'How full a tote
can be'). ``scene.meta['hull_fill']`` is the request's hull volume over the tote's (``hull_fill``); above
``STACKED_FILL_CAPACITY`` a stacked request is built as asked, with a warning that parcels will be lost.

In both layouts the world is stepped until the pile stops moving (``_settle_culling``), parcels whose
centre of mass ends outside the bin (``BinSpec.contains``, the one definition) are removed, and the
returned ``Scene`` holds mesh-frame poses with ``object_id == index``. ``scene.meta`` reports
``requested = placed + skipped + lost``. The chute phase runs with ``DROP_SOLVER_ITERATIONS`` solver
iterations (10 never came to rest: the heap jitters); the nominal settings are restored for the
final settle, so the returned pile rests under the simulator's own physics.
"""

from __future__ import annotations

import logging
from typing import Sequence

import numpy as np
import pybullet as pb
import shapely
from scipy.spatial.transform import Rotation

from parcelpick_env.assets.library import AssetLibrary
from parcelpick_env.assets.parcel import ParcelAsset
from parcelpick_env.scene.config import PileConfig
from parcelpick_env.scene.scene import BinSpec, ParcelState, Scene
from parcelpick_env.sim.simulator import Simulator

DROP_SOLVER_ITERATIONS = 30  # solver iterations while the pile falls; fewer jitter and never come to rest
DROP_TIME = 1.5  # s of simulated time the chute phase may take at most (parcels fall ~1 m in 0.45 s)
SETTLE_TIME = 2.0  # s the pile may take to settle once the chute is gone (and for a scattered layout)
STACK_CANDIDATES = 64  # start spots tried per stacked parcel; the lowest wins (a dense, low start)
WAVE_SIZE = 20  # stacked parcels per wave at most: larger requests come in equal waves, each settling on the last
STACK_JITTER = 0.01  # m: start heights this close count as equally low
SCATTER_CAPACITY = 6  # scattered parcels that always fit the default tote, any object set (docs/piles.md)
# a parcel rests on a side only if it would not topple: tipping angle atan(narrowest base / height) at least
# this (a 0.47 g nudge, the order of an infeed drop's or a conveyor transfer's lateral jolt); envelopes and
# mailers on their edges and long tubes on their ends lie flat instead. At 15 deg (0.27 g) a 36 mm mailer
# stood on its edge against a wall, offering the cup only its edge and the tool only the wall (the oracle's
# last 3 attempts in 3 of 40 episodes of the 5-episode grid)
SIDE_TIP_ANGLE_DEG = 25.0
# the hull fill (``hull_fill``) up to which a stacked request keeps at least 95% of its parcels, measured over
# every object set and both asset splits at 30, 40 and 50 parcels (docs/piles.md, 'How full a tote can be');
# fuller requests keep hulls of 0.57-0.67 of the tote's volume and lose the rest
STACKED_FILL_CAPACITY = 0.55
SCATTER_YAW_STEPS = np.array([0.0, np.pi / 2])  # scattered: the drawn yaw, turned 90 deg, then square to the walls


log = logging.getLogger(__name__)
_WARNED = {"overfull": False}


def hull_fill(assets: Sequence[ParcelAsset], spec: BinSpec) -> float:
    """The parcels' convex-hull volume over the tote's inner volume: how full a request asks the tote to be."""
    return float(sum(asset.mesh.convex_hull.volume for asset in assets)) / spec.volume


def _choose_assets(pool: Sequence[ParcelAsset], n: int, rng: np.random.Generator) -> list[ParcelAsset]:
    """Draw ``n`` assets, cycling through random permutations so repeats come as late as possible."""
    order: list[int] = []
    while len(order) < n:
        order.extend(rng.permutation(len(pool)).tolist())
    return [pool[i] for i in order[:n]]


def _heavy_first(assets: list[ParcelAsset], frictions: np.ndarray, mass: float
                 ) -> tuple[list[ParcelAsset], np.ndarray]:
    """Parcels heavier than ``mass`` first, each class in its drawn order (a stable partition): they land on
    the floor, not askew on lighter ones, where no top-down cup holds them (docs/piles.md)."""
    order = np.argsort([asset.mass <= mass for asset in assets], kind="stable")
    return [assets[i] for i in order], frictions[order]


def _chute_orientations(assets: list[ParcelAsset], cfg: PileConfig, rng: np.random.Generator) -> np.ndarray:
    """Parcels come off an infeed conveyor on a face (mostly the largest, never a side they would topple
    from: ``_flat_tilt``) and tumble a little down the chute: random yaw, then a tilt about a random
    horizontal axis of ``stack_tilt_deg`` (std)."""
    n = len(assets)
    tilts = [_flat_tilt(cfg, rng, asset.extents) for asset in assets]
    yaws = rng.uniform(0, 2 * np.pi, size=n)
    heading = rng.uniform(0, 2 * np.pi, size=n)
    angle = np.radians(cfg.stack_tilt_deg) * rng.normal(size=n)
    tumble = Rotation.from_rotvec(np.stack([np.cos(heading), np.sin(heading), np.zeros(n)], 1) * angle[:, None])
    quats = (tumble * Rotation.from_euler("z", yaws[:, None]) * Rotation.concatenate(tilts)).as_quat()
    return quats * np.where(quats[:, 3:4] < 0, -1.0, 1.0)


def _inner_bounds(spec: BinSpec) -> tuple[np.ndarray, np.ndarray]:
    half = np.asarray(spec.inner_size) / 2
    centre = np.asarray(spec.center_xy, dtype=np.float64)
    return centre - half, centre + half


def _stacked_poses(assets: list[ParcelAsset], cfg: PileConfig, rng: np.random.Generator,
                   occupied: Sequence[tuple[np.ndarray, np.ndarray]] = ()):
    """Start poses inside the chute: tumbled orientations, non-overlapping world AABBs, lowest of many
    spots. ``occupied`` holds the world AABBs (lo, hi) of the pile already in the bin."""
    spec = cfg.bin
    lo, hi = _inner_bounds(spec)
    quats = _chute_orientations(assets, cfg, rng)
    boxes_lo: list[np.ndarray] = [np.asarray(b[0], dtype=np.float64) for b in occupied]
    boxes_hi: list[np.ndarray] = [np.asarray(b[1], dtype=np.float64) for b in occupied]
    positions = []
    for asset, q in zip(assets, quats):
        pts = Rotation.from_quat(q).apply(asset.mesh.convex_hull.vertices)
        rlo, rhi = pts.min(0), pts.max(0)
        # Every parcel fits the chute in some orientation; in this one it may not, then it is centred
        # and starts above the rim (it falls in once it turns).
        fits = np.all(rhi[:2] - rlo[:2] < hi - lo)
        xy_lo = lo - rlo[:2] if fits else (lo + hi) / 2 - (rlo[:2] + rhi[:2]) / 2
        xy_hi = hi - rhi[:2] if fits else xy_lo
        candidates = rng.uniform(xy_lo, xy_hi, size=(STACK_CANDIDATES, 2))
        z = np.full(len(candidates), spec.floor_z - rlo[2])
        if boxes_lo:
            blo, bhi = np.asarray(boxes_lo), np.asarray(boxes_hi)
            c_lo = candidates[:, None, :] + rlo[:2]
            c_hi = candidates[:, None, :] + rhi[:2]
            overlap = np.all((c_lo < bhi[None, :, :2]) & (c_hi > blo[None, :, :2]), axis=2)
            tops = np.where(overlap, bhi[None, :, 2], -np.inf).max(axis=1)
            z = np.maximum(z, tops - rlo[2])
        best = int(np.argmin(z + STACK_JITTER * rng.random(len(z))))  # lowest, ties broken at random
        position = np.array([candidates[best, 0], candidates[best, 1], z[best] + cfg.drop_height])
        positions.append(position)
        boxes_lo.append(position + rlo)
        boxes_hi.append(position + rhi)
    return np.asarray(positions), quats


def _flat_tilt(cfg: PileConfig, rng: np.random.Generator, extents: np.ndarray | None = None) -> Rotation:
    """Largest face down (body z is the thin axis by construction) unless the dice say otherwise.

    With the parcel's body ``extents``, a side it could not stand on is refused (it lies flat): one whose
    tipping angle, atan(narrowest base side / height), is under ``SIDE_TIP_ANGLE_DEG``. Such a parcel (an
    envelope on its edge, a long thin tube on its end) topples at the first nudge of a real infeed.
    """
    if rng.random() < cfg.scatter_flat_prob:
        return Rotation.identity()
    # rest on a side: turn the long (x) or middle (y) axis upright... or a cylinder on its end
    upright = 0 if rng.random() < 0.5 else 1
    if extents is not None:
        e = np.asarray(extents, dtype=np.float64)
        base = np.delete(e, upright)
        if np.degrees(np.arctan2(base.min(), e[upright])) < SIDE_TIP_ANGLE_DEG:
            return Rotation.identity()
    return Rotation.from_euler("y" if upright == 0 else "x", np.pi / 2)


def _free_region(footprint: np.ndarray, placed: list[np.ndarray], lo: np.ndarray, hi: np.ndarray,
                 gap: float) -> shapely.Geometry:
    """Where the footprint's origin may go: inside the walls (``gap`` clear) and ``gap`` clear of every
    placed footprint. Each obstacle grows by the mirrored footprint (Minkowski sum of convex hulls)."""
    fmin, fmax = footprint.min(0), footprint.max(0)
    box = shapely.box(*(lo - fmin + gap / 2), *(hi - fmax - gap / 2))
    if box.is_empty or not box.is_valid:
        return shapely.Polygon()
    if not placed:
        return box
    grown = [shapely.convex_hull(shapely.multipoints((obstacle[:, None, :] - footprint[None]).reshape(-1, 2)))
             .buffer(gap, quad_segs=2) for obstacle in placed]
    return box.difference(shapely.union_all(grown))


def _scattered_poses(assets: list[ParcelAsset], cfg: PileConfig, rng: np.random.Generator):
    """Non-overlapping flat placements, largest footprint first; returns (kept indices, positions, quats)."""
    lo, hi = _inner_bounds(cfg.bin)
    tilts = [_flat_tilt(cfg, rng, asset.extents) for asset in assets]
    yaws = rng.integers(0, 4, size=len(assets)) * np.pi / 2 + np.radians(cfg.scatter_yaw_jitter_deg) * rng.uniform(
        -1, 1, len(assets))
    mirror = rng.choice([-1.0, 1.0], size=2)  # which corner of the bin the layout starts from
    hulls = [asset.mesh.convex_hull.vertices for asset in assets]
    areas = [shapely.convex_hull(shapely.multipoints(t.apply(h)[:, :2])).area for t, h in zip(tilts, hulls)]
    placed: list[np.ndarray] = []
    poses: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for i in np.argsort(areas, kind="stable")[::-1]:
        for yaw in np.concatenate([yaws[i] + SCATTER_YAW_STEPS, SCATTER_YAW_STEPS]):  # drawn, then square
            rot = Rotation.from_euler("z", yaw) * tilts[i]
            rotated = rot.apply(hulls[i])
            footprint = rotated[:, :2]
            free = _free_region(footprint, placed, lo, hi, cfg.scatter_gap)
            if free.is_empty:
                continue
            # The free region's corner nearest the pile's start corner (lowest in y, then x, after the
            # mirror): the parcel lies against walls or neighbours, so the free floor stays in one piece.
            corners = shapely.get_coordinates(shapely.boundary(free))
            key = corners * mirror
            xy = corners[np.lexsort((key[:, 0], np.round(key[:, 1], 3)))[0]]
            placed.append(footprint + xy)
            poses[int(i)] = (np.array([xy[0], xy[1], cfg.bin.floor_z - rotated[:, 2].min() + 0.002]), rot.as_quat())
            break
    kept = sorted(poses)
    positions = np.asarray([poses[i][0] for i in kept]).reshape(-1, 3)
    quats = np.asarray([poses[i][1] for i in kept]).reshape(-1, 4)
    return kept, positions, quats


def _add_chute(sim: Simulator, spec: BinSpec, top: float) -> int:
    """Temporary chute walls: the bin's walls continued from the rim up to ``top`` above the floor."""
    t = spec.wall_thickness
    h = top - spec.wall_height
    sx, sy = spec.inner_size
    cx, cy = spec.center_xy
    zc = spec.floor_z + spec.wall_height + h / 2
    half = [[t / 2, sy / 2 + t, h / 2], [t / 2, sy / 2 + t, h / 2], [sx / 2, t / 2, h / 2], [sx / 2, t / 2, h / 2]]
    centres = [[cx - sx / 2 - t / 2, cy, zc], [cx + sx / 2 + t / 2, cy, zc],
               [cx, cy - sy / 2 - t / 2, zc], [cx, cy + sy / 2 + t / 2, zc]]
    col = pb.createCollisionShapeArray([pb.GEOM_BOX] * 4, halfExtents=half, collisionFramePositions=centres,
                                       physicsClientId=sim.client)
    body = pb.createMultiBody(0.0, col, -1, physicsClientId=sim.client)
    pb.changeDynamics(body, -1, lateralFriction=0.3, restitution=0.0, physicsClientId=sim.client)
    return body


def _settle_culling(sim: Simulator, live: dict[int, ParcelAsset], spec: BinSpec, cap: int,
                    solver_iterations: int | None = None) -> tuple[int, set[int], bool]:
    """Step until the pile stops moving, removing parcels that fell out of the bin (below the rim,
    outside the walls) as soon as they do, so it does not wait for them to roll on the ground.

    At rest is the simulator's one test (``Simulator.still`` over ``SimConfig.rest_window``). Bullet piles also
    creep by a few mm/s for seconds, so ``cap`` bounds the wait. Mutates ``live``; returns the steps
    taken, the removed bodies and whether it came to rest within ``cap`` steps.
    """
    with sim.physics_overrides(solver_iterations=solver_iterations):
        dt = sim.config.timestep
        chunk = sim.rest_steps(dt)
        fallen: set[int] = set()
        steps, rest = 0, False
        bodies = list(live)
        before = sim.com_poses(bodies)
        while steps < cap and live and not rest:
            n = min(chunk, cap - steps)
            sim.step(n)
            steps += n
            after = sim.com_poses(bodies)
            rest = bool(sim.still(before, after, chunk * dt).all())
            out = (after[0][:, 2] < spec.floor_z + spec.wall_height) & ~spec.contains(after[0])
            if out.any():
                for body in np.asarray(bodies)[out].tolist():
                    sim.remove(body)
                    fallen.add(body)
                    del live[body]
                rest = False
                bodies = list(live)
                after = (after[0][~out], after[1][~out])
            before = after
    return steps, fallen, rest or not live


def build_pile(sim: Simulator, config: PileConfig, seed: int, library: AssetLibrary | None = None) -> Scene:
    """Reset ``sim`` and build a settled pile; same (config, seed, library) -> bitwise-identical poses."""
    if not isinstance(config, PileConfig):
        raise TypeError(f"config must be a PileConfig, got {type(config).__name__}")
    library = library or AssetLibrary.default()
    pool = library.assets(config.split, config.object_set)
    if not pool:
        raise ValueError(f"the library has no {config.split!r} assets in object set {config.object_set!r}")
    spec = config.bin
    rng = np.random.default_rng(int(seed))
    assets = _choose_assets(pool, config.num_parcels, rng)
    frictions = rng.uniform(*config.friction_range, size=len(assets))
    fill = hull_fill(assets, spec)
    if config.layout == "stacked" and fill > STACKED_FILL_CAPACITY and not _WARNED["overfull"]:
        _WARNED["overfull"] = True  # once a process: a dataset run draws many such requests
        log.warning("a stacked request of %d %s parcels asks for %.0f%% of the tote's %.1f L in convex hulls; a "
                    "stacked tote keeps about 60%%, so expect parcels lost (scene.meta['lost'], docs/piles.md)",
                    len(assets), config.object_set, 100 * fill, 1000 * spec.volume)
    if config.layout == "stacked" and config.heavy_first_mass is not None:
        assets, frictions = _heavy_first(assets, frictions, config.heavy_first_mass)
    limit = config.max_settle_steps or sim.config.max_settle_steps
    drop_iterations = min(DROP_SOLVER_ITERATIONS, sim.config.solver_iterations)
    drop_cap = min(limit, int(round(DROP_TIME / sim.config.timestep)))
    settle_cap = min(limit, int(round(SETTLE_TIME / sim.config.timestep)))
    sim.reset()
    sim.add_bin(spec)
    body_of: dict[int, int] = {}
    live: dict[int, ParcelAsset] = {}
    steps, fallen = 0, set[int]()
    if config.layout == "stacked":  # waves through the chute, then take it away
        waves = np.array_split(np.arange(len(assets)), -(-len(assets) // WAVE_SIZE))
        for wave in waves:
            occupied = [sim.aabb(b) for b in live]
            positions, quats = _stacked_poses([assets[i] for i in wave], config, rng, occupied)
            for k, i in enumerate(wave.tolist()):
                body_of[i] = sim.add_parcel(assets[i], positions[k], quats[k], frictions[i])
                live[body_of[i]] = assets[i]
            top = max(config.chute_height, float(max(sim.aabb(b)[1][2] for b in live)) - spec.floor_z)
            chute = _add_chute(sim, spec, spec.floor_z + top)
            more, out, _ = _settle_culling(sim, live, spec, drop_cap, drop_iterations)
            steps, fallen = steps + more, fallen | out
            sim.remove(chute)
        skipped = 0
    else:
        kept, positions, quats = _scattered_poses(assets, config, rng)
        for k, i in enumerate(kept):
            body_of[i] = sim.add_parcel(assets[i], positions[k], quats[k], frictions[i])
            live[body_of[i]] = assets[i]
        skipped = len(assets) - len(kept)
    more, out, at_rest = _settle_culling(sim, live, spec, settle_cap)
    steps, fallen = steps + more, fallen | out

    bodies = list(live)
    inside = spec.contains(sim.com_poses(bodies)[0]) if bodies else np.zeros(0, bool)
    held = {b for b, ok in zip(bodies, inside) if ok}
    parcels: list[ParcelState] = []
    lost: list[str] = []
    for i, body in body_of.items():
        if body not in held:
            lost.append(assets[i].asset_id)
            if sim.has_body(body):
                sim.remove(body)
            continue
        pos, orn = sim.body_pose(body)
        parcels.append(ParcelState(object_id=len(parcels), body_id=body, asset=assets[i],
                                   position=pos, orientation=orn, friction=float(frictions[i])))
    meta = {
        "requested": config.num_parcels,
        "placed": len(parcels),
        "skipped": skipped,
        "lost": len(lost),
        "lost_assets": lost,
        "hull_fill": fill,
        "settle_steps": steps,
        "at_rest": at_rest,
    }
    return Scene(parcels=parcels, bin=spec, seed=int(seed), layout=config.layout,
                 object_set=config.object_set, split=config.split, meta=meta)


def refresh_scene_poses(sim: Simulator, scene: Scene) -> None:
    """Re-read every parcel's mesh-frame pose from the simulator (after the env moved things)."""
    for parcel in scene.parcels:
        if not sim.has_body(parcel.body_id):
            raise ValueError(f"parcel {parcel.object_id} (body {parcel.body_id}) is no longer in the simulator; "
                             "drop removed parcels from the scene before refreshing")
        parcel.position, parcel.orientation = sim.body_pose(parcel.body_id)
