"""Normal-STD baseline (SuctionNet-1Billion): flat surfaces are good suction sites.

The normal map of the depth image is smoothed into a flatness heat map: ``heat = 1 - std / max(std)``,
where ``std`` is the per-pixel standard deviation of the normals over a window. Candidates are the
best pixel of each grid cell after a box filter. There is nothing to learn.

Resolution and KNN. SuctionNet runs on 1280x720 images with Open3D KNN-224 normals. Here the depth
image is first subsampled by ``downsample`` (default 2, so 320x240 for the env's 640x480) for speed;
the windows, the cell and the KNN count are scaled with it (windows by 1/s, KNN by 1/s^2), so the
normals and the std are taken over the same surface patch as at full resolution. KNN 224 at full
resolution is therefore KNN 56 at the default ``downsample=2``. Open3D's KNN normal estimation
dominates the cost (benchmarks/bench_policies.py); ``downsample=4`` (KNN 16) is roughly ten times
faster for closed-loop use, with a coarser candidate grid.

Workspace. SuctionNet restricts candidates to the objects' image region; a policy here may not see
ground truth, so candidates are restricted to the inside of the bin: ``config.workspace`` if set, else
the env's ``info['workspace']`` (``BinSpec.workspace()``, the cell's known geometry), else the bounding
box of the observed cloud. That box is narrowed by the background a real cell masks out: the floor
(``floor_clearance``) and the walls (``wall_clearance``, one cup radius). The depth image sees the
bin's inner wall faces, the flattest surfaces left once the floor is gone; a cup sent along their
horizontal normal strikes the wall on the approach or cannot descend past the rim (measured in closed
loop: every pick of the unmasked policy went there, 0% R_grasp). A cup centred closer to a wall than
its radius cannot seat there in any case. Normal-STD still has no notion of objects or of reachability.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Mapping

import numpy as np
import open3d as o3d
from scipy.ndimage import uniform_filter

from parcelpick_env.suction.config import CELL_CUP_RADIUS
from policies.base import Candidates, Policy
from policies.heatmap import box_filter, grid_topk, pixels_to_world
from policies.observation import camera, check_workspace, depth_image, in_box, workspace
from policies.postprocess import select_candidates

if TYPE_CHECKING:
    from parcelpick_env.scene.scene import BinSpec

# The std normaliser never drops below this: on a scene whose normals barely vary (a flat synthetic
# render), ``1 - std / max(std)`` would otherwise stretch floating-point round-off to the full [0, 1].
_STD_FLOOR = 1e-3


@dataclass(frozen=True)
class NormalStdConfig:
    """Window sizes and ``knn`` are given at full image resolution; see the module docstring."""

    downsample: int = 2
    knn: int = 224
    min_knn: int = 16
    std_window: int = 25
    smooth_window: int = 15
    cell: int = 10
    max_candidates: int = 1024
    nms_radius: float = 0.02
    # World-frame box (min xyz, max xyz) candidates must lie in; None: ``info['workspace']`` (the env's
    # bin) when given, else the observed cloud's bounding box.
    workspace: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    # Empty-bin background removal: pixels this close above the workspace floor are not candidates
    # (the flat bin floor is otherwise the best-scoring surface in view).
    floor_clearance: float = 0.004
    # Bin-wall removal: pixels closer than this to the workspace's side faces (the bin's inner walls) in x
    # or y are not candidates; the cell's cup radius, so the lip clears the wall.
    wall_clearance: float = CELL_CUP_RADIUS

    def __post_init__(self) -> None:
        for name in ("downsample", "knn", "min_knn", "std_window", "smooth_window", "cell", "max_candidates"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"NormalStdConfig.{name} must be a positive integer, got {value!r}")
        if self.min_knn < 3:
            raise ValueError(f"NormalStdConfig.min_knn must be >= 3 to fit a plane, got {self.min_knn}")
        for name in ("floor_clearance", "wall_clearance"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"NormalStdConfig.{name} must be >= 0, got {getattr(self, name)!r}")
        if not self.nms_radius >= 0:
            raise ValueError(f"NormalStdConfig.nms_radius must be >= 0, got {self.nms_radius!r}")
        if self.workspace is not None:
            check_workspace(self.workspace, "NormalStdConfig")

    @classmethod
    def for_bin(cls, spec: "BinSpec", **kwargs: Any) -> "NormalStdConfig":
        """A config whose workspace is the inside of ``spec``'s bin (as the env's ``info['workspace']``)."""
        lo, hi = spec.workspace()
        return cls(workspace=(tuple(map(float, lo)), tuple(map(float, hi))), **kwargs)

    def window(self, full_res: int) -> int:
        """A full-resolution window scaled to the working resolution, kept odd so it is centred."""
        return max(1, int(round(full_res / self.downsample))) | 1

    @property
    def effective_knn(self) -> int:
        return max(self.min_knn, int(round(self.knn / self.downsample**2)))

    @property
    def effective_cell(self) -> int:
        return max(1, int(round(self.cell / self.downsample)))


@dataclass
class FlatnessMap:
    """Everything Normal-STD derives from one depth image, at the working resolution."""

    heat: np.ndarray  # (h, w) smoothed flatness in [0, 1]; -inf where depth is missing
    points: np.ndarray  # (h, w, 3) world frame; 0 where depth is missing
    normals: np.ndarray  # (h, w, 3) unit, oriented towards the camera; 0 where depth is missing
    valid: np.ndarray  # (h, w) bool


def _depth_and_calibration(obs: Mapping[str, np.ndarray], info: Mapping[str, Any] | None
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    depth = depth_image(obs, "Normal-STD").astype(np.float64)
    K, T = camera(info, "Normal-STD")
    return depth, K, T


def _workspace(fmap: FlatnessMap, obs: Mapping[str, np.ndarray], box, floor_clearance: float,
               wall_clearance: float) -> np.ndarray:
    """Pixels inside ``box`` (else the observed cloud's bounding box), clear of its floor and side walls.

    The depth image also sees the floor around the bin, the bin floor and the bin's inner walls, the
    flattest surfaces in view; without this mask every top candidate would land there.
    """
    if box is not None:
        lo, hi = np.asarray(box, dtype=np.float64)
    else:
        cloud = np.asarray(obs.get("points", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
        cloud = cloud[np.all(np.isfinite(cloud), axis=1)]
        if len(cloud) == 0:
            return fmap.valid
        lo, hi = cloud.min(axis=0), cloud.max(axis=0)
    lo = lo + np.array([wall_clearance, wall_clearance, floor_clearance])
    hi = hi - np.array([wall_clearance, wall_clearance, 0.0])
    if np.any(lo >= hi):
        raise ValueError(f"NormalStdConfig.wall_clearance ({wall_clearance}) and floor_clearance ({floor_clearance}) "
                         f"leave no workspace: {lo.round(3).tolist()} to {hi.round(3).tolist()}")
    return fmap.valid & in_box(fmap.points, lo, hi)


class NormalStdPolicy(Policy):
    name = "normal_std"

    def __init__(self, config: NormalStdConfig | None = None) -> None:
        self.config = config or NormalStdConfig()

    def flatness(self, obs: Mapping[str, np.ndarray], info: Mapping[str, Any] | None) -> FlatnessMap:
        """Heat map of surface flatness from the depth image (exposed for tests and visualisation)."""
        cfg = self.config
        depth, K, T = _depth_and_calibration(obs, info)
        s = cfg.downsample
        depth = depth[::s, ::s]
        K = K.copy()
        K[:2] /= s  # pixel u' = u / s for a strided subsample
        valid = depth > 0
        rows, cols = np.nonzero(valid)
        points = np.zeros(depth.shape + (3,))
        points[valid] = pixels_to_world(rows, cols, depth, K, T)

        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[valid]))
        if len(cloud.points) < cfg.min_knn:
            raise ValueError(f"only {len(cloud.points)} valid depth pixels; Normal-STD needs at least {cfg.min_knn}")
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=cfg.effective_knn))
        cloud.orient_normals_towards_camera_location(T[:3, 3])
        normals = np.zeros_like(points)
        normals[valid] = np.asarray(cloud.normals)

        # Masked window statistics: holes in the depth image do not count as samples.
        win = cfg.window(cfg.std_window)
        weight = valid.astype(np.float64)
        count = uniform_filter(weight, size=win, mode="nearest")
        safe = np.maximum(count, 1e-12)[..., None]
        mean = uniform_filter(normals, size=(win, win, 1), mode="nearest") / safe
        mean_sq = uniform_filter(normals**2, size=(win, win, 1), mode="nearest") / safe
        std = np.sqrt(np.clip(mean_sq - mean**2, 0.0, None)).mean(axis=-1)  # SuctionNet: mean of channel stds
        std[~valid] = 0.0
        heat = 1.0 - std / max(float(std.max()), _STD_FLOOR)
        # A hole next to a pixel lowers its smoothed score (it counts as 0): the surface is unknown there.
        heat = box_filter(heat, cfg.window(cfg.smooth_window), valid)
        return FlatnessMap(heat=heat, points=points, normals=normals, valid=valid)

    def predict(self, obs: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None,
                top_k: int = 50) -> Candidates:
        if top_k < 1:
            raise ValueError(f"top_k must be >= 1, got {top_k}")
        fmap = self.flatness(obs, info)
        box = self.config.workspace if self.config.workspace is not None else workspace(info, "Normal-STD")
        cfg = self.config
        heat = np.where(_workspace(fmap, obs, box, cfg.floor_clearance, cfg.wall_clearance), fmap.heat, -np.inf)
        rows, cols, scores = grid_topk(heat, self.config.effective_cell, self.config.max_candidates)
        return select_candidates(fmap.points[rows, cols], fmap.normals[rows, cols], scores, top_k=top_k,
                                 nms_radius=self.config.nms_radius)
