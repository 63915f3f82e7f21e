"""How a pile is made: parcel count, layout, object set, split, bin and the randomisation ranges."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from parcelpick_env.assets.library import OBJECT_SETS, SPLITS
from parcelpick_env.config_checks import require_choice, require_int
from parcelpick_env.scene.scene import BinSpec

LAYOUTS: tuple[str, ...] = ("stacked", "scattered")
MAX_PARCELS = 50


def check_pile_fields(config: Any) -> None:
    """``num_parcels``, ``layout``, ``object_set`` and ``split`` of any config that describes a pile.

    ``EnvConfig`` calls this too, so a bad value fails when the env is configured rather than at its first
    reset, and both configs share one set of limits.
    """
    owner = type(config).__name__
    require_int(owner, "num_parcels", config.num_parcels, 1, MAX_PARCELS)
    require_choice(owner, "layout", config.layout, LAYOUTS)
    require_choice(owner, "object_set", config.object_set, OBJECT_SETS)
    require_choice(owner, "split", config.split, SPLITS)


@dataclass(frozen=True)
class PileConfig:
    """Pile generation settings (DESIGN.md, 'Scenes').

    ``stacked`` drops the parcels, with random orientations, from a staggered column above the bin
    so they fall into a pile together; ``drop_height`` is the extra gap added above each parcel's
    non-overlapping start slot. ``scattered`` lays them flat-side down without footprint overlap
    (``scatter_gap`` apart) and only lets them settle. Friction is uniform in ``friction_range``.
    A stacked pile re-drops parcels that bounced out of the bin up to ``redrop_rounds`` times; what
    still ends outside is removed and listed in ``scene.meta``.
    """

    num_parcels: int = 10
    layout: str = "stacked"
    object_set: str = "mixed"
    split: str = "train"
    bin: BinSpec = field(default_factory=BinSpec)
    friction_range: tuple[float, float] = (0.3, 1.0)
    drop_height: float = 0.05  # m above the non-overlapping start slot
    scatter_gap: float = 0.01  # m between scattered footprints
    scatter_flat_prob: float = 0.85  # probability of resting on the largest face when scattered
    scatter_attempts: int = 200  # rejection-sampling tries per parcel before giving up on it
    redrop_rounds: int = 2  # stacked: parcels that fell out are dropped onto the pile again, this often
    max_settle_steps: int | None = None  # None: the simulator's SimConfig.max_settle_steps

    def __post_init__(self) -> None:
        check_pile_fields(self)
        if not isinstance(self.bin, BinSpec):
            raise ValueError(f"bin must be a BinSpec, got {type(self.bin).__name__}")
        lo, hi = self.friction_range
        if not (0 <= lo <= hi <= 5):
            raise ValueError(f"friction_range must satisfy 0 <= low <= high <= 5, got {self.friction_range}")
        if not 0 <= self.drop_height <= 2:
            raise ValueError(f"drop_height must be in [0, 2] m, got {self.drop_height}")
        if not 0 <= self.scatter_gap <= 0.2:
            raise ValueError(f"scatter_gap must be in [0, 0.2] m, got {self.scatter_gap}")
        if not 0 <= self.scatter_flat_prob <= 1:
            raise ValueError(f"scatter_flat_prob must be in [0, 1], got {self.scatter_flat_prob}")
        require_int("PileConfig", "scatter_attempts", self.scatter_attempts, lo=1)
        require_int("PileConfig", "redrop_rounds", self.redrop_rounds, 0, 10)
        if self.max_settle_steps is not None:
            require_int("PileConfig", "max_settle_steps", self.max_settle_steps, lo=1)
