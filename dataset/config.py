"""What one dataset generation run produces: every knob in one validated dataclass.

The config is stored in each dataset's manifest, so a resumed run can refuse to mix shards made
under different settings, and a reader can tell how the labels were made.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from parcelpick_env.camera.config import MAX_IMAGE_SIDE, MIN_IMAGE_SIDE
from parcelpick_env.config_checks import (
    config_from_dict,
    config_to_dict,
    require,
    require_choice,
    require_int,
    require_positive_ints,
)
from parcelpick_env.suction.config import SuctionConfig
from parcelpick_env.suction.label_sets import LABEL_SETS

SPLITS = ("train", "test")
LAYOUTS = ("stacked", "scattered")
OBJECT_SETS = ("rectangular", "planar", "cylindrical", "mixed")
RANDOM = "random"
COMPRESSIONS = ("gzip", "lzf")
MAX_PARCELS = 50


@dataclass(frozen=True)
class GenerationConfig:
    """Settings of one generation run.

    ``layout``/``object_set`` may be ``"random"``: each scene then draws one uniformly from its seed.
    ``rgb_noise_std`` is a (min, max) range in 8-bit intensity levels; each scene draws its own
    strength from it, so models see a range of sensor quality. Camera fields left ``None`` keep the
    camera module's defaults. ``fps_presample`` bounds farthest-point sampling cost: the cloud is first
    reduced uniformly at random to ``fps_presample * annotation_points`` points (0 disables this).
    ``labels`` picks the channel set (docs/labels.md, "Label sets"): ``"paper"``, the paper's four channels with
    the scorer config ``suction``; or ``"physical"``, whether the env's own cup would hold each pick
    (``parcelpick_env.suction.quality.PhysicalCell``: the env's cup, real masses; ``suction`` is then unused).
    ``extra_labels`` stores more sets beside it, as ``labels_<set>`` and ``score_<set>`` (test sets carry both, so
    the AP's label oracle reads the set that matches each quality definition).
    """

    scenes: int = 1000
    split: str = "train"
    seed: int = 0
    min_parcels: int = 1
    max_parcels: int = MAX_PARCELS
    layout: str = RANDOM
    object_set: str = RANDOM
    annotation_points: int = 16384
    fps_presample: float = 2.0
    crop_to_bin: bool = True
    width: int = 640
    height: int = 480
    depth_noise_std: float | None = None
    dropout_prob: float | None = None
    renderer: str | None = None
    rgb_noise_std: tuple[float, float] = (0.0, 6.0)
    store_images: bool = True
    library_seed: int = 0
    scenes_per_shard: int = 100
    compression: str = "gzip"
    compression_level: int = 4
    suction: SuctionConfig = field(default_factory=SuctionConfig)
    labels: str = "paper"
    extra_labels: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        owner = "GenerationConfig"
        require_positive_ints(self, ("scenes", "annotation_points", "width", "height", "scenes_per_shard"))
        require_int(owner, "seed", self.seed, lo=0)
        require_int(owner, "library_seed", self.library_seed, lo=0)
        require_int(owner, "compression_level", self.compression_level, 0, 9)
        require_int(owner, "min_parcels", self.min_parcels, 1, MAX_PARCELS)
        require_int(owner, "max_parcels", self.max_parcels, self.min_parcels, MAX_PARCELS)
        require_choice(owner, "split", self.split, SPLITS)
        require_choice(owner, "layout", self.layout, LAYOUTS + (RANDOM,))
        require_choice(owner, "object_set", self.object_set, OBJECT_SETS + (RANDOM,))
        require(np.isfinite(self.fps_presample) and (self.fps_presample == 0 or self.fps_presample >= 1), owner,
                f"fps_presample must be 0 (off) or >= 1, got {self.fps_presample}")
        for name in ("width", "height"):  # the camera's own bounds, checked here before any worker starts
            require_int(owner, name, getattr(self, name), lo=MIN_IMAGE_SIDE, hi=MAX_IMAGE_SIDE)
        require(self.width * self.height >= self.annotation_points, owner,
                f"{self.width}x{self.height} image has fewer pixels than annotation_points={self.annotation_points}")
        require(self.depth_noise_std is None or (np.isfinite(self.depth_noise_std) and self.depth_noise_std >= 0),
                owner, f"depth_noise_std must be >= 0, got {self.depth_noise_std}")
        require(self.dropout_prob is None or 0.0 <= self.dropout_prob < 1.0, owner,
                f"dropout_prob must be in [0, 1), got {self.dropout_prob}")
        require_choice(owner, "renderer", self.renderer, (None, "auto", "egl", "tiny"))
        try:
            lo, hi = (float(x) for x in self.rgb_noise_std)
        except (TypeError, ValueError):
            lo, hi = np.nan, np.nan
        require(np.isfinite(lo) and np.isfinite(hi) and 0.0 <= lo <= hi, owner,
                f"rgb_noise_std must be a range (min, max) with 0 <= min <= max, got {self.rgb_noise_std!r}")
        require_choice(owner, "compression", self.compression, COMPRESSIONS)
        require_choice(owner, "labels", self.labels, LABEL_SETS)
        object.__setattr__(self, "extra_labels", tuple(self.extra_labels))
        for extra in self.extra_labels:
            require_choice(owner, "extra_labels", extra, LABEL_SETS)
        require(self.labels not in self.extra_labels and len(set(self.extra_labels)) == len(self.extra_labels), owner,
                f"extra_labels must not repeat a set or the main one ({self.labels!r}), got {self.extra_labels!r}")
        require(isinstance(self.suction, SuctionConfig), owner,
                f"suction must be a SuctionConfig, got {type(self.suction)}")

    @property
    def num_shards(self) -> int:
        return -(-self.scenes // self.scenes_per_shard)

    def shard_range(self, shard: int) -> range:
        """Scene indices held by ``shard``; fixed by the config so a resumed run rebuilds the same shards."""
        if not 0 <= shard < self.num_shards:
            raise ValueError(f"shard {shard} out of range 0..{self.num_shards - 1}")
        start = shard * self.scenes_per_shard
        return range(start, min(start + self.scenes_per_shard, self.scenes))

    def scene_seed(self, scene_index: int) -> int:
        """Per-scene seed from (base seed, split, index) alone, so any backend or worker count agrees."""
        if not 0 <= scene_index < self.scenes:
            raise ValueError(f"scene_index {scene_index} out of range 0..{self.scenes - 1}")
        entropy = [self.seed, SPLITS.index(self.split), scene_index]
        return int(np.random.SeedSequence(entropy).generate_state(1, dtype=np.uint64)[0] >> np.uint64(1))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready, as stored in the manifest (which a resumed run compares against)."""
        return config_to_dict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> GenerationConfig:
        return config_from_dict(cls, data, nested={"suction": SuctionConfig})
