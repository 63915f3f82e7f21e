"""The overhead 3-D camera's settings: a fixed Mech-Eye-like sensor looking straight down."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from parcelpick_env.config_checks import require_int
from parcelpick_env.scene.scene import BinSpec

RENDERERS: tuple[str, ...] = ("auto", "egl", "tiny")
MIN_IMAGE_SIDE, MAX_IMAGE_SIDE = 8, 4096  # pixels; real 3-D cameras top out near 2k x 1.5k
NORMAL_METHODS: tuple[str, ...] = ("open3d", "organized")


@dataclass(frozen=True)
class CameraConfig:
    """Pinhole camera at ``position`` (world), optical axis straight down (-z), image x along world +x.

    ``fov_y_deg`` is the vertical field of view; pixels are square, so the horizontal one follows
    from the aspect ratio. The defaults frame the default 0.70 x 0.50 m bin from 1.4 m with margin
    (``for_bin`` frames any other bin). ``depth_noise_std`` is Gaussian z-noise in metres and
    ``dropout_prob`` the fraction of valid pixels that return no depth (0), as real sensors do.
    """

    width: int = 640
    height: int = 480
    position: tuple[float, float, float] = (0.0, 0.0, 1.4)
    fov_y_deg: float = 35.0
    near: float = 0.1
    far: float = 3.0
    depth_noise_std: float = 0.0005
    dropout_prob: float = 0.0
    renderer: str = "auto"
    normal_knn: int = 30
    normal_method: str = "open3d"  # or "organized": image-window PCA, ~4x faster (camera/normals.py)

    def __post_init__(self) -> None:
        for name in ("width", "height"):  # bounded: a 100000 x 100000 frame would be ~100 GB of buffers
            require_int("CameraConfig", name, getattr(self, name), lo=MIN_IMAGE_SIDE, hi=MAX_IMAGE_SIDE)
        if len(self.position) != 3 or not np.all(np.isfinite(self.position)):
            raise ValueError(f"position must be 3 finite numbers, got {self.position}")
        if not 1.0 <= self.fov_y_deg <= 150.0:
            raise ValueError(f"fov_y_deg must be in [1, 150], got {self.fov_y_deg}")
        if not 0 < self.near < self.far:
            raise ValueError(f"need 0 < near < far, got near={self.near}, far={self.far}")
        if not (math.isfinite(self.depth_noise_std) and self.depth_noise_std >= 0):
            raise ValueError(f"depth_noise_std must be >= 0, got {self.depth_noise_std}")
        if not 0 <= self.dropout_prob < 1:
            raise ValueError(f"dropout_prob must be in [0, 1), got {self.dropout_prob}")
        if self.renderer not in RENDERERS:
            raise ValueError(f"renderer must be one of {RENDERERS}, got {self.renderer!r}")
        if self.normal_method not in NORMAL_METHODS:
            raise ValueError(f"normal_method must be one of {NORMAL_METHODS}, got {self.normal_method!r}")
        if not isinstance(self.normal_knn, int) or self.normal_knn < 3:
            raise ValueError(f"normal_knn must be an int >= 3, got {self.normal_knn!r}")

    @property
    def aspect(self) -> float:
        return self.width / self.height

    @classmethod
    def for_bin(cls, spec: BinSpec, height_above_floor: float = 1.4, margin: float = 1.15, **kwargs) -> "CameraConfig":
        """A config centred over ``spec`` whose view covers the bin's outer rim with ``margin``."""
        width, height = kwargs.get("width", cls.width), kwargs.get("height", cls.height)
        rim_distance = height_above_floor - spec.wall_height
        if rim_distance <= 0:
            raise ValueError("the camera must be above the bin walls")
        half_x = (spec.inner_size[0] / 2 + spec.wall_thickness) * margin
        half_y = (spec.inner_size[1] / 2 + spec.wall_thickness) * margin
        half_y_needed = max(half_y, half_x * height / width)
        fov = 2 * math.degrees(math.atan(half_y_needed / rim_distance))
        position = (spec.center_xy[0], spec.center_xy[1], spec.floor_z + height_above_floor)
        return cls(position=position, fov_y_deg=fov, **kwargs)
