"""What one dataset generation run produces: every knob in one validated dataclass.

The config is stored in each dataset's manifest, so a resumed run can refuse to mix shards made
under different settings, and a reader can tell how the labels were made.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from parcelpick_env.suction.config import SuctionConfig

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

    def __post_init__(self) -> None:
        def need(ok: bool, message: str) -> None:
            if not ok:
                raise ValueError(f"GenerationConfig: {message}")

        for name in ("scenes", "seed", "min_parcels", "max_parcels", "annotation_points", "width", "height",
                     "library_seed", "scenes_per_shard", "compression_level"):
            value = getattr(self, name)
            need(isinstance(value, (int, np.integer)) and not isinstance(value, bool),
                 f"{name} must be an integer, got {value!r}")
        need(self.scenes >= 1, f"scenes must be >= 1, got {self.scenes}")
        need(self.seed >= 0, f"seed must be >= 0, got {self.seed}")
        need(self.split in SPLITS, f"split must be one of {SPLITS}, got {self.split!r}")
        need(1 <= self.min_parcels <= self.max_parcels <= MAX_PARCELS,
             f"need 1 <= min_parcels <= max_parcels <= {MAX_PARCELS}, got {self.min_parcels}..{self.max_parcels}")
        need(self.layout in LAYOUTS + (RANDOM,), f"layout must be one of {LAYOUTS + (RANDOM,)}, got {self.layout!r}")
        need(self.object_set in OBJECT_SETS + (RANDOM,),
             f"object_set must be one of {OBJECT_SETS + (RANDOM,)}, got {self.object_set!r}")
        need(self.annotation_points >= 1, f"annotation_points must be >= 1, got {self.annotation_points}")
        need(np.isfinite(self.fps_presample) and (self.fps_presample == 0 or self.fps_presample >= 1),
             f"fps_presample must be 0 (off) or >= 1, got {self.fps_presample}")
        need(self.width >= 8 and self.height >= 8, f"image must be at least 8x8, got {self.width}x{self.height}")
        need(self.width * self.height >= self.annotation_points,
             f"{self.width}x{self.height} image has fewer pixels than annotation_points={self.annotation_points}")
        need(self.depth_noise_std is None or (np.isfinite(self.depth_noise_std) and self.depth_noise_std >= 0),
             f"depth_noise_std must be >= 0, got {self.depth_noise_std}")
        need(self.dropout_prob is None or 0.0 <= self.dropout_prob < 1.0,
             f"dropout_prob must be in [0, 1), got {self.dropout_prob}")
        need(self.renderer in (None, "auto", "egl", "tiny"),
             f"renderer must be None (camera default), 'auto', 'egl' or 'tiny', got {self.renderer!r}")
        try:
            lo, hi = (float(x) for x in self.rgb_noise_std)
        except (TypeError, ValueError):
            lo, hi = np.nan, np.nan
        need(np.isfinite(lo) and np.isfinite(hi) and 0.0 <= lo <= hi,
             f"rgb_noise_std must be a range (min, max) with 0 <= min <= max, got {self.rgb_noise_std!r}")
        need(self.library_seed >= 0, f"library_seed must be >= 0, got {self.library_seed}")
        need(self.scenes_per_shard >= 1, f"scenes_per_shard must be >= 1, got {self.scenes_per_shard}")
        need(self.compression in COMPRESSIONS, f"compression must be one of {COMPRESSIONS}, got {self.compression!r}")
        need(0 <= self.compression_level <= 9, f"compression_level must be in 0..9, got {self.compression_level}")
        need(isinstance(self.suction, SuctionConfig), f"suction must be a SuctionConfig, got {type(self.suction)}")

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
        out = dataclasses.asdict(self)
        out["rgb_noise_std"] = list(self.rgb_noise_std)
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> GenerationConfig:
        data = dict(data)
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"GenerationConfig: unknown keys {sorted(unknown)}")
        if "suction" in data and isinstance(data["suction"], dict):
            data["suction"] = SuctionConfig(**data["suction"])
        if "rgb_noise_std" in data:
            data["rgb_noise_std"] = tuple(data["rgb_noise_std"])
        return cls(**data)
