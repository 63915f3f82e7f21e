"""Where the privileged oracle would push a parcel to part a pile in which no pick holds.

In the 30-parcel heap every parcel left can bear or lean on another; then every pick the oracle rehearses
drags a neighbour and drops, and the episode ends on three failures. One push of the topmost free parcel,
chosen in hindsight, opened most of those dead ends (results/ORACLE.md, 'A parting move'). The oracle tries
the pushes listed here on its twin of the cell (``CellTwin.rehearse_push``) and takes the first after which
one of its picks holds there (``OraclePolicy``, ``parting_pushes``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import open3d as o3d
import trimesh

from parcelpick_env.envs.push import PUSH_START_TOLERANCE
from parcelpick_env.suction.geometry import build_scene, ring_pattern

if TYPE_CHECKING:  # the oracle imports this module
    from policies.oracle import GroundTruth

SIDE_GAP = 0.01  # m between the cup's side and the parcel where the tool comes down
BELOW_TOP = 0.03  # m below the parcel's top where the cup pushes ...
ABOVE_BOTTOM = 0.015  # m ... but never lower than this above its bottom (a thin mailer: just above what it lies on)
COLUMN_RAYS = 8  # rays on the cup's rim (and one at its axis) that must find the tool's way down clear
ABOVE_SCENE = 0.10  # m: those rays start this far above the highest parcel


@dataclass(frozen=True)
class PushCandidate:
    """A parting push: the tool tip comes down to ``start`` and moves along ``direction`` (horizontal, unit)."""

    parcel: int  # row of the parcel it is aimed at
    start: np.ndarray  # (3,)
    direction: np.ndarray  # (3,)


def push_candidates(truth: "GroundTruth", pinned: np.ndarray, cup_radius: float, limit: int,
                    bounds: tuple[np.ndarray, np.ndarray] | None = None) -> list[PushCandidate]:
    """Up to ``limit`` pushes: the parcels nothing rests on first (``pinned`` False), the highest first, then the
    pinned ones, highest first; each pushed four ways along its own horizontal axes, from beside its outline at the
    push's height (``push_frame``). A push whose start lies outside ``bounds`` (the env's action box,
    ``BinSpec.workspace``: beside a parcel against a wall it lies beyond the wall) is left out, as is one where the
    cup cannot come down to its start (something above it in the cup's column): the env would refuse the first
    and the twin the second, and neither should take one of the ``limit`` tries."""
    heights = truth.coms[:, 2] if len(truth.meshes) else np.zeros(0)
    order = sorted(range(len(truth.meshes)), key=lambda k: (bool(pinned[k]), -float(heights[k])))
    out: list[PushCandidate] = []
    for k in order:
        centre, axes, half, z = push_frame(truth.meshes[k])
        for d in (axes[0], -axes[0], axes[1], -axes[1]):
            reach = float(np.abs(axes @ d) @ half) + cup_radius + SIDE_GAP
            start = np.array([*(centre - reach * d), z])
            if bounds is None or not (np.any(start < bounds[0]) or np.any(start > bounds[1])):
                out.append(PushCandidate(k, start, np.array([*d, 0.0])))
    if out:
        clear = column_clear(truth, np.array([p.start for p in out]), cup_radius)
        out = [p for p, ok in zip(out, clear) if ok]
    return out[:limit]


def push_frame(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Where a parcel is pushed: the centre (2,), the two horizontal axes (2, 2) and half-extents (2,) of the
    smallest rectangle about its cross-section at the push height, and that height: ``BELOW_TOP`` under its top,
    at least ``ABOVE_BOTTOM`` over its bottom. Its own outline there, not its world bounding box, which for a
    tilted tube or a mailer on edge lies off its body. The axes are ordered and signed alike for every parcel
    (the first nearer the world's x and pointing to +x, the second to +y), so a level carton is pushed along x first."""
    lo, hi = mesh.bounds
    z = max(float(lo[2]) + ABOVE_BOTTOM, float(hi[2]) - BELOW_TOP)
    section = mesh.section(plane_origin=[0.0, 0.0, z], plane_normal=[0.0, 0.0, 1.0])
    outline = None if section is None else np.asarray(section.vertices)[:, :2]
    if outline is None or len(outline) < 3 or np.ptp(outline, axis=0).min() < 1e-6:
        return (lo[:2] + hi[:2]) / 2, np.eye(2), (hi[:2] - lo[:2]) / 2, z  # no outline there: the bounding box
    to_rectangle, size = trimesh.bounds.oriented_bounds_2D(outline)
    axes, half = to_rectangle[:2, :2].copy(), np.asarray(size, dtype=np.float64) / 2
    centre = np.linalg.solve(to_rectangle[:2, :2], -to_rectangle[:2, 2])  # the rectangle's centre, world xy
    if abs(axes[1, 0]) > abs(axes[0, 0]):
        axes, half = axes[::-1].copy(), half[::-1].copy()
    axes[0] *= 1.0 if axes[0, 0] >= 0 else -1.0
    axes[1] *= 1.0 if axes[1, 1] >= 0 else -1.0
    return centre, axes, half, z


def column_clear(truth: "GroundTruth", starts: np.ndarray, cup_radius: float) -> np.ndarray:
    """(S,) whether the cup can come straight down to each start: rays down from above the pile along its axis and
    its rim first meet a parcel, the tote or nothing less than ``PUSH_START_TOLERANCE`` above the start (the env's
    push refuses a descent that stops higher)."""
    rim = ring_pattern([0.0, cup_radius], [1, COLUMN_RAYS])
    top = max(float(m.bounds[1, 2]) for m in truth.meshes + truth.obstacles) + ABOVE_SCENE
    origins = np.repeat(starts, len(rim), axis=0)
    origins[:, :2] += np.tile(rim, (len(starts), 1))
    origins[:, 2] = top
    down = np.tile([0.0, 0.0, -1.0], (len(origins), 1))
    rays = o3d.core.Tensor.from_numpy(np.concatenate([origins, down], axis=1).astype(np.float32))
    hit = build_scene(truth.meshes + truth.obstacles).cast_rays(rays)["t_hit"].numpy().astype(np.float64)
    first = (top - hit).reshape(len(starts), len(rim))  # height of the first thing each ray meets (-inf: nothing)
    return np.all(first < starts[:, 2:3] + PUSH_START_TOLERANCE, axis=1)
