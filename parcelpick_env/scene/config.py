"""How a pile is made: parcel count, layout, object set, split, bin and the randomisation ranges."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from parcelpick_env.assets.library import OBJECT_SETS, SPLITS
from parcelpick_env.config_checks import require, require_choice, require_finite_numbers, require_int
from parcelpick_env.scene.scene import BinSpec

LAYOUTS: tuple[str, ...] = ("stacked", "scattered")
MAX_PARCELS = 50
MAX_FRICTION = 5.0  # the largest parcel friction coefficient a pile may draw (and the state_dict's bound)


def check_pile_fields(config: Any) -> None:
    """``num_parcels``, ``layout``, ``object_set``, ``split`` and ``heavy_first_mass`` of any config that describes a
    pile.

    ``EnvConfig`` calls this too, so a bad value fails when the env is configured rather than at its first
    reset, and both configs share one set of limits.
    """
    owner = type(config).__name__
    require_int(owner, "num_parcels", config.num_parcels, 1, MAX_PARCELS)
    require_choice(owner, "layout", config.layout, LAYOUTS)
    require_choice(owner, "object_set", config.object_set, OBJECT_SETS)
    require_choice(owner, "split", config.split, SPLITS)
    if config.heavy_first_mass is not None:
        require_finite_numbers(config, ("heavy_first_mass",))
        require(config.heavy_first_mass >= 0, owner, f"heavy_first_mass must be >= 0 kg, got {config.heavy_first_mass!r}")


@dataclass(frozen=True)
class PileConfig:
    """Pile generation settings (docs/piles.md: the figures and their reasons).

    ``stacked`` drops the parcels, with random orientations, from staggered start slots inside
    temporary chute walls that continue the bin's walls up to ``chute_height`` (m above the floor);
    the chute is removed once the heap is at rest, and what then slides out is ``lost``.
    ``drop_height`` is the gap added above each parcel's non-overlapping start slot.
    ``scattered`` lays them flat-side down without footprint overlap (``scatter_gap`` apart) and only
    lets them settle; beyond the bin's capacity (``pile.SCATTER_CAPACITY`` in the default bin) parcels
    that find no room are ``skipped``. Friction is uniform in ``friction_range``.
    """

    num_parcels: int = 10
    layout: str = "stacked"
    object_set: str = "mixed"
    split: str = "train"
    bin: BinSpec = field(default_factory=BinSpec)
    friction_range: tuple[float, float] = (0.3, 1.0)
    drop_height: float = 0.02  # m above the non-overlapping start slot
    stack_tilt_deg: float = 25.0  # stacked: std of the tumble away from lying on a face, degrees
    chute_height: float = 0.60  # m above the floor: top of the temporary chute walls (raised if the slots need it)
    scatter_gap: float = 0.01  # m between scattered footprints
    scatter_flat_prob: float = 0.85  # probability of resting on the largest face when scattered
    scatter_yaw_jitter_deg: float = 15.0  # scattered parcels lie square to the walls, give or take this
    # stacked: parcels heavier than this (kg) go down the chute first, as an infeed scale can route a heavy
    # class; None keeps the drawn order (docs/piles.md, 'Heavy parcels first')
    heavy_first_mass: float | None = None
    max_settle_steps: int | None = None  # None: the simulator's SimConfig.max_settle_steps

    def __post_init__(self) -> None:
        check_pile_fields(self)
        if not isinstance(self.bin, BinSpec):
            raise ValueError(f"bin must be a BinSpec, got {type(self.bin).__name__}")
        lo, hi = self.friction_range
        if not (0 <= lo <= hi <= MAX_FRICTION):
            raise ValueError(f"friction_range must satisfy 0 <= low <= high <= {MAX_FRICTION:g}, "
                             f"got {self.friction_range}")
        if not 0 <= self.drop_height <= 2:
            raise ValueError(f"drop_height must be in [0, 2] m, got {self.drop_height}")
        if not 0 <= self.scatter_gap <= 0.2:
            raise ValueError(f"scatter_gap must be in [0, 0.2] m, got {self.scatter_gap}")
        if not 0 <= self.scatter_flat_prob <= 1:
            raise ValueError(f"scatter_flat_prob must be in [0, 1], got {self.scatter_flat_prob}")
        if not 0 <= self.scatter_yaw_jitter_deg <= 45:
            raise ValueError(f"scatter_yaw_jitter_deg must be in [0, 45], got {self.scatter_yaw_jitter_deg}")
        if not 0 <= self.stack_tilt_deg <= 180:
            raise ValueError(f"stack_tilt_deg must be in [0, 180], got {self.stack_tilt_deg}")
        if not self.bin.wall_height < self.chute_height <= 3:
            raise ValueError(f"chute_height must be above the bin's walls ({self.bin.wall_height} m) and "
                             f"at most 3 m, got {self.chute_height}")
        if self.max_settle_steps is not None:
            require_int("PileConfig", "max_settle_steps", self.max_settle_steps, lo=1)
