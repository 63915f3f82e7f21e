"""Vote segments: the parcels the centre votes group the observed points into, each centred on its visible top.

A vote for a parcel's centre has to cross the whole parcel, and on large flat parcels it misses by centimetres
(median 3.4 cm on a mailer of the held-out-asset validation split), while the centroid of a parcel's visible top
misses by 0.2 cm, if one knew which points are that parcel's (``eval/centre_bound.py``'s ``visible_top`` reaches
99% of the label oracle's Top-50 AP). Geometry alone cannot tell two touching parcels apart; the votes alone are
too coarse; together they segment well. Two decoded points are joined where they lie within ``radius`` of each other
and their voted centres within ``vote_gap``: a parcel's surface is continuous and its votes drift slowly across it,
while between two parcels either the surface breaks (a step, a gap) or the votes jump to another centre.
Each segment with enough up-facing points is centred on their centroid, unless that centroid lies far from the
segment's mean vote, as a covered parcel's does (the camera sees part of its top). Nothing here sees ground truth.

Only points inside the bin are segmented (``bin_interior``): the head learnt to vote on parcels, and its votes on
the floor and walls are unconstrained, so an envelope lying on the bare floor joined the floor, and took the
floor's centre, in the closed loop's last picks of a pile (measured on the validation piles).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from policies.surface_segments import radius_components, segment_means


def vote_segments(points: np.ndarray, centres: np.ndarray, radius: float, vote_gap: float,
                  tree: cKDTree | None = None) -> np.ndarray:
    """(N,) int64 labels: components of the graph joining the ``points`` closer than ``radius`` whose voted
    ``centres`` (N, 3) lie within ``vote_gap`` of each other (``tree``: one already built on the points)."""
    centres = np.asarray(centres, dtype=np.float32)
    if centres.shape != np.shape(points):
        raise ValueError(f"need one voted centre per point, got {centres.shape} for points {np.shape(points)}")
    if not vote_gap > 0:
        raise ValueError(f"need vote_gap > 0, got {vote_gap}")
    gap2 = np.float32(vote_gap) ** 2

    def votes_agree(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        step = centres[a] - centres[b]
        return np.einsum("ij,ij->i", step, step) <= gap2

    return radius_components(points, radius, votes_agree, tree)


def median_spacing(points: np.ndarray, tree: cKDTree | None = None, workers: int = 1) -> float:
    """The median distance (m) from each of ``points`` (N, 3) to its nearest other one; 0 for fewer than two
    (``tree``: one already built on the points, float64; ``workers``: the query's threads).

    The segments' radius is a multiple of it: the decoded points' density follows the candidates asked for, and a
    radius fixed in metres that joins a parcel's points at one density (7 mm at 16,384 candidates) shatters every
    parcel at a quarter of them (docs/training.md, 'Finer vote segments')."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) < 2:
        return 0.0
    return float(np.median((cKDTree(points) if tree is None else tree).query(points, k=2, workers=workers)[0][:, 1]))


def top_centres(points: np.ndarray, normals: np.ndarray, labels: np.ndarray, up_cos: float, min_points: int,
                votes: np.ndarray | None = None, max_shift: float = np.inf
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, 3) float64: the centroid of the up-facing points (normal z >= ``up_cos``) of each point's segment;
    (N,) whether that segment has at least ``min_points`` of them and, given the points' ``votes`` (N, 3), whether
    that centroid lies within ``max_shift`` horizontally of the segment's mean vote (where not, the centre is NaN);
    and (N,) that horizontal shift, in metres (zeros without ``votes``, NaN where no centre is found).

    The shift test keeps a partly covered parcel on its votes: its visible top's centroid sits off its centre of
    mass, towards the part the camera sees, while its votes still point at the whole parcel. Below the test, the
    shift is the two estimates' disagreement: how far to trust the top's centre."""
    normals = np.asarray(normals, dtype=np.float64)
    labels = np.asarray(labels, dtype=np.int64)
    if normals.shape != np.shape(points) or labels.shape != (len(normals),):
        raise ValueError(f"need a normal and a label per point, got {normals.shape} and {labels.shape} for "
                         f"points {np.shape(points)}")
    if votes is not None and np.shape(votes) != normals.shape:
        raise ValueError(f"need a vote per point, got {np.shape(votes)} for points {np.shape(points)}")
    if len(labels) == 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=bool), np.zeros(0)
    count = int(labels.max()) + 1
    up = normals[:, 2] >= up_cos
    centroids, counts = segment_means(np.asarray(points, dtype=np.float64)[up], labels[up], count)
    found = counts >= int(min_points)
    shift = np.zeros(count)
    if votes is not None:
        with np.errstate(invalid="ignore"):  # segments without a top: NaN, and not found
            shift = np.linalg.norm(segment_means(votes, labels, count)[0][:, :2] - centroids[:, :2], axis=1)
        found[found] = shift[found] <= max_shift
    centroids[~found], shift[~found] = np.nan, np.nan
    return centroids[labels], found[labels], shift[labels]


def covered_fraction(points: np.ndarray, labels: np.ndarray, votes: np.ndarray, top_z: np.ndarray, margin: float,
                     workers: int = 1) -> np.ndarray:
    """(N,) for each point, the share of its segment's points whose mirror image about the segment's mean vote (the
    parcel's centre, as the votes place it) falls, seen from above, on a point of another segment standing more than
    ``margin`` above this segment's top (``top_z``, (N,), metres): how much of the parcel's unseen side lies under
    another parcel.

    A parcel that another rests on shows the camera only part of its top, and the votes still centre it on the whole;
    mirrored about that centre, the part it shows lands on the part it hides, under the parcel resting there. Lifting
    it drags that parcel along: in closed loop such picks held 66% of the time against 95% on free parcels (the
    validation piles, docs/training.md, 'Covered parcels')."""
    points = np.asarray(points, dtype=np.float64)
    labels = np.asarray(labels, dtype=np.int64)
    if len(points) == 0:
        return np.zeros(0)
    count = int(labels.max()) + 1
    centre = segment_means(np.asarray(votes, dtype=np.float64)[:, :2], labels, count)[0]
    mirrors = 2.0 * centre[labels] - points[:, :2]
    seen = cKDTree(points[:, :2]).query(mirrors, workers=workers)[1]
    under = (labels[seen] != labels) & (points[seen, 2] > np.asarray(top_z, dtype=np.float64) + margin)
    return segment_means(under[:, None], labels, count)[0][labels, 0]


def bin_interior(points: np.ndarray, box: np.ndarray | None, floor_margin: float, wall_margin: float) -> np.ndarray:
    """(N,) bool: the points inside ``box`` (the bin's inner box, ``info['workspace']``) at least ``floor_margin``
    above its floor and ``wall_margin`` in from its walls; every point where ``box`` is None (no bin given)."""
    points = np.asarray(points)
    if box is None:
        return np.ones(len(points), dtype=bool)
    low, high = np.asarray(box, dtype=np.float64)
    above_floor = points[:, 2] >= low[2] + floor_margin
    off_walls = np.all((points[:, :2] >= low[:2] + wall_margin) & (points[:, :2] <= high[:2] - wall_margin), axis=1)
    return above_floor & off_walls
