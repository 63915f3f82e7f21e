"""One place for every Diffusion-Suction hyper-parameter (lengths in metres; the paper's code uses mm)."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Mapping

from parcelpick_env.config_checks import (config_from_dict, lists_to_tuples, require, require_choice,
                                          require_positive_ints, require_positive_numbers)

ENCODERS = ("pointnet2", "pointnet")
SCHEDULES = ("linear", "cosine")
PREDICTIONS = ("eps", "x0")
TIMESTEP_SPACINGS = ("leading", "trailing", "linspace")  # diffusers' names (Lin et al. 2024, Table 2)
# What checkpoints saved before these fields existed sampled with: the hand-written DDIM had only these.
LEGACY_SAMPLER = {"timestep_spacing": "leading", "eta": 0.0}
SAMPLERS = ("grid", "fps")


@dataclass
class DiffusionConfig:
    """Defaults reproduce the paper (N=16,384, PointNet++ MSG, 1000 train / 20 DDIM steps, scale 0.5).

    ``width`` scales every encoder MLP (1.0 = the paper's 192/384/768/1536-channel SA layers);
    :meth:`cpu` gives the configuration recommended for training on 2 CPU cores.

    Sampling is diffusers' ``DDIMScheduler`` (policies/diffusion/scheduler.py). Timestep spacing defaults to
    'leading' (5 of 1000 steps: t = 800 .. 0) on a measured reason, against the advice of Lin et al. ("Common
    Diffusion Noise Schedules and Sample Steps are Flawed", 2024) and diffusers to prefer 'trailing' (999 .. 199)
    for few steps: with the shipped x0-predicting checkpoint, 'trailing' lowered the top-k precision (train.py's AP
    proxy) at 3, 5, 10 and 20 steps, at 5 steps from 0.33 to 0.26 on either half of the 50 stored test scenes
    (paired s.e. 0.01) and from 0.60 to 0.44 on 24 synthetic ones; it won only at 1-2 steps. A plausible cause:
    'leading' ends with a network call at t = 0, refining an almost clean map. Re-check on validation data for an
    eps-predicting model. 'linspace' is offered for parity only: diffusers' DDIM steps by train_steps //
    inference_steps, which skips its listed timesteps (diffusers #12633; 'trailing' too, by one step, where
    inference_steps does not divide train_steps). Checkpoints stored without these fields load with
    :data:`LEGACY_SAMPLER`, what the code sampled them with before the fields existed.
    """

    num_points: int = 16384
    encoder: str = "pointnet2"  # 'pointnet2' (paper) | 'pointnet' (ablation)
    use_normals: bool = True  # ablation: w/o normals (encoder sees only xyz)
    use_visibility: bool = True  # ablation: w/o visibility -> 3 score channels
    # diffusion
    train_steps: int = 1000
    inference_steps: int = 20
    schedule: str = "linear"  # 'linear' (public code) | 'cosine' (paper text)
    beta_start: float = 1e-4
    beta_end: float = 0.02
    scale: float = 0.5  # signal scale: x0_bar = (gt*2-1)*scale
    prediction: str = "eps"  # 'eps' (public code) | 'x0' (paper Algorithm 1); diffusers' 'epsilon' | 'sample'
    timestep_spacing: str = "leading"  # 'leading' | 'trailing' | 'linspace': which timesteps a DDIM run visits
    eta: float = 0.0  # DDIM noise: 0 deterministic given the initial noise, 1 DDPM-like
    map_loss_weight: float = 1.0  # weight of the loss on the fully sampled map (public code); 0 disables
    positive_weight: float = 0.0  # per point and channel, the loss is weighted 1 + positive_weight * label
    # Not in the paper: condition the decoder on each point's lever arm to the centroid of the smooth surface it
    # lies on (policies/surface_segments.py), a geometric stand-in for the parcel's centre of mass that the wrench
    # score depends on. Segments join points closer than segment_radius whose normals agree to segment_min_cos.
    segment_levers: bool = False
    # Also not in the paper (issue 14's item 4): the segment's size (radius of gyration) beside the levers in the
    # decoder's condition, and the lever arms (and size) as encoder input beside the normals, so the PointNet++
    # sees them within each neighbourhood.
    segment_size: bool = False
    levers_in_encoder: bool = False
    segment_radius: float = 0.02
    segment_min_cos: float = 0.8
    # encoder: PointNet++ MSG, 4 SA + 4 FP
    feature_dim: int = 128
    width: float = 1.0
    sa_npoints: tuple[int, ...] = (4096, 1024, 256, 64)  # at num_points; scaled with the actual cloud size
    sa_radii: tuple[tuple[float, ...], ...] = (
        (0.010, 0.020, 0.030), (0.030, 0.045, 0.060), (0.060, 0.080, 0.120), (0.120, 0.160, 0.240))
    nsample: int = 32
    ball_dilation: tuple[int, ...] = (1, 2, 3)  # per scale: take every d-th of the d*nsample nearest in the ball
    sampler: str = "grid"  # centre sampling: 'grid' (fast voxel sampler) | 'fps' (Open3D farthest point)
    # decoder (PCDB)
    decoder_dim: int = 128
    head_hidden: int = 64  # 0 -> a single linear 128->C head
    attention_ratio: int = 16
    decode_points: int = 0  # inference only: >0 denoises a spatially uniform subset of this many points
    # Inference only, not in the paper: >0 decodes at up to this many of the observed depth image's points in the bin
    # (candidates.py), where the observation has the depth image, the camera and the bin (the env's 'pointcloud'
    # mode, the AP's records), instead of at the encoded cloud's points; PointNet++ encoders only. 0: the encoded
    # points. 16,384, the paper's cloud: +3.3 Top-50 AP over the encoded 4,096 (docs/diffusion.md).
    candidate_points: int = 16384

    def __post_init__(self) -> None:
        self.sa_npoints = lists_to_tuples(self.sa_npoints)
        self.sa_radii = lists_to_tuples(self.sa_radii)
        self.ball_dilation = lists_to_tuples(self.ball_dilation)
        owner = "DiffusionConfig"
        require_positive_ints(self, ("num_points", "train_steps", "inference_steps", "feature_dim", "nsample",
                                     "decoder_dim", "attention_ratio"))
        require_choice(owner, "encoder", self.encoder, ENCODERS)
        require_choice(owner, "schedule", self.schedule, SCHEDULES)
        require_choice(owner, "prediction", self.prediction, PREDICTIONS)
        require_choice(owner, "sampler", self.sampler, SAMPLERS)
        require_choice(owner, "timestep_spacing", self.timestep_spacing, TIMESTEP_SPACINGS)
        require(0.0 <= self.eta <= 1.0, owner, f"eta must be in [0, 1], got {self.eta}")
        if self.inference_steps > self.train_steps:
            raise ValueError(f"inference_steps ({self.inference_steps}) > train_steps ({self.train_steps})")
        if not 0.0 < self.beta_start < self.beta_end < 1.0:
            raise ValueError(f"need 0 < beta_start < beta_end < 1, got {self.beta_start}, {self.beta_end}")
        require_positive_numbers(self, ("scale", "width", "segment_radius"))
        require(-1.0 <= self.segment_min_cos <= 1.0, owner,
                f"segment_min_cos must be in [-1, 1], got {self.segment_min_cos}")
        require(self.map_loss_weight >= 0.0, owner, f"map_loss_weight must be >= 0, got {self.map_loss_weight}")
        require(self.positive_weight >= 0.0, owner, f"positive_weight must be >= 0, got {self.positive_weight}")
        if self.head_hidden < 0 or self.decode_points < 0 or self.candidate_points < 0:
            raise ValueError("head_hidden, decode_points and candidate_points must be >= 0")
        if self.decoder_dim % 4 or self.decoder_dim // self.attention_ratio < 1:
            raise ValueError(f"decoder_dim ({self.decoder_dim}) must be a multiple of 4 and >= attention_ratio")
        if len(self.sa_npoints) != len(self.sa_radii) or not self.sa_npoints:
            raise ValueError("sa_npoints and sa_radii need one entry per SA level")
        if any(b > a for a, b in zip((self.num_points,) + self.sa_npoints, self.sa_npoints)) or min(self.sa_npoints) < 1:
            raise ValueError(f"sa_npoints must be positive and non-increasing from num_points, got {self.sa_npoints}")
        scales = {len(r) for r in self.sa_radii}
        if len(scales) != 1 or len(self.ball_dilation) != scales.pop():
            raise ValueError("every SA level needs the same number of radii, one ball_dilation per radius")
        if any(r <= 0 for level in self.sa_radii for r in level) or min(self.ball_dilation) < 1:
            raise ValueError("sa_radii must be > 0 (metres) and ball_dilation >= 1")

    @property
    def uses_segments(self) -> bool:
        """Whether the inputs need the surface segmentation (``neighbourhood.model_inputs``)."""
        return self.segment_levers or self.segment_size or self.levers_in_encoder

    @property
    def num_channels(self) -> int:
        """Score channels: seal, wrench, collision (+ visibility)."""
        return 4 if self.use_visibility else 3

    def to_dict(self) -> dict[str, Any]:
        """Keeps tuples (JSON writes them as lists): ``checkpoint.load_model`` compares the values with fields."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "DiffusionConfig":
        """A stored config; one without the sampler fields predates them and gets :data:`LEGACY_SAMPLER`."""
        return config_from_dict(cls, {**LEGACY_SAMPLER, **data})

    @classmethod
    def cpu(cls, **overrides: Any) -> "DiffusionConfig":
        """Recommended for a useful model in under an hour on 2 CPU cores (N=4096, quarter-width encoder, 5 DDIM
        steps, decoder conditioned on surface-segment lever arms).

        The SA point counts keep the paper's 4x ratios; radii stay in metres, so the same model also runs
        on 16,384-point clouds (denser neighbourhoods) at inference. It predicts x0 (the paper's Algorithm 1)
        without the public code's loss on the fully sampled map: backpropagating through 20 DDIM steps made a
        step 5x dearer, and on the same data x0 without it reached a validation top-k precision of 0.043 / 0.051
        at steps 200 / 400, against 0.032 / 0.029 for eps with it (issue #5's notes). Sampling such a model with
        3-5 DDIM steps ranks better than with 20 (validation top-k precision 0.105 / 0.094 against 0.076).
        Segment levers: substituting a wrench score computed from them into the previous model's output lifted its
        test top-k precision from 0.12 to 0.42; the wrench channel was its weakest (Spearman 0.21 with the labels).
        """
        base = dict(num_points=4096, width=0.25, sa_npoints=(1024, 256, 64, 16), decoder_dim=64, head_hidden=32,
                    prediction="x0", map_loss_weight=0.0, inference_steps=5, segment_levers=True)
        base.update(overrides)
        return cls(**base)

    @classmethod
    def tiny(cls, **overrides: Any) -> "DiffusionConfig":
        """For tests: a few hundred points, narrow layers."""
        base = dict(num_points=512, width=0.125, sa_npoints=(128, 32, 16, 8), feature_dim=32, decoder_dim=32,
                    head_hidden=16, nsample=8, attention_ratio=8)
        base.update(overrides)
        return cls(**base)
