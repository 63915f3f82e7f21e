"""Procedural parcels in the paper's three shape clusters (docs/piles.md).

Every parcel starts from a watertight, evenly gridded primitive (a box with an ``nx x ny x nz``
grid on its faces, or a capped cylinder) whose vertices are then displaced by smooth fields:
dents and bulges for cartons, pillowing, wrinkles and bending for flat mailers. Smooth
displacements of a closed grid keep the surface closed, so every mesh stays watertight, and the
grid keeps triangles small enough for the suction scorer's ray casting to see the shape while
staying under ~3k faces. Colours live per face (base colour, a label patch, a tape strip) so the
simulator can render exactly what the scorer sees.
"""

from __future__ import annotations

import numpy as np
import trimesh

from parcelpick_env.assets.parcel import CATEGORIES, ParcelAsset, Split
from parcelpick_env.suction.config import CELL_CUP_RADIUS, SuctionConfig
from parcelpick_env.suction.cup import CARRY_LOAD_TARGET, CupSpec

# Two limits bound a parcel's mass (docs/piles.md, "Masses"). The arm: Kinova's Gen3 user guide rates 4 kg
# mid-range continuous without an end effector, and the suction tool (flange, rod, bellows cup, hose) is
# allowed 0.5 kg of it. The cup: its rated pull V = dP0 pi r^2 / S at a perfect seal, of which a parcel
# hanging still may use the carrying load share (CARRY_LOAD_TARGET), so the carry keeps the same margin.
GEN3_PAYLOAD = 4.0  # kg, mid-range continuous, no end effector
TOOL_ALLOWANCE = 0.5  # kg, the suction tool's share of the payload
CUP_MASS_LIMIT = CARRY_LOAD_TARGET * CupSpec().rated_force(CELL_CUP_RADIUS) / SuctionConfig().gravity  # 2.31 kg
MIN_MASS, MAX_MASS = 0.05, min(GEN3_PAYLOAD - TOOL_ALLOWANCE, CUP_MASS_LIMIT)  # kg, clipped after the density estimate

# Effective densities (kg/m^3) of a whole parcel including its air: most cartons are mostly empty, but small
# boxes also carry books, tools and tins, so the range reaches past water; with the smalls' sizes this keeps the
# heavy parcels that exercise the holding physics (docs/piles.md, 'Masses').
_DENSITY = {"rectangular": (120.0, 1200.0), "planar": (150.0, 600.0), "cylindrical": (150.0, 750.0)}


def _grid_box(counts: tuple[int, int, int]) -> trimesh.Trimesh:
    """A watertight cube [-1, 1]^3 whose faces carry a regular grid of ``counts`` cells per axis."""
    vertices, faces = [], []
    offset = 0
    for axis in range(3):
        u_ax, v_ax = [a for a in range(3) if a != axis]
        nu, nv = counts[u_ax], counts[v_ax]
        u, v = np.meshgrid(np.linspace(-1, 1, nu + 1), np.linspace(-1, 1, nv + 1), indexing="ij")
        idx = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
        a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
        for sign in (-1.0, 1.0):
            pts = np.zeros((u.size, 3))
            pts[:, u_ax], pts[:, v_ax], pts[:, axis] = u.ravel(), v.ravel(), sign
            quads = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
            # (u, v, axis) is right-handed for axis 0 and 2 and left-handed for axis 1.
            flip = (sign < 0) != (axis == 1)
            if flip:
                quads = quads[:, ::-1]
            vertices.append(pts)
            faces.append(quads + offset)
            offset += len(pts)
    mesh = trimesh.Trimesh(np.concatenate(vertices), np.concatenate(faces), process=False)
    mesh.merge_vertices(digits_vertex=9)
    return mesh


def _face_weight(q: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Per-vertex weight, 1 at a face centre and 0 on every box edge, so edges stay straight."""
    w = np.ones(len(q))
    for b in range(3):
        w = np.where(axis == b, w, w * np.clip(1.0 - q[:, b] ** 2, 0.0, 1.0))
    return w


def _smooth_field(uv: np.ndarray, rng: np.random.Generator, n_bumps: int, sigma: tuple[float, float]) -> np.ndarray:
    """A sum of Gaussian bumps with random signed amplitudes in [-1, 1] over 2-D coordinates in [-1, 1]."""
    centres = rng.uniform(-0.8, 0.8, size=(n_bumps, 2))
    sig = rng.uniform(*sigma, size=n_bumps)
    amp = rng.uniform(-1.0, 1.0, size=n_bumps)
    d2 = ((uv[:, None, :] - centres[None]) ** 2).sum(-1)
    return (amp * np.exp(-d2 / (2 * sig**2))).sum(-1)


# m: a smalls cell's cartons, sized so fifty stay inside the tote (docs/piles.md): 85% of sides from the
# triangular (min, mode, max), the rest uniform over the whole range
CARTON_SIDE_TRIANGLE = (0.05, 0.07, 0.14)
CARTON_SIDE_RANGE = (0.05, 0.18)


def _sample_carton_side(rng: np.random.Generator) -> float:
    """5-18 cm, most between 6 and 12 cm (peaked near 7 cm): the small cartons of a smalls induction
    cell sized for the Gen3 and a 0.70 x 0.45 m tote (docs/piles.md)."""
    lo, hi = CARTON_SIDE_RANGE
    return float(rng.triangular(*CARTON_SIDE_TRIANGLE) if rng.random() < 0.85 else rng.uniform(lo, hi))


def _rectangular(rng: np.random.Generator) -> trimesh.Trimesh:
    ext = np.sort([_sample_carton_side(rng) for _ in range(3)])[::-1]  # x >= y >= z: flat side on z
    half = ext / 2
    nx, ny, nz = (int(np.clip(round(e / 0.025), 4, 14)) for e in ext)
    mesh = _grid_box((nx, ny, nz))
    q = mesh.vertices.copy()
    axis = np.argmax(np.abs(q) * (1 + 1e-9 * np.arange(3)), axis=1)
    w = _face_weight(q, axis)
    disp = np.zeros(len(q))
    max_amp = min(0.012, 0.12 * half.min())
    for ax in range(3):
        for sign in (-1.0, 1.0):
            sel = (axis == ax) & (np.sign(q[:, ax]) == sign)
            uv = q[sel][:, [b for b in range(3) if b != ax]]
            bulge = rng.uniform(-0.3, 0.6)  # overall face bulge (+) or cave-in (-)
            dents = _smooth_field(uv, rng, int(rng.integers(0, 4)), (0.15, 0.4))
            disp[sel] = max_amp * (bulge + 0.7 * np.clip(dents, -1, 0.3))
    verts = q * half
    unit = np.zeros_like(verts)
    unit[np.arange(len(q)), axis] = np.sign(q[np.arange(len(q)), axis])
    verts += unit * (disp * w)[:, None]
    return trimesh.Trimesh(verts, mesh.faces, process=False)


PLANAR_LENGTH, PLANAR_WIDTH = (0.10, 0.26), (0.08, 0.18)  # m: envelope and mailer formats (docs/piles.md)


def _planar(rng: np.random.Generator) -> trimesh.Trimesh:
    kind = rng.choice(["envelope", "mailer", "polybag"])
    thickness = {"envelope": (0.005, 0.015), "mailer": (0.01, 0.03), "polybag": (0.02, 0.05)}[kind]
    t = float(rng.uniform(*thickness))
    lx, ly = sorted([rng.uniform(*PLANAR_LENGTH), rng.uniform(*PLANAR_WIDTH)], reverse=True)
    counts = (int(np.clip(round(lx / 0.02), 6, 20)), int(np.clip(round(ly / 0.02), 5, 16)), 2)
    mesh = _grid_box(counts)
    q = mesh.vertices.copy()
    verts = q * np.array([lx, ly, t]) / 2
    xy = q[:, :2]
    rim = np.clip(1 - xy[:, 0] ** 2, 0, 1) * np.clip(1 - xy[:, 1] ** 2, 0, 1)  # 0 on the sealed rim
    side = np.sign(q[:, 2])
    # Pillow: contents push the faces apart in the middle; the rim stays flat.
    pillow = {"envelope": 0.15, "mailer": 0.3, "polybag": 0.6}[kind] * t * rng.uniform(0.3, 1.0)
    # Wrinkles: a few smooth bumps (top and bottom differ).
    amp = {"envelope": 0.002, "mailer": 0.003, "polybag": 0.006}[kind]
    wr = np.zeros(len(q))
    for sign in (-1.0, 1.0):
        sel = side == sign
        wr[sel] = amp * _smooth_field(xy[sel], rng, int(rng.integers(3, 9)), (0.08, 0.25))
    verts[:, 2] += side * (pillow * rim) + wr * np.sqrt(rim)
    # Keep the two faces apart (no self-intersection): at least 40 % of the nominal thickness.
    top, bot = side > 0, side < 0
    verts[top, 2] = np.maximum(verts[top, 2], 0.2 * t)
    verts[bot, 2] = np.minimum(verts[bot, 2], -0.2 * t)
    verts[:, 2] *= t / np.ptp(verts[:, 2])  # the sampled thickness is the parcel's full thickness
    # Curved: bend the whole parcel along its long axis.
    curvature = rng.uniform(-1.0, 1.0) * (0.4 if rng.random() < 0.5 else 0.0)  # 1/m
    verts[:, 2] += curvature * (verts[:, 0] ** 2 - (lx / 2) ** 2 / 3)
    return trimesh.Trimesh(verts, mesh.faces, process=False)


# m: (min, mode, max) tube radius. Mailing tubes of 70-100 mm diameter, most near 76 mm: the 40 mm bellows
# cup (suction/config.CELL_CUP_RADIUS) seals a crown only from R = 29 mm and with a usable margin (seal
# >= 0.3) from R = 34 mm, so thinner tubes go to the manual exception lane; fatter and longer ones are
# beyond a smalls cell whose tote holds fifty (docs/piles.md)
TUBE_RADIUS = (0.035, 0.038, 0.05)
TUBE_LENGTH, ROLL_LENGTH = (0.15, 0.25), (0.08, 0.14)  # m: (shortest, longest) mailing tube and roll


def _cylindrical(rng: np.random.Generator) -> trimesh.Trimesh:
    radius = float(rng.triangular(*TUBE_RADIUS))  # most tubes are thin; fat rolls are rare
    if rng.random() < 0.6:  # mailing tube: long and thin
        length = float(rng.uniform(max(TUBE_LENGTH[0], 4 * radius), TUBE_LENGTH[1]))
    else:  # roll: short and fat
        length = float(rng.uniform(max(ROLL_LENGTH[0], 1.2 * radius), ROLL_LENGTH[1]))
    mesh = trimesh.creation.cylinder(radius=radius, height=length, sections=48)
    # Lay the axis along body x so the flat-side-down pose is the natural one (z is the short side).
    mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    return mesh


_BUILDERS = {"rectangular": _rectangular, "planar": _planar, "cylindrical": _cylindrical}

_PALETTE = {  # base colours per cluster (RGB in [0, 1]); a random one is jittered per parcel
    "rectangular": [(0.72, 0.55, 0.36), (0.80, 0.66, 0.46), (0.60, 0.44, 0.28), (0.90, 0.85, 0.75)],
    "planar": [(0.95, 0.95, 0.93), (0.85, 0.75, 0.55), (0.30, 0.30, 0.32), (0.75, 0.20, 0.25), (0.25, 0.40, 0.70)],
    "cylindrical": [(0.85, 0.80, 0.70), (0.55, 0.42, 0.30), (0.92, 0.92, 0.92), (0.20, 0.45, 0.30)],
}


def _colours(mesh: trimesh.Trimesh, category: str, rng: np.random.Generator) -> tuple[np.ndarray, tuple]:
    """Per-face RGBA (uint8): a jittered base colour, a white label patch on top, maybe a tape strip."""
    palette = _PALETTE[category]
    base = np.clip(np.array(palette[rng.integers(len(palette))]) + rng.normal(0, 0.04, 3), 0, 1)
    rgba = (float(base[0]), float(base[1]), float(base[2]), 1.0)
    colours = np.tile(np.append(base, 1.0), (len(mesh.faces), 1))
    centres, normals = mesh.triangles_center, mesh.face_normals
    lo, hi = mesh.bounds
    size = hi - lo
    up = normals[:, 2] > 0.5
    if rng.random() < 0.85:  # shipping label on the top face
        lw, lh = rng.uniform(0.3, 0.6) * size[0], rng.uniform(0.3, 0.6) * size[1]
        cx = rng.uniform(lo[0] + lw / 2, hi[0] - lw / 2)
        cy = rng.uniform(lo[1] + lh / 2, hi[1] - lh / 2)
        inside = (np.abs(centres[:, 0] - cx) < lw / 2) & (np.abs(centres[:, 1] - cy) < lh / 2)
        colours[up & inside] = (0.97, 0.97, 0.97, 1.0)
    if category == "rectangular" and rng.random() < 0.8:  # tape strip across the top and down the sides
        tw = rng.uniform(0.04, 0.06)
        tape = rng.choice([(0.78, 0.62, 0.35), (0.85, 0.85, 0.80), (0.20, 0.20, 0.20)])
        strip = (np.abs(centres[:, 1]) < tw / 2) & (np.abs(normals[:, 1]) < 0.5) & (centres[:, 2] > 0)
        colours[strip] = np.append(tape, 1.0)
    if category == "cylindrical" and rng.random() < 0.6:  # end caps in a contrasting colour
        caps = np.abs(normals[:, 0]) > 0.9
        colours[caps] = np.append(np.clip(1.0 - base * 0.5, 0, 1), 1.0)
    return np.round(colours * 255).astype(np.uint8), rgba


def _checked_split(split: str) -> Split:
    """``split`` as the ``Split`` literal a ``ParcelAsset`` holds; anything else is refused by name."""
    if split == "train":
        return "train"
    if split == "test":
        return "test"
    raise ValueError(f"split must be 'train' or 'test', got {split!r}")


def generate_parcel(category: str, rng: np.random.Generator, asset_id: str, split: str) -> ParcelAsset:
    """One random parcel of ``category``; all randomness comes from ``rng``."""
    if category not in CATEGORIES:
        raise ValueError(f"unknown parcel category {category!r}; expected one of {CATEGORIES}")
    checked_split = _checked_split(split)
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng must be a numpy Generator, got {type(rng).__name__}")
    mesh = _BUILDERS[category](rng)
    # Geometric centre: the body origin sits at the centre of the axis-aligned bounds.
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    mesh.fix_normals()
    if not mesh.is_watertight or mesh.volume <= 0:  # a generator bug, never expected
        raise RuntimeError(f"generated {category} parcel {asset_id} is not a closed positive-volume mesh")
    extents = mesh.extents.copy()
    density = rng.uniform(*_DENSITY[category])
    mass = float(np.clip(density * mesh.volume, MIN_MASS, MAX_MASS))
    # Contents shift: move the centre of mass up to 10 % of each extent (less for thin axes).
    com = mesh.center_mass + rng.uniform(-0.1, 0.1, 3) * extents * np.array([1.0, 1.0, 0.5])
    face_colours, rgba = _colours(mesh, category, rng)
    if not isinstance(mesh.visual, trimesh.visual.ColorVisuals):  # a builder bug: textures cannot hold face colours
        raise RuntimeError(f"generated {category} parcel {asset_id} has {type(mesh.visual).__name__}, not per-face colours")
    mesh.visual.face_colors = face_colours
    return ParcelAsset(
        asset_id=asset_id, category=category, split=checked_split, mesh=mesh, mass=mass,
        com=np.asarray(com, dtype=np.float64), rgba=rgba, extents=extents,
    )
