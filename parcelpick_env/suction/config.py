"""Every constant of suction scoring, in one place (DESIGN.md, 'Suction scoring')."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True)
class SuctionConfig:
    cup_radius: float = 0.010  # r, metres
    rim_vertices: int = 72
    seal_model: Literal["spring", "suctionnet"] = "spring"
    obstruction_height: float = 0.005  # surface inside the cup disk this far above p breaks the seal
    ray_offset: float = 0.05  # rim rays start this far above the candidate along n
    max_ray_depth: float = 0.10  # a rim ray travelling further than this below the cup plane misses
    material_k: float = 15.6  # k in tau_thr = r * k * pi
    gravity: float = 9.8
    unit_mass: float = 1.0
    tool_radius: float = 0.010  # collision cylinder radius
    tool_near: float = 0.010  # cylinder starts this far from p along n
    tool_far: float = 0.100  # and ends here
    body_radius: float = 0.0  # optional wider tool body above the cylinder; 0 disables it
    body_near: float = 0.100
    body_far: float = 0.300
    num_threads: int = 0  # Open3D ray-casting threads; 0 uses every core (set 1 in parallel workers)

    def __post_init__(self) -> None:
        positive = {
            "cup_radius": self.cup_radius, "material_k": self.material_k, "gravity": self.gravity,
            "unit_mass": self.unit_mass, "tool_radius": self.tool_radius, "ray_offset": self.ray_offset,
            "max_ray_depth": self.max_ray_depth,
        }
        for name, value in positive.items():
            if not value > 0:
                raise ValueError(f"SuctionConfig.{name} must be > 0, got {value!r}")
        if self.rim_vertices < 8:
            raise ValueError(f"SuctionConfig.rim_vertices must be >= 8, got {self.rim_vertices}")
        if self.seal_model not in ("spring", "suctionnet"):
            raise ValueError(f"SuctionConfig.seal_model must be 'spring' or 'suctionnet', got {self.seal_model!r}")
        if not 0 <= self.tool_near < self.tool_far:
            raise ValueError("SuctionConfig needs 0 <= tool_near < tool_far")
        threads = self.num_threads
        if isinstance(threads, bool) or not isinstance(threads, int) or threads < 0:
            raise ValueError(f"SuctionConfig.num_threads must be an int >= 0, got {self.num_threads!r}")
        if self.body_radius < 0 or (self.body_radius > 0 and not self.body_near < self.body_far):
            raise ValueError("SuctionConfig body_radius must be >= 0 with body_near < body_far")

    @property
    def torque_threshold(self) -> float:
        """tau_thr = r * k * pi (about 0.49 N m at r = 10 mm)."""
        import math

        return self.cup_radius * self.material_k * math.pi
