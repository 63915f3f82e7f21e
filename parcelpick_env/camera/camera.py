"""The overhead camera: pybullet render -> metric depth, segmentation, world point cloud with normals.

Rendering prefers pybullet's EGL plugin (hardware or Mesa OpenGL, fast), which the Simulator loads
when its client starts (``SimConfig.egl_rendering``: the plugin only sees shapes created after
it; ``sim/egl.py`` keeps every EGL client of the process valid), and falls back to the TinyRenderer
(software, slower; its image sits about half a pixel lower) with one logged warning per process when
the simulator has no EGL. A closed or stale simulator is refused with an error, never rendered. The
OpenGL depth buffer is converted to metric z-depth, sensor effects (Gaussian z-noise, dropouts)
are drawn from the caller's generator, and every valid pixel is back-projected with the OpenCV
pinhole model. Normals come from Open3D's KNN estimate (or the faster image-window PCA in
``normals.py``), flipped to face the camera (outward); a caller that needs them at a few points only (the
dataset) captures with ``normals=False`` and asks ``normals_at`` for those.
"""

from __future__ import annotations

import logging
import math
import weakref

import numpy as np
import pybullet as pb

from parcelpick_env.camera.config import CameraConfig
from parcelpick_env.camera.frame import BACKGROUND, CameraFrame
from parcelpick_env.camera.normals import knn_normals_at, open3d_normals, organized_normals
from parcelpick_env.scene.scene import Scene
from parcelpick_env.sim.simulator import Simulator

log = logging.getLogger(__name__)

_WARM_SIMULATORS: "weakref.WeakSet[Simulator]" = weakref.WeakSet()  # EGL contexts past their first frames
_WARNED = {"tiny_fallback": False}


class Camera:
    """A fixed overhead camera; ``capture`` renders the current state of a simulator."""

    def __init__(self, config: CameraConfig | None = None) -> None:
        self.config = config or CameraConfig()
        cfg = self.config
        fy = (cfg.height / 2) / math.tan(math.radians(cfg.fov_y_deg) / 2)
        self.intrinsics = np.array([[fy, 0.0, (cfg.width - 1) / 2],
                                    [0.0, fy, (cfg.height - 1) / 2],
                                    [0.0, 0.0, 1.0]])
        # OpenCV camera axes in the world: x right = +x, y down = -y, z forward = -z (looking down).
        extrinsics = np.eye(4)
        extrinsics[:3, :3] = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
        extrinsics[:3, 3] = cfg.position
        self.extrinsics = extrinsics
        eye = np.asarray(cfg.position, dtype=np.float64)
        self._view = pb.computeViewMatrix(eye.tolist(), (eye - [0, 0, 1]).tolist(), [0.0, 1.0, 0.0])
        self._proj = pb.computeProjectionMatrixFOV(cfg.fov_y_deg, cfg.aspect, cfg.near, cfg.far)
        self.renderer = "tiny" if cfg.renderer == "tiny" else "egl"  # confirmed at the first capture
        # Back-projection rays of every pixel (z = 1), in the camera frame.
        rows, cols = np.mgrid[0:cfg.height, 0:cfg.width]
        K = self.intrinsics
        self._rays = np.stack([(cols - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1], np.ones_like(cols, float)], -1)

    @property
    def position(self) -> np.ndarray:
        return self.extrinsics[:3, 3].copy()

    def project(self, points_world: np.ndarray) -> np.ndarray:
        """(N, 3) world points -> (N, 2) continuous pixel coordinates (u = column, v = row)."""
        pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        R, t = self.extrinsics[:3, :3], self.extrinsics[:3, 3]
        cam = (pts - t) @ R
        uvw = cam @ self.intrinsics.T
        return uvw[:, :2] / uvw[:, 2:3]

    def _get_image(self, sim: Simulator, width: int, height: int, renderer: int) -> tuple:
        return pb.getCameraImage(width, height, viewMatrix=self._view, projectionMatrix=self._proj,
                                 renderer=renderer, shadow=0, lightDirection=[0.3, -0.4, 1.0],
                                 physicsClientId=sim.client)

    def _render(self, sim: Simulator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        cfg = self.config
        if sim.closed:
            raise RuntimeError("Camera: cannot render a closed Simulator")
        if sim.egl_enabled and not sim.egl_current:  # never render from a stale EGL client (blank images)
            raise RuntimeError("Camera: this Simulator's EGL renderer is no longer valid; make a new Simulator")
        use_egl = cfg.renderer in ("auto", "egl") and sim.egl_enabled
        if cfg.renderer in ("auto", "egl") and not use_egl and not _WARNED["tiny_fallback"]:
            log.warning("EGL rendering is not enabled on this simulator; using pybullet's TinyRenderer (slower)")
            _WARNED["tiny_fallback"] = True
        self.renderer = "egl" if use_egl else "tiny"
        renderer = pb.ER_BULLET_HARDWARE_OPENGL if use_egl else pb.ER_TINY_RENDERER
        if use_egl:
            # The EGL renderer shades its first frame after a world change with stale state (and its
            # first frames in a new context differently again), so RGB would depend on what the
            # simulator drew before. Throw-away frames sync it; tiny ones cost almost nothing.
            for _ in range(1 if sim in _WARM_SIMULATORS else 2):
                self._get_image(sim, 8, 8, renderer)
            _WARM_SIMULATORS.add(sim)
        w, h, rgba, depth_buf, seg = self._get_image(sim, cfg.width, cfg.height, renderer)
        rgb = np.asarray(rgba, dtype=np.uint8).reshape(h, w, 4)[..., :3]
        depth_buf = np.asarray(depth_buf, dtype=np.float64).reshape(h, w)
        seg = np.asarray(seg, dtype=np.int64).reshape(h, w)
        return rgb, depth_buf, seg

    def capture(self, sim: Simulator, scene: Scene, rng: np.random.Generator | None = None,
                normals: bool = True) -> CameraFrame:
        """Render ``sim`` now; segmentation labels are ``scene``'s object ids (``BACKGROUND`` elsewhere).

        ``normals=False`` leaves ``frame.normals`` empty, (0, 3), for a caller that needs them at a few of
        the points only: ``normals_at`` then gives exactly those, for a fraction of the cost.
        """
        cfg = self.config
        rgb, depth_buf, seg_bodies = self._render(sim)
        near, far = cfg.near, cfg.far
        depth = far * near / (far - (far - near) * depth_buf)
        valid = depth_buf < 1.0 - 1e-7  # the far plane means no return

        # Body id -> scene object id; bin, ground, robot and empty pixels -> BACKGROUND.
        body_ids = np.array([p.body_id for p in scene.parcels], dtype=np.int64)
        top = int(max(seg_bodies.max(initial=-1), body_ids.max(initial=-1))) + 2
        lookup = np.full(top, BACKGROUND, dtype=np.int32)
        lookup[body_ids + 1] = np.array([p.object_id for p in scene.parcels], dtype=np.int32)
        segmentation = lookup[np.clip(seg_bodies + 1, 0, top - 1)]

        if cfg.depth_noise_std > 0 or cfg.dropout_prob > 0:
            rng = rng if rng is not None else np.random.default_rng()
            if cfg.depth_noise_std > 0:
                depth = depth + rng.normal(0.0, cfg.depth_noise_std, size=depth.shape)
            if cfg.dropout_prob > 0:
                valid &= rng.random(size=depth.shape) >= cfg.dropout_prob
        valid &= depth > 0
        depth = np.where(valid, depth, 0.0).astype(np.float32)

        rows, cols = np.nonzero(valid)
        points = self._back_project(depth, rows, cols)
        cloud_normals = self._normals(points, depth, rows, cols, None) if normals else np.zeros((0, 3))
        return CameraFrame(
            rgb=np.ascontiguousarray(rgb), depth=depth, segmentation=segmentation.astype(np.int32),
            intrinsics=self.intrinsics.copy(), extrinsics=self.extrinsics.copy(),
            points=points.astype(np.float32), normals=cloud_normals.astype(np.float32),
            point_object_ids=segmentation[rows, cols].astype(np.int32),
            point_pixels=np.stack([rows, cols], axis=1).astype(np.int32), points64=points,
        )

    def normals_at(self, frame: CameraFrame, indices: np.ndarray) -> np.ndarray:
        """(M, 3) float32: the normals ``capture`` gives ``frame.points[indices]``, estimated only there.

        ``frame`` must come from this camera's ``capture``: its float64 cloud (``frame.points64``, or rebuilt
        from the stored depth and pixels, bit for bit) is what ``capture`` estimates on, so the normals agree
        with ``capture``'s to rounding. The organised estimator filters the whole image either way (it is cheap).
        """
        if frame.depth.shape != (self.config.height, self.config.width):
            raise ValueError(f"frame is {frame.width}x{frame.height}, this camera captures "
                             f"{self.config.width}x{self.config.height}")
        indices = np.asarray(indices, dtype=np.int64).reshape(-1)
        rows, cols = frame.point_pixels[:, 0], frame.point_pixels[:, 1]
        points = frame.points64 if frame.points64 is not None else self._back_project(frame.depth, rows, cols)
        return self._normals(points, frame.depth, rows, cols, indices).astype(np.float32)

    def _back_project(self, depth: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """World points (float64) of the pixels ``(rows, cols)`` of a metric z-depth image."""
        # gathered by flat index (numpy's 2-D fancy indexing of (H, W, 3) is several times slower) and scaled in
        # place: each fresh 7 MB array of a 640x480 cloud costs its page faults
        flat = np.asarray(rows, dtype=np.int64) * depth.shape[1] + cols
        cam_pts = self._rays.reshape(-1, 3)[flat]
        cam_pts *= depth.reshape(-1)[flat, None]  # float32 depth promoted to float64, exactly
        # a C-contiguous R^T: numpy's matmul takes its slow strided loop for a transposed view
        world = cam_pts @ np.ascontiguousarray(self.extrinsics[:3, :3].T)
        world += self.extrinsics[:3, 3]
        return world

    def _normals(self, points: np.ndarray, depth: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                 at: np.ndarray | None) -> np.ndarray:
        """Normals of ``points`` (the valid pixels ``rows, cols``), all of them or only ``points[at]``."""
        cfg = self.config
        if cfg.normal_method == "organized":
            image = np.zeros(depth.shape + (3,))
            image[rows, cols] = points
            valid = np.zeros(depth.shape, bool)
            valid[rows, cols] = True
            normals = organized_normals(image, valid, cfg.normal_knn, self.position)
            return normals if at is None else normals[at]
        if at is None:
            return open3d_normals(points, cfg.normal_knn, self.position)
        return knn_normals_at(points, at, cfg.normal_knn, self.position)
