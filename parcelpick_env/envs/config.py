"""Every option of ParcelPick-v0, with its default, in one place.

``gym.make("ParcelPick-v0", **kwargs)`` passes keyword arguments straight to ``EnvConfig``, so any
field here can be set from the command line tools. The cup radius ``r`` and material constant ``k``
of the Dex-Net 3.0 holding check come from ``suction`` (one definition shared with the labels).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Any, Callable

from parcelpick_env.camera.config import CameraConfig
from parcelpick_env.config_checks import (require, require_choice, require_int, require_positive_ints,
                                          require_positive_numbers)
from parcelpick_env.robot.arm import ArmConfig
from parcelpick_env.scene.config import PileConfig, check_pile_fields
from parcelpick_env.scene.scene import BinSpec
from parcelpick_env.sim.config import SimConfig
from parcelpick_env.suction.config import CELL_CUP_RADIUS, SuctionConfig
from parcelpick_env.suction.cup import CARRY_LOAD_TARGET, CupSpec

# "pose_push": a pose action plus a seventh number whose sign chooses a pick (>= 0) or a parting push (< 0),
# envs/push.py
ACTION_MODES: tuple[str, ...] = ("pose", "pixel", "pose_push")
# What the env observes (envs/observation.py): the camera cloud and images, the images only, or the
# privileged ground truth (state_dict, for the oracle and state-based RL only).
OBS_MODES: tuple[str, ...] = ("pointcloud", "rgbd", "state_dict")
ENV_CUP_RADIUS = CELL_CUP_RADIUS  # m: the 40 mm bellows cup (suction/config.py, docs/cell.md); see EnvConfig.suction


@dataclass(frozen=True)
class GraspConfig:
    """The physical pick (docs/cell.md; moves in ``grasp.py``, the cup's holding model in ``suction/cup.py``)."""

    cup: CupSpec = field(default_factory=CupSpec)  # vacuum, lip friction, hold-break and strike rules
    # contact seal quality below this holds nothing: the lip leaks so much that the ejector builds less than
    # 30% of its vacuum (CupSpec's leakage law, 17.6 kPa at 0.2); above it the leak-reduced vacuum decides
    seal_threshold: float = 0.2
    carry_dt: float = 1.0 / 60.0  # s, physics step while carrying (the pile sleeps, Simulator.asleep)
    # s, physics step while lifting: the pile is awake, and at 60 Hz a mailer sliding off the rising parcel at
    # 1 m/s sinks 17 mm in one step and falls through the 2 cm floor (docs/cell.md, 'Tunnelling')
    lift_dt: float = 1.0 / 120.0
    carry_solver_iterations: int = 20
    carry_load_target: float = CARRY_LOAD_TARGET  # the carry is timed so no predicted ring load exceeds this share of capacity
    min_carry_acceleration: float = 0.1  # m/s^2: floor of that timing (a parcel loaded past the target still moves)
    carry_speed: float = 0.5  # m/s peak tool speed while carrying
    seal_dwell: float = 0.05  # s holding still after contact while the vacuum builds (not checked)
    pregrasp_distance: float = 0.02  # m along n above the target where the guarded approach starts
    overshoot: float = 0.02  # m beyond the target along -n where the approach gives up (no_contact)
    approach_speed: float = 0.15  # m/s peak tool speed on the guarded approach
    touch_force: float = 1.0  # N of cup contact that ends the guarded approach (the lip is on the surface)
    clearance: float = 0.05  # m the carried parcel's underside keeps above the pile top and the bin rim
    min_lift: float = 0.05  # m the lift rises at least
    # m: at the lift's start the tool moves the parcel this far off the walls and neighbours pressing it
    # sideways, while rising break_away_rise (a real bellows' sideways give; the simulated attachment is
    # rigid: grasp.PickExecutor._break_away)
    break_away: float = 0.003
    break_away_rise: float = 0.01
    hover_clearance: float = 0.05  # m above the highest obstacle near the pick for the hover point
    hover_corridor: float = 0.08  # m: obstacles whose footprint comes this close to the pick set the hover height
    ready_height: float = 0.60  # m above the bin floor: the cup above the bin centre, seeds IK
    drop_zone: tuple[float, float, float] = (0.50, -0.50, 0.45)  # tool-tip target outside the bin (z: at least)
    control_dt_free: float = 1.0 / 30.0  # s between control waypoints of free-space moves
    max_post_settle_steps: int = 240  # cap on settling the pile after an attempt
    trace_interval: float = 1.0 / 15.0  # s of simulated time between arm/parcel poses kept for replays
    # the parting push (action_mode="pose_push", envs/push.py): the tool, vacuum off, pushes this far sideways
    push_distance: float = 0.10  # m of tool travel from where its descent ends
    push_speed: float = 0.15  # m/s peak tool speed while pushing
    push_touch_force: float = 5.0  # N on the tool that ends the push's descent (it has met something)
    push_max_force: float = 60.0  # N on the tool that ends the push early (a parcel jammed against a wall)

    def __post_init__(self) -> None:
        if isinstance(self.cup, dict):  # a stored config (dataclasses.asdict) nests it as a dict
            object.__setattr__(self, "cup", CupSpec(**self.cup))
        require(isinstance(self.cup, CupSpec), "GraspConfig", f"cup must be a CupSpec, got {type(self.cup).__name__}")
        require(0.0 <= self.seal_threshold <= 1.0, "GraspConfig",
                f"seal_threshold must be in [0, 1], got {self.seal_threshold}")
        require_positive_numbers(self, ("pregrasp_distance", "overshoot", "approach_speed", "touch_force", "clearance",
                                        "hover_clearance", "hover_corridor", "control_dt_free", "trace_interval",
                                        "seal_dwell", "carry_dt", "lift_dt", "ready_height", "carry_load_target",
                                        "min_carry_acceleration", "carry_speed", "min_lift", "break_away",
                                        "break_away_rise", "push_distance", "push_speed", "push_touch_force",
                                        "push_max_force"))
        require(self.carry_dt <= 0.05, "GraspConfig", f"carry_dt must be <= 0.05 s, got {self.carry_dt}")
        require(self.lift_dt <= 0.05, "GraspConfig", f"lift_dt must be <= 0.05 s, got {self.lift_dt}")
        require(self.carry_load_target < 1.0, "GraspConfig",
                f"carry_load_target must be < 1 (a share of capacity), got {self.carry_load_target}")
        require_positive_ints(self, ("carry_solver_iterations",))
        require_int("GraspConfig", "max_post_settle_steps", self.max_post_settle_steps, lo=0)
        if len(self.drop_zone) != 3 or not all(math.isfinite(v) for v in self.drop_zone):
            raise ValueError(f"drop_zone must be 3 finite numbers, got {self.drop_zone}")


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
    obs_mode: str = "pointcloud"  # one of OBS_MODES; "state_dict" is privileged (envs/observation.py)
    num_points: int = 4096  # fixed N of the observed cloud (sampled or padded); Diffusion-Suction's CPU preset size
    bin: BinSpec = field(default_factory=BinSpec)
    heavy_first_mass: float | None = PileConfig.heavy_first_mass  # stacked induction order (PileConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    # The physical cup: a 40 mm bellows cup (r = 20 mm, suction/cup.py), rated V = dP*pi*r^2 / S (50 N at
    # 60 kPa, S = 1.5), judged by its bellows seal model (the one PickExecutor's contact seal uses, so a
    # policy reading info['suction'] scores candidates with the cell's own cup). SuctionNet's 10 mm spring
    # convention (docs/labels.md) stays the dataset labels' cup.
    suction: SuctionConfig = field(default_factory=lambda: SuctionConfig(cup_radius=ENV_CUP_RADIUS,
                                                                         seal_model="bellows"))
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
    max_pushes: int = 10  # parting pushes an episode allows (action_mode="pose_push"); more are invalid actions

    def __post_init__(self) -> None:
        owner = "EnvConfig"
        check_pile_fields(self)
        require_choice(owner, "action_mode", self.action_mode, ACTION_MODES)
        require_choice(owner, "obs_mode", self.obs_mode, OBS_MODES)
        require_positive_ints(self, ("num_points", "max_consecutive_failures", "record_points"))
        if self.max_attempts is not None:
            require_int(owner, "max_attempts", self.max_attempts, lo=1)
        require_int(owner, "max_pushes", self.max_pushes, lo=0)
        require(self.action_margin >= 0, owner, f"action_margin must be >= 0, got {self.action_margin!r}")
        require(self.record_dir is None or isinstance(self.record_dir, (str, os.PathLike)), owner,
                f"record_dir must be a directory path (str) or None, got {self.record_dir!r}")
        for name, cls in (("bin", BinSpec), ("camera", CameraConfig), ("suction", SuctionConfig),
                          ("grasp", GraspConfig), ("arm", ArmConfig), ("sim", SimConfig)):
            require(isinstance(getattr(self, name), cls), owner,
                    f"{name} must be a {cls.__name__}, got {type(getattr(self, name)).__name__}")
        require(self.scene_factory is None or callable(self.scene_factory), owner,
                "scene_factory must be callable (sim, seed) -> Scene")

    @property
    def attempt_limit(self) -> int:
        return self.max_attempts if self.max_attempts is not None else 2 * self.num_parcels + 3
