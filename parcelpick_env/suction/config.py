"""Every constant of suction scoring, in one place (docs/labels.md)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

from parcelpick_env.config_checks import require, require_finite_numbers, require_int, require_positive_numbers

SEAL_MODELS = ("spring", "suctionnet", "bellows")
# "paper": the paper's label wrench (norm of the bending torque about the COM, times the gravity-angle factor);
# "suctionnet": SuctionNet's evaluator (larger bending component about the surface centroid, no angle factor);
# "suctionnet_label": SuctionNet's lenient label-time wrench (docs/labels.md, "Wrench models").
WRENCH_MODELS = ("paper", "suctionnet", "suctionnet_label")
# The cell's physical cup: one 40 mm (r = 20 mm) 1.5-fold bellows cup (docs/cell.md, "Cup and vacuum").
# Sized for the parcel mix: it seals tubes down to R ~ 30 mm; the env, the tool URDF and the mass bound read it.
CELL_CUP_RADIUS = 0.020


@dataclass(frozen=True)
class BellowsCup:
    """The compliance of a single 1.5-fold bellows cup (docs/cup_seal.md), figures for a 40-50 mm cup.

    The lip radius is ``SuctionConfig.cup_radius`` (one cup radius shared by the seal, the wrench
    and the holding model); the cell uses ``CELL_CUP_RADIUS`` (20 mm) with these figures. Lengths in metres, angles in degrees.
    """

    stroke: float = 0.010  # axial compression the bellows takes up (lip pressed in, or surface rising into the cup)
    max_bend: float = 25.0  # lip tilt (deg) the bellows absorbs: the plane fitted to the rim vs the cup plane
    lip_compliance: float = 0.004  # +- out-of-plane give of lip and lowest fold about that plane (edges, curvature)
    leak_gap: float = 0.003  # leak tolerance: a lip this far above the surface at first touch no longer closes

    def __post_init__(self) -> None:
        require_positive_numbers(self, ("stroke", "max_bend", "lip_compliance", "leak_gap"))
        require(self.max_bend < 90.0, "BellowsCup", f"max_bend must be < 90 degrees, got {self.max_bend!r}")

    @property
    def max_bend_rad(self) -> float:
        return math.radians(self.max_bend)


@dataclass(frozen=True)
class SuctionConfig:
    cup_radius: float = 0.010  # r, metres
    rim_vertices: int = 72
    seal_model: Literal["spring", "suctionnet", "bellows"] = "spring"
    wrench_model: Literal["paper", "suctionnet", "suctionnet_label"] = "paper"
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
    bellows: BellowsCup = BellowsCup()  # the cup's compliance, read by seal_model "bellows" and contact_seal

    def __post_init__(self) -> None:
        if isinstance(self.bellows, Mapping):  # a stored config (dataclasses.asdict) nests it as a dict
            object.__setattr__(self, "bellows", BellowsCup(**self.bellows))
        if not isinstance(self.bellows, BellowsCup):
            raise ValueError(f"SuctionConfig.bellows must be a BellowsCup, got {type(self.bellows).__name__}")
        # Finite reals first (inf, NaN, strings and bools refused, each naming its field), then their relations.
        require_positive_numbers(self, ("cup_radius", "material_k", "gravity", "unit_mass", "tool_radius",
                                        "ray_offset", "max_ray_depth"))
        require_finite_numbers(self, ("obstruction_height", "tool_near", "tool_far", "body_radius", "body_near",
                                      "body_far"))
        require_int("SuctionConfig", "rim_vertices", self.rim_vertices, lo=8)
        if self.seal_model not in SEAL_MODELS:
            raise ValueError(f"SuctionConfig.seal_model must be one of {SEAL_MODELS}, got {self.seal_model!r}")
        if self.wrench_model not in WRENCH_MODELS:
            raise ValueError(f"SuctionConfig.wrench_model must be one of {WRENCH_MODELS}, got {self.wrench_model!r}")
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
        return self.cup_radius * self.material_k * math.pi
