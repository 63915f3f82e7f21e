"""Dense training targets for the Cao et al. heatmaps, built from one labelled scene.

SuctionNet's baseline learns two image-space maps: a *seal* map (each annotated suction point's seal
label splatted as a small Gaussian at its pixel) and a *centre* map (a Gaussian at each object's
projected centre of mass, its width scaled by the object's visible size, so wrench-friendly picks
near the centre score high). Everything here is vectorised over points, objects and pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from parcelpick_env.camera.frame import BACKGROUND
from policies.cao.config import CaoConfig
from policies.observation import check_camera


@dataclass
class LabelledFrame:
    """What the targets need from one stored scene (array shapes as in the dataset shards).

    ``labels`` are the per-point [seal, wrench, collision, visibility] scores of ``points``;
    ``object_ids`` name the rows of ``object_centres`` and match the ``segmentation`` values.
    """

    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32, metres, 0 = no return
    segmentation: np.ndarray  # (H, W) int, BACKGROUND off parcels
    intrinsics: np.ndarray  # (3, 3)
    extrinsics: np.ndarray  # (4, 4) camera -> world, OpenCV
    points: np.ndarray  # (N, 3) world
    labels: np.ndarray  # (N, 4)
    object_ids: np.ndarray  # (K,)
    object_centres: np.ndarray  # (K, 3) world

    def __post_init__(self) -> None:
        if self.depth.ndim == 3 and self.depth.shape[-1] == 1:
            self.depth = self.depth[..., 0]
        h, w = self.depth.shape[:2]
        if self.rgb.shape != (h, w, 3):
            raise ValueError(f"rgb must be ({h}, {w}, 3) to match depth, got {self.rgb.shape}")
        if self.segmentation.shape != (h, w):
            raise ValueError(f"segmentation must be ({h}, {w}), got {self.segmentation.shape}")
        check_camera(self.intrinsics, self.extrinsics)
        if self.points.ndim != 2 or self.points.shape[1] != 3 or self.labels.shape != (len(self.points), 4):
            raise ValueError(f"points must be (N, 3) with labels (N, 4), got {self.points.shape}, {self.labels.shape}")
        if self.object_centres.shape != (len(self.object_ids), 3):
            raise ValueError(f"object_centres must be ({len(self.object_ids)}, 3), got {self.object_centres.shape}")
        for name in ("depth", "points", "labels", "object_centres"):
            if not np.isfinite(getattr(self, name)).all():
                raise ValueError(f"{name} contains NaN or inf")


RECORD_KEYS = ("rgb", "depth", "segmentation", "intrinsics", "extrinsics", "points", "labels", "object_com_world")


def frame_from_record(record: dict[str, np.ndarray]) -> LabelledFrame:
    """A dataset record (``dataset.annotate``) as a LabelledFrame; parcel ``i`` has segmentation id ``i``."""
    missing = [key for key in RECORD_KEYS if key not in record]
    if missing:
        raise ValueError(f"dataset record lacks {missing}; the Cao baseline needs images "
                         f"(generate with store_images=True)")
    centres = np.asarray(record["object_com_world"], dtype=np.float64).reshape(-1, 3)
    return LabelledFrame(rgb=np.asarray(record["rgb"]), depth=np.asarray(record["depth"], dtype=np.float32),
                         segmentation=np.asarray(record["segmentation"]), intrinsics=record["intrinsics"],
                         extrinsics=record["extrinsics"], points=np.asarray(record["points"]),
                         labels=np.asarray(record["labels"]), object_ids=np.arange(len(centres)),
                         object_centres=centres)


def scale_intrinsics(intrinsics: np.ndarray, from_hw: tuple[int, int], to_hw: tuple[int, int]) -> np.ndarray:
    """K for the same camera resampled to ``to_hw`` pixels (pixel centres at integer coordinates)."""
    sy, sx = to_hw[0] / from_hw[0], to_hw[1] / from_hw[1]
    K = np.array(intrinsics, dtype=np.float64, copy=True)
    K[0, 0] *= sx
    K[1, 1] *= sy
    K[0, 1] *= sx
    K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K


def nearest_resize(image: np.ndarray, out_hw: tuple[int, int]) -> np.ndarray:
    """Nearest-pixel resampling that never mixes values (depth holes, segmentation ids)."""
    h, w = image.shape[:2]
    rows = np.minimum(((np.arange(out_hw[0]) + 0.5) * h / out_hw[0]).astype(np.int64), h - 1)
    cols = np.minimum(((np.arange(out_hw[1]) + 0.5) * w / out_hw[1]).astype(np.int64), w - 1)
    return image[rows[:, None], cols[None, :]]


def project_points(points: np.ndarray, intrinsics: np.ndarray,
                   extrinsics: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points -> sub-pixel (row, col) and camera z-depth (OpenCV camera-to-world extrinsics)."""
    T = np.asarray(extrinsics, dtype=np.float64)
    cam = (np.asarray(points, dtype=np.float64) - T[:3, 3]) @ T[:3, :3]  # R^T (p - t), row-wise
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uvw = cam @ np.asarray(intrinsics, dtype=np.float64).T
        rc = np.stack([uvw[:, 1] / z, uvw[:, 0] / z], axis=1)
    return rc, z


def seal_target(pixels_rc: np.ndarray, values: np.ndarray, shape: tuple[int, int], sigma: float) -> np.ndarray:
    """Max-splat ``values * exp(-d^2 / 2 sigma^2)`` around each sub-pixel location in ``pixels_rc``.

    The max (not the sum) keeps overlapping points from inflating scores past their labels.
    """
    h, w = shape
    target = np.zeros(h * w, dtype=np.float32)
    keep = np.isfinite(pixels_rc).all(axis=1) & np.isfinite(values)
    rc, values = pixels_rc[keep], values[keep].astype(np.float32)
    radius = int(np.ceil(3.0 * sigma))
    offsets = np.arange(-radius, radius + 1)
    dr, dc = (o.ravel() for o in np.meshgrid(offsets, offsets, indexing="ij"))
    rows = np.rint(rc[:, 0])[:, None] + dr[None, :]  # (N, window)
    cols = np.rint(rc[:, 1])[:, None] + dc[None, :]
    d2 = (rows - rc[:, 0:1]) ** 2 + (cols - rc[:, 1:2]) ** 2
    weight = values[:, None] * np.exp(-d2 / (2.0 * sigma ** 2)).astype(np.float32)
    inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
    flat = rows[inside].astype(np.int64) * w + cols[inside].astype(np.int64)
    np.maximum.at(target, flat, weight[inside])
    return target.reshape(h, w)


def object_sigmas(segmentation: np.ndarray, object_ids: np.ndarray, scale: float, min_sigma: float) -> np.ndarray:
    """Centre-Gaussian widths: ``scale`` times each object's visible equivalent radius sqrt(area / pi)."""
    seg = segmentation.ravel()
    ids = np.asarray(object_ids, dtype=np.int64)
    parcel = seg != BACKGROUND
    if parcel.any() and (seg[parcel].min() < 0):
        raise ValueError("segmentation holds negative ids other than BACKGROUND")
    size = max(int(seg.max(initial=-1)), int(ids.max(initial=-1))) + 1
    areas = np.bincount(seg[parcel].astype(np.int64), minlength=size)
    area = np.where(ids >= 0, areas[np.clip(ids, 0, None)], 0)
    return np.maximum(scale * np.sqrt(area / np.pi), min_sigma)


def centre_target(centres_rc: np.ndarray, sigmas: np.ndarray, shape: tuple[int, int],
                  segmentation: np.ndarray | None = None, object_ids: np.ndarray | None = None) -> np.ndarray:
    """Gaussians at object centres. With a segmentation, each pixel only sees its own object's Gaussian.

    Masking by object keeps the map from leaking across boundaries onto a neighbour, so the product
    with the seal map cannot reward a point on one parcel for lying near another parcel's centre.
    """
    h, w = shape
    if segmentation is None:
        rr, cc = np.mgrid[0:h, 0:w].astype(np.float32)
        ok = np.isfinite(centres_rc).all(axis=1)
        c, s = centres_rc[ok].astype(np.float32), np.asarray(sigmas, dtype=np.float32)[ok]
        if len(c) == 0:
            return np.zeros(shape, dtype=np.float32)
        d2 = (rr[None] - c[:, 0, None, None]) ** 2 + (cc[None] - c[:, 1, None, None]) ** 2
        return np.exp(-d2 / (2.0 * s[:, None, None] ** 2)).max(axis=0).astype(np.float32)
    if object_ids is None:
        raise ValueError("centre_target needs object_ids to go with a segmentation")
    ids = np.asarray(object_ids, dtype=np.int64)
    seg = segmentation.astype(np.int64)
    lookup = np.full(max(int(seg.max(initial=-1)), int(ids.max(initial=-1))) + 2, -1, dtype=np.int64)
    lookup[ids[ids >= 0]] = np.flatnonzero(ids >= 0)
    row = np.where(seg >= 0, lookup[np.clip(seg, 0, None)], -1)  # index into centres, -1 = none
    has = (row >= 0) & np.isfinite(centres_rc[np.clip(row, 0, None)]).all(axis=-1)
    rr, cc = np.mgrid[0:h, 0:w]
    c = centres_rc[np.clip(row, 0, None)]
    s = np.asarray(sigmas, dtype=np.float64)[np.clip(row, 0, None)]
    d2 = (rr - c[..., 0]) ** 2 + (cc - c[..., 1]) ** 2
    return np.where(has, np.exp(-d2 / (2.0 * s ** 2)), 0.0).astype(np.float32)


def frame_targets(frame: LabelledFrame, config: CaoConfig) -> np.ndarray:
    """(2, h, w) float32 [seal, centre] targets at the network's input resolution."""
    out_hw = (config.input_height, config.input_width)
    K = scale_intrinsics(frame.intrinsics, frame.depth.shape[:2], out_hw)
    rc, z = project_points(frame.points, K, frame.extrinsics)
    labels = np.clip(np.nan_to_num(frame.labels[:, config.seal_label_columns], nan=0.0), 0.0, 1.0)
    values = np.where(z > 0, labels.prod(axis=1), np.nan)
    seal = seal_target(rc, values, out_hw, config.seal_sigma_px)

    centres_rc, cz = project_points(frame.object_centres, K, frame.extrinsics)
    centres_rc[cz <= 0] = np.nan
    seg = nearest_resize(frame.segmentation, out_hw)
    sigmas = object_sigmas(seg, frame.object_ids, config.centre_sigma_scale, config.min_centre_sigma_px)
    centre = centre_target(centres_rc, sigmas, out_hw, seg, frame.object_ids)
    return np.stack([seal, centre]).astype(np.float32)
