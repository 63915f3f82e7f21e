"""Every option of ParcelPick-v0, with its default, in one place.

``gym.make("ParcelPick-v0", **kwargs)`` passes keyword arguments straight to ``EnvConfig``, so any
field here can be set from the command line tools. The cup radius ``r`` and material constant ``k``
of the Dex-Net 3.0 holding check come from ``suction`` (one definition shared with the labels).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

from parcelpick_env.camera.config import CameraConfig
from parcelpick_env.config_checks import (require, require_choice, require_int, require_positive_ints,
                                          require_positive_numbers)
from parcelpick_env.robot.arm import ArmConfig
from parcelpick_env.scene.config import check_pile_fields
from parcelpick_env.scene.scene import BinSpec
from parcelpick_env.sim.config import SimConfig
from parcelpick_env.suction.config import SuctionConfig

ACTION_MODES: tuple[str, ...] = ("pose", "pixel")
ENV_CUP_RADIUS = 0.020  # m; see EnvConfig.suction


@dataclass(frozen=True)
class GraspConfig:
    """The physical pick (DESIGN.md, 'Physical grasp check inside the environment')."""

    seal_threshold: float = 0.5  # S_seal at the actual contact below this holds nothing
    vacuum_kpa: float = 60.0  # dP; V = dP * pi * r^2 (about 19 N at r = 10 mm)
    cup_friction: float = 0.5  # mu of the cup lip on parcel surfaces
    violation_steps: int = 3  # a wrench violation lasting this many carry steps breaks the seal
    carry_dt: float = 1.0 / 60.0  # s, physics step while lifting and carrying (the pile sits still)
    carry_solver_iterations: int = 20
    seal_dwell: float = 0.05  # s holding still after contact while the vacuum builds (not checked)
    pregrasp_distance: float = 0.04  # m along n above the target where the guarded approach starts
    overshoot: float = 0.02  # m beyond the target along -n where the approach gives up (no_contact)
    approach_speed: float = 0.15  # m/s peak tool speed on the guarded approach
    lift_speed: float = 0.3  # m/s peak tool speed on the vertical lift
    clearance: float = 0.05  # m the carried parcel must clear above the bin rim
    hover_clearance: float = 0.08  # m above the rim for the hover point before descending
    ready_height: float = 0.60  # m above the bin floor: the cup above the bin centre, clear of most piles
    drop_zone: tuple[float, float, float] = (0.50, -0.50, 0.45)  # tool-tip target outside the bin
    control_dt_free: float = 1.0 / 30.0  # s between checked waypoints of free-space moves
    max_post_settle_steps: int = 240  # cap on settling the pile after an attempt
    trace_interval: float = 1.0 / 15.0  # s of simulated time between arm/parcel poses kept for replays

    def __post_init__(self) -> None:
        if not 0.0 <= self.seal_threshold <= 1.0:
            raise ValueError(f"seal_threshold must be in [0, 1], got {self.seal_threshold}")
        require_positive_numbers(self, ("vacuum_kpa", "cup_friction", "pregrasp_distance", "overshoot",
                                        "approach_speed", "lift_speed", "clearance", "hover_clearance",
                                        "control_dt_free", "trace_interval", "seal_dwell", "carry_dt", "ready_height"))
        require(self.carry_dt <= 0.05, "GraspConfig", f"carry_dt must be <= 0.05 s, got {self.carry_dt}")
        require_positive_ints(self, ("carry_solver_iterations", "violation_steps"))
        require_int("GraspConfig", "max_post_settle_steps", self.max_post_settle_steps, lo=0)
        if len(self.drop_zone) != 3 or not all(math.isfinite(v) for v in self.drop_zone):
            raise ValueError(f"drop_zone must be 3 finite numbers, got {self.drop_zone}")

    def vacuum_force(self, cup_radius: float) -> float:
        """V = dP * pi * r^2, newtons."""
        return self.vacuum_kpa * 1e3 * math.pi * cup_radius**2


@dataclass(frozen=True)
class EnvConfig:
    """ParcelPick-v0 options.

    ``scene_factory`` (tests, known-answer scenes): a callable ``(sim, seed) -> Scene`` used instead
    of ``build_pile``; ``reset(options={'scene_factory': f})`` overrides it for one episode.
    """

    object_set: str = "mixed"
    layout: str = "stacked"
    num_parcels: int = 10
    split: str = "train"
    action_mode: str = "pose"
    num_points: int = 4096  # fixed N of the observed cloud (sampled or padded); Diffusion-Suction's CPU preset size
    bin: BinSpec = field(default_factory=BinSpec)
    camera: CameraConfig = field(default_factory=CameraConfig)
    # The physical cup: 20 mm radius (a common 40 mm parcel cup), so V = dP*pi*r^2 (75 N at 60 kPa) can
    # lift the heaviest 5 kg parcels when picked near their centre of mass. DESIGN's 10 mm (SuctionNet's
    # labelling convention) would cap every pick at 1.9 kg; the dataset labels keep 10 mm.
    suction: SuctionConfig = field(default_factory=lambda: SuctionConfig(cup_radius=ENV_CUP_RADIUS))
    grasp: GraspConfig = field(default_factory=GraspConfig)
    arm: ArmConfig = field(default_factory=ArmConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    max_attempts: int | None = None  # None: 2 * num_parcels + 3
    max_consecutive_failures: int = 3
    record_dir: str | None = None  # one rerun .rrd per episode when set
    record_points: int = 4096  # cap on cloud points logged per frame in replays
    asset_seed: int = 0  # which procedural asset library
    scene_factory: Callable[..., Any] | None = None
    action_margin: float = 0.05  # m: pose actions may lie this far outside the bin's inner box

    def __post_init__(self) -> None:
        owner = "EnvConfig"
        check_pile_fields(self)
        require_choice(owner, "action_mode", self.action_mode, ACTION_MODES)
        require_positive_ints(self, ("num_points", "max_consecutive_failures", "record_points"))
        if self.max_attempts is not None:
            require_int(owner, "max_attempts", self.max_attempts, lo=1)
        require(self.action_margin >= 0, owner, f"action_margin must be >= 0, got {self.action_margin!r}")
        for name, cls in (("bin", BinSpec), ("camera", CameraConfig), ("suction", SuctionConfig),
                          ("grasp", GraspConfig), ("arm", ArmConfig), ("sim", SimConfig)):
            require(isinstance(getattr(self, name), cls), owner,
                    f"{name} must be a {cls.__name__}, got {type(getattr(self, name)).__name__}")
        require(self.scene_factory is None or callable(self.scene_factory), owner,
                "scene_factory must be callable (sim, seed) -> Scene")

    @property
    def attempt_limit(self) -> int:
        return self.max_attempts if self.max_attempts is not None else 2 * self.num_parcels + 3
