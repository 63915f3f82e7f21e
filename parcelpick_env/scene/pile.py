"""Building a settled pile of parcels in a bin, deterministically from a seed.

``stacked``: every parcel gets a uniformly random orientation and a start slot above the bin,
chosen greedily as the lowest of a few random spots where its rotated bounding box overlaps no
earlier one (nor the walls). All are released together from ``drop_height`` above their slots,
so the lower ones land first and the upper ones fall onto them: a pile, without the cost of
settling wave after wave. Parcels that bounce out are dropped again onto the settled pile
(``PileConfig.redrop_rounds`` waves), which keeps most of a full bin's parcels.

``scattered``: parcels are laid flat-side down (mostly) with random yaw, placed by rejection
sampling so their footprints (convex hulls of the rotated mesh projected on the floor) do not
overlap, then settled. Parcels that cannot be fitted are skipped and counted in
``scene.meta['skipped']``.

In both layouts the world is stepped until motion stops (``Simulator.settle``), parcels that end
outside the bin are removed, and the returned ``Scene`` holds mesh-frame poses with
``object_id == index``. For speed the drop runs with ``DROP_SOLVER_ITERATIONS`` solver iterations
(a doubled timestep was tried too: more jitter, no net gain); the nominal settings are restored
for a final settle, so the returned pile is at rest under the simulator's own physics. Parcels
that fall out are removed as soon as they are below the rim and outside the walls, so the
settle does not wait for them to stop rolling on the ground.
"""

from __future__ import annotations

import numpy as np
import shapely
import shapely.affinity
from scipy.spatial.transform import Rotation

from parcelpick_env.assets.library import AssetLibrary
from parcelpick_env.assets.parcel import ParcelAsset
from parcelpick_env.scene.config import PileConfig
from parcelpick_env.scene.scene import BinSpec, ParcelState, Scene
from parcelpick_env.sim.simulator import Simulator

DROP_SOLVER_ITERATIONS = 10  # solver iterations while the pile falls; nominal ones settle it last
STACK_CANDIDATES = 8  # start spots tried per stacked parcel; the lowest wins (a wide, low pile)
OUTSIDE_TOLERANCE = 0.005  # m: a COM this far beyond the inner walls counts as outside the bin


def _choose_assets(pool: list[ParcelAsset], n: int, rng: np.random.Generator) -> list[ParcelAsset]:
    """Draw ``n`` assets, cycling through random permutations so repeats come as late as possible."""
    order: list[int] = []
    while len(order) < n:
        order.extend(rng.permutation(len(pool)).tolist())
    return [pool[i] for i in order[:n]]


def _random_quaternions(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q * np.where(q[:, 3:4] < 0, -1.0, 1.0)


def _inner_bounds(spec: BinSpec) -> tuple[np.ndarray, np.ndarray]:
    half = np.asarray(spec.inner_size) / 2
    centre = np.asarray(spec.center_xy, dtype=np.float64)
    return centre - half, centre + half


def _stacked_poses(assets: list[ParcelAsset], cfg: PileConfig, rng: np.random.Generator,
                   occupied: list[tuple[np.ndarray, np.ndarray]] = ()):
    """Start poses: random orientations, stacked as non-overlapping world AABBs, lowest of a few spots.

    ``occupied`` holds world AABBs (lo, hi) already in the bin, e.g. a settled pile to drop onto.
    """
    spec = cfg.bin
    lo, hi = _inner_bounds(spec)
    quats = _random_quaternions(rng, len(assets))
    boxes_lo: list[np.ndarray] = [np.asarray(lo_, dtype=np.float64) for lo_, _ in occupied]  # world AABBs
    boxes_hi: list[np.ndarray] = [np.asarray(hi_, dtype=np.float64) for _, hi_ in occupied]
    positions = []
    for asset, q in zip(assets, quats):
        pts = Rotation.from_quat(q).apply(asset.mesh.convex_hull.vertices)
        rlo, rhi = pts.min(0), pts.max(0)
        # xy so the AABB stays inside the walls when it fits, else centred over the bin.
        xy_lo = np.where(rhi[:2] - rlo[:2] < hi - lo, lo - rlo[:2], (lo + hi) / 2 - (rlo[:2] + rhi[:2]) / 2)
        xy_hi = np.where(rhi[:2] - rlo[:2] < hi - lo, hi - rhi[:2], xy_lo)
        candidates = rng.uniform(xy_lo, xy_hi, size=(STACK_CANDIDATES, 2))
        fits = np.all(rhi[:2] - rlo[:2] < hi - lo)
        base = spec.floor_z if fits else spec.floor_z + spec.wall_height
        z = np.full(STACK_CANDIDATES, base - rlo[2])
        if boxes_lo:
            blo, bhi = np.asarray(boxes_lo), np.asarray(boxes_hi)
            c_lo = candidates[:, None, :] + rlo[:2]
            c_hi = candidates[:, None, :] + rhi[:2]
            overlap = np.all((c_lo < bhi[None, :, :2]) & (c_hi > blo[None, :, :2]), axis=2)
            tops = np.where(overlap, bhi[None, :, 2], -np.inf).max(axis=1)
            z = np.maximum(z, tops - rlo[2])
        best = int(np.argmin(z))
        position = np.array([candidates[best, 0], candidates[best, 1], z[best] + cfg.drop_height])
        positions.append(position)
        boxes_lo.append(position + rlo)
        boxes_hi.append(position + rhi)
    return np.asarray(positions), quats


def _flat_orientation(asset: ParcelAsset, cfg: PileConfig, rng: np.random.Generator) -> np.ndarray:
    """Largest face down (body z is the thin axis by construction) unless the dice say otherwise."""
    if rng.random() < cfg.scatter_flat_prob:
        tilt = Rotation.identity()
    else:  # rest on a side: turn the long (x) or middle (y) axis upright... or a cylinder on its end
        tilt = Rotation.from_euler("y" if rng.random() < 0.5 else "x", np.pi / 2)
    yaw = Rotation.from_euler("z", rng.uniform(0, 2 * np.pi))
    return (yaw * tilt).as_quat()


def _scattered_poses(assets: list[ParcelAsset], cfg: PileConfig, rng: np.random.Generator):
    """Non-overlapping flat placements; returns (kept asset indices, positions, quaternions)."""
    spec = cfg.bin
    lo, hi = _inner_bounds(spec)
    placed: list[shapely.Geometry] = []
    kept, positions, quats = [], [], []
    for i, asset in enumerate(assets):
        q = _flat_orientation(asset, cfg, rng)
        hull = asset.mesh.convex_hull.vertices
        rotated = Rotation.from_quat(q).apply(hull)
        footprint = shapely.convex_hull(shapely.multipoints(rotated[:, :2]))
        fmin, fmax = rotated[:, :2].min(0), rotated[:, :2].max(0)
        xlo, xhi = lo - fmin + cfg.scatter_gap / 2, hi - fmax - cfg.scatter_gap / 2
        if np.any(xlo > xhi):
            continue  # larger than the bin floor in this orientation
        tries = rng.uniform(xlo, xhi, size=(cfg.scatter_attempts, 2))
        for xy in tries:
            candidate = shapely.affinity.translate(footprint, xy[0], xy[1])
            if not any(candidate.distance(other) < cfg.scatter_gap for other in placed):
                placed.append(candidate)
                kept.append(i)
                positions.append([xy[0], xy[1], spec.floor_z - rotated[:, 2].min() + 0.002])
                quats.append(q)
                break
    return kept, np.asarray(positions).reshape(-1, 3), np.asarray(quats).reshape(-1, 4)


def _inside_bin(sim: Simulator, body_id: int, asset: ParcelAsset, spec: BinSpec) -> bool:
    pos, orn = sim.body_pose(body_id)
    com = Rotation.from_quat(orn).apply(asset.com) + pos
    lo, hi = _inner_bounds(spec)
    tol = OUTSIDE_TOLERANCE
    return bool(np.all(com[:2] > lo - tol) and np.all(com[:2] < hi + tol) and com[2] > spec.floor_z - tol)


def _fallen_out(sim: Simulator, body_id: int, asset: ParcelAsset, spec: BinSpec) -> bool:
    """Below the rim and outside the walls: it can never come back into the bin."""
    pos, orn = sim.body_pose(body_id)
    com = Rotation.from_quat(orn).apply(asset.com) + pos
    return com[2] < spec.floor_z + spec.wall_height and not _inside_bin(sim, body_id, asset, spec)


def _settle_culling(sim: Simulator, bodies: list[int], assets: list[ParcelAsset],
                    config: PileConfig) -> tuple[int, set[int]]:
    """Settle, removing parcels that fell out of the bin as soon as they do (they would only roll on).

    The drop phase runs with fewer solver iterations; a final phase at the nominal count follows.
    Returns the steps taken and the removed bodies.
    """
    cap = config.max_settle_steps or sim.config.max_settle_steps
    chunk = 8 * sim.config.check_interval
    live = dict(zip(bodies, assets))
    fallen: set[int] = set()
    steps = 0
    drop = dict(solver_iterations=min(DROP_SOLVER_ITERATIONS, sim.config.solver_iterations))
    for overrides in (drop, {}):
        with sim.physics_overrides(**overrides):
            phase = 0
            while phase < cap:
                n = sim.settle(list(live), max_steps=min(chunk, cap - phase))
                phase += n
                for body, asset in list(live.items()):
                    if _fallen_out(sim, body, asset, config.bin):
                        sim.remove(body)
                        fallen.add(body)
                        del live[body]
                if n < chunk or not live:
                    break
        steps += phase
    return steps, fallen


def build_pile(sim: Simulator, config: PileConfig, seed: int, library: AssetLibrary | None = None) -> Scene:
    """Reset ``sim`` and build a settled pile; same (config, seed, library) -> bitwise-identical poses."""
    if not isinstance(config, PileConfig):
        raise TypeError(f"config must be a PileConfig, got {type(config).__name__}")
    library = library or AssetLibrary.default()
    pool = library.assets(config.split, config.object_set)
    if not pool:
        raise ValueError(f"the library has no {config.split!r} assets in object set {config.object_set!r}")
    rng = np.random.default_rng(int(seed))
    assets = _choose_assets(pool, config.num_parcels, rng)
    frictions = rng.uniform(*config.friction_range, size=len(assets))
    if config.layout == "stacked":
        positions, quats = _stacked_poses(assets, config, rng)
        kept = list(range(len(assets)))
    else:
        kept, positions, quats = _scattered_poses(assets, config, rng)

    sim.reset()
    sim.add_bin(config.bin)
    body_of: dict[int, int] = {i: sim.add_parcel(assets[i], positions[k], quats[k], frictions[i])
                               for k, i in enumerate(kept)}
    steps, fallen = _settle_culling(sim, list(body_of.values()), [assets[i] for i in body_of], config)
    redropped = 0
    for _ in range(config.redrop_rounds if config.layout == "stacked" else 0):
        lost = [i for i, body in body_of.items() if body in fallen]
        if not lost:
            break
        # Drop the parcels that fell out again, onto the pile as it now lies.
        occupied = [sim.aabb(body) for body in body_of.values() if body not in fallen]
        re_pos, re_quats = _stacked_poses([assets[i] for i in lost], config, rng, occupied)
        for k, i in enumerate(lost):
            body_of[i] = sim.add_parcel(assets[i], re_pos[k], re_quats[k], frictions[i])
        redropped += len(lost)
        more, fallen = _settle_culling(sim, list(body_of.values()), [assets[i] for i in body_of], config)
        steps += more
    at_rest = sim.is_at_rest([b for b in body_of.values() if b not in fallen])

    parcels: list[ParcelState] = []
    removed: list[str] = []
    for i, body in body_of.items():
        if body in fallen or not _inside_bin(sim, body, assets[i], config.bin):
            removed.append(assets[i].asset_id)
            if sim.has_body(body):
                sim.remove(body)
            continue
        pos, orn = sim.body_pose(body)
        parcels.append(ParcelState(object_id=len(parcels), body_id=body, asset=assets[i],
                                   position=pos, orientation=orn, friction=float(frictions[i])))
    meta = {
        "requested": config.num_parcels,
        "skipped": config.num_parcels - len(kept),
        "removed_outside": removed,
        "redropped": redropped,
        "settle_steps": steps,
        "at_rest": at_rest,
    }
    return Scene(parcels=parcels, bin=config.bin, seed=int(seed), layout=config.layout,
                 object_set=config.object_set, split=config.split, meta=meta)


def refresh_scene_poses(sim: Simulator, scene: Scene) -> None:
    """Re-read every parcel's mesh-frame pose from the simulator (after the env moved things)."""
    for parcel in scene.parcels:
        if not sim.has_body(parcel.body_id):
            raise ValueError(f"parcel {parcel.object_id} (body {parcel.body_id}) is no longer in the simulator; "
                             "drop removed parcels from the scene before refreshing")
        parcel.position, parcel.orientation = sim.body_pose(parcel.body_id)
