"""Every knob of the Cao et al. (SuctionNet baseline) heatmap policy, in one validated dataclass.

The config is saved inside each checkpoint, so a checkpoint always rebuilds the network and the
pre-processing it was trained with.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from parcelpick_env.config_checks import (config_from_dict, config_to_dict, require, require_int,
                                          require_positive_ints, require_positive_numbers)

LABEL_CHANNELS = ("seal", "wrench", "collision", "visibility")  # order of the dataset's label columns


@dataclass(frozen=True)
class CaoConfig:
    """Network input size, backbone, target shapes, training and candidate extraction.

    ``input_height``/``input_width``: observations are resized to this before the network; the
    heatmaps are resized back to the observation for extraction. ``widths`` are the U-Net's channel
    counts per level (its depth is ``len(widths)``; the input size must divide by ``2**(len-1)``).
    ``seal_sigma_px``: the Gaussian splatted at each annotated point's pixel (network pixels).
    ``seal_channels``: label columns multiplied into the seal target (default: the seal score alone,
    as in SuctionNet's baseline). ``centre_sigma_scale``: the centre Gaussian's sigma as a fraction of
    an object's equivalent radius in pixels (sqrt(visible area / pi)), at least ``min_centre_sigma_px``.
    ``box_filter``/``grid_cell``/``grid_top_k``: the extraction shared with Normal-STD; the sizes are
    pixels of a ``reference_width``-wide image, scaled to the observation's width so they cover the
    same patch of the scene at any resolution.
    ``depth_scale``: metres of relief per unit of the normalised depth channel.
    ``colour``: False feeds the relief plane alone (an ablation: how much of the baseline's score comes from seeing
    colour, which the point-cloud methods do not).
    """

    input_height: int = 120
    input_width: int = 160
    widths: tuple[int, ...] = (8, 16, 32, 64)
    depth_scale: float = 0.10
    colour: bool = True
    seal_sigma_px: float = 2.0
    seal_channels: tuple[str, ...] = ("seal",)
    centre_sigma_scale: float = 0.5
    min_centre_sigma_px: float = 1.5
    box_filter: int = 15
    grid_cell: int = 10
    grid_top_k: int = 1024
    reference_width: int = 640
    nms_radius: float = 0.02
    # training
    epochs: int = 30
    batch_size: int = 8
    learning_rate: float = 2e-3
    weight_decay: float = 1e-4
    val_fraction: float = 0.1
    augment_flips: bool = True

    def __post_init__(self) -> None:
        owner = "CaoConfig"
        require_int(owner, "input_height", self.input_height, lo=8)
        require_int(owner, "input_width", self.input_width, lo=8)
        require(len(self.widths) >= 1 and all(isinstance(w, int) and w > 0 for w in self.widths), owner,
                f"widths must be positive integers, got {self.widths!r}")
        stride = 2 ** (len(self.widths) - 1)
        require(self.input_height % stride == 0 and self.input_width % stride == 0, owner,
                f"input {self.input_width}x{self.input_height} must divide by {stride} for {len(self.widths)} levels")
        require_positive_numbers(self, ("depth_scale", "seal_sigma_px", "centre_sigma_scale", "min_centre_sigma_px",
                                        "learning_rate", "nms_radius"))
        require(len(self.seal_channels) >= 1 and set(self.seal_channels) <= set(LABEL_CHANNELS), owner,
                f"seal_channels must be a non-empty subset of {LABEL_CHANNELS}, got {self.seal_channels!r}")
        require_positive_ints(self, ("box_filter", "grid_cell", "grid_top_k", "reference_width", "epochs",
                                     "batch_size"))
        require(self.box_filter % 2 == 1, owner, f"box_filter must be odd, got {self.box_filter}")
        require(self.weight_decay >= 0, owner, f"weight_decay must be >= 0, got {self.weight_decay}")
        require(0.0 <= self.val_fraction < 1.0, owner, f"val_fraction must be in [0, 1), got {self.val_fraction}")
        require(isinstance(self.colour, bool), owner, f"colour must be True or False, got {self.colour!r}")

    @property
    def input_channels(self) -> int:
        """The network's input planes: RGB and relief, or relief alone."""
        return 4 if self.colour else 1

    @property
    def seal_label_columns(self) -> list[int]:
        return [LABEL_CHANNELS.index(name) for name in self.seal_channels]

    def to_dict(self) -> dict[str, Any]:
        return config_to_dict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> CaoConfig:
        return config_from_dict(cls, data)
