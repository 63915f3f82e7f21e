"""Every constant of the Dex-Net 3.0 style baseline, in one place (docs/protocols.md, 'The rows of the tables').

``DexNetConfig`` fixes what a checkpoint means (crop geometry, network widths) plus how the policy
searches (cross-entropy method); it is stored inside every checkpoint so a policy always crops the way
its network was trained. ``TrainConfig`` holds optimisation settings only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from parcelpick_env.config_checks import (config_from_dict, config_to_dict, require, require_int,
                                          require_positive_ints, require_positive_numbers)


@dataclass(frozen=True)
class DexNetConfig:
    """Crop, network and CEM settings.

    The crop spans ``crop_metric_size`` metres at the candidate's depth whatever the camera resolution,
    so one network serves 160x120 and 640x480 images. Crop depth is ``(z - z_candidate) / depth_scale``
    clipped to ``+-depth_clip``; a second channel marks pixels with a valid return.
    CEM follows Dex-Net 3.0: ``num_seeds`` uniform seeds, then ``cem_iterations`` rounds that refit a GMM
    (``gmm_component_fraction`` components per elite) to the best ``elite_fraction`` and draw
    ``num_gmm_samples`` new candidates. GMM coordinates are pixels divided by the image width, so
    ``gmm_reg_covar`` is resolution independent.
    """

    crop_size: int = 96
    crop_metric_size: float = 0.16  # metres covered by the crop side at the candidate depth
    depth_scale: float = 0.05  # metres per unit of the re-centred crop
    depth_clip: float = 4.0
    max_approach_angle_deg: float = 30.0  # approach axis (-normal) to world vertical
    visibility_tolerance: float = 0.01  # metres between a point's camera depth and the depth image
    num_seeds: int = 250
    num_gmm_samples: int = 50
    cem_iterations: int = 3
    elite_fraction: float = 0.25
    gmm_component_fraction: float = 0.4
    gmm_em_iterations: int = 10
    gmm_reg_covar: float = 1e-4  # in (pixels / width)^2: std of about 1% of the image width
    max_snap_distance: float = 0.02  # GMM samples snap to the nearest eligible pixel within this (fraction of width)
    nms_radius: float = 0.02  # metres, as the paper's post-processing
    conv_channels: tuple[int, ...] = (16, 32, 32, 64)
    fc_width: int = 64
    depth_feature_mean: float = 1.0  # candidate depth is fed as (z - mean) / std
    depth_feature_std: float = 0.5

    def __post_init__(self) -> None:
        owner = "DexNetConfig"
        require_positive_ints(self, ("crop_size", "num_seeds", "num_gmm_samples", "gmm_em_iterations", "fc_width"))
        require(self.crop_size % 16 == 0, owner, f"crop_size must be a multiple of 16, got {self.crop_size}")
        require_int(owner, "cem_iterations", self.cem_iterations, lo=0)
        require_positive_numbers(self, ("crop_metric_size", "depth_scale", "depth_clip", "visibility_tolerance",
                                        "gmm_reg_covar", "max_snap_distance", "nms_radius", "depth_feature_std"))
        require(0 < self.max_approach_angle_deg <= 90, owner,
                f"max_approach_angle_deg must be in (0, 90], got {self.max_approach_angle_deg}")
        require(0 < self.elite_fraction <= 1, owner, f"elite_fraction must be in (0, 1], got {self.elite_fraction}")
        require(0 < self.gmm_component_fraction <= 1, owner,
                f"gmm_component_fraction must be in (0, 1], got {self.gmm_component_fraction}")
        require(len(self.conv_channels) >= 1 and all(isinstance(c, int) and c >= 1 for c in self.conv_channels),
                owner, f"conv_channels must be positive integers, got {self.conv_channels!r}")
        require(self.crop_size % (2 ** len(self.conv_channels)) == 0, owner,
                f"crop_size {self.crop_size} must be divisible by 2**len(conv_channels)")

    @property
    def min_vertical_cos(self) -> float:
        """A candidate is eligible when its outward normal's z component is at least this."""
        return math.cos(math.radians(self.max_approach_angle_deg))

    def to_dict(self) -> dict[str, Any]:
        return config_to_dict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DexNetConfig:
        return config_from_dict(cls, data)


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings of ``python -m policies.dexnet.train``.

    A training sample is one annotation point seen by the camera whose approach is eligible for the
    policy. Its target is the analytic quality ``seal * wrench * collision``; samples with a target of
    at least ``positive_threshold`` count as positives for class-balanced sampling.
    """

    epochs: int = 10
    batch_size: int = 128
    lr: float = 1e-3
    weight_decay: float = 1e-4
    val_fraction: float = 0.1  # fraction of scenes held out for validation
    positive_threshold: float = 0.5
    samples_per_epoch: int = 8192  # drawn with class balance from the training scenes
    max_points_per_scene: int = 1024  # cap on annotation points kept per scene
    seed: int = 0
    dexnet: DexNetConfig = field(default_factory=DexNetConfig)

    def __post_init__(self) -> None:
        owner = "TrainConfig"
        require_positive_ints(self, ("epochs", "batch_size", "samples_per_epoch", "max_points_per_scene"))
        require_int(owner, "seed", self.seed, lo=0)
        require_positive_numbers(self, ("lr",))
        require(math.isfinite(self.weight_decay) and self.weight_decay >= 0, owner,
                f"weight_decay must be >= 0, got {self.weight_decay}")
        require(0 <= self.val_fraction < 1, owner, f"val_fraction must be in [0, 1), got {self.val_fraction}")
        require(0 < self.positive_threshold <= 1, owner,
                f"positive_threshold must be in (0, 1], got {self.positive_threshold}")
        require(isinstance(self.dexnet, DexNetConfig), owner, f"dexnet must be a DexNetConfig, got {type(self.dexnet)}")
