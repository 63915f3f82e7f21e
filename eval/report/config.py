"""The report's settings in one dataclass, with the defaults the issue sizes for resolvable comparisons."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from eval.ap import PAPER_COMPAT_NMS_RADIUS
from eval.clearance import DEFAULT_EPISODES, LAYOUTS, OBJECT_SETS
from eval.paper_results import METHOD_LABELS
from eval.report.variants import ABLATION_SEEDS, ABLATION_TRAIN_ARGS
from parcelpick_env.parallel import BACKENDS
from parcelpick_env.suction.quality import AP_DEFINITIONS

DEFAULT_POLICIES: tuple[str, ...] = ("oracle", "diffusion", "diffusion_vote", "diffusion_hold", "diffusion_vote_hold",
                                     "cao", "normal_std", "dexnet", "random", "sb3")
AP_METRICS: tuple[str, ...] = ("AP", "AP0.8", "AP0.4")  # the paper's Table II columns, in its order
DIFFUSION = "diffusion"
ORACLE = "oracle"  # under eval.ap the registered oracle submits the best stored labels: the label oracle
LABEL_ORACLE = "label oracle (stored labels)"  # its row in every AP table
CEILING = "q = 1 ceiling"  # the last row of every AP table: every slot the protocol keeps at q = 1
# The paper's protocol: entry["ap"] is this definition's result, and paired comparisons, ablations, the gaps to
# the paper and the figures read it.
HEADLINE_QUALITY = "suctionnet"
AP_QUALITIES: tuple[str, ...] = ("suctionnet", "physical")
QUALITY_TITLES: dict[str, str] = {
    "suctionnet": "SuctionNet-1Billion's evaluator (the paper's protocol): seal × wrench × collision",
    "physical": "this project's own definition: would the pick hold in this env (its cup, the real masses, "
                "Dex-Net's ring conditions); the paper has no counterpart",
    "paper_compat": "SuctionNet's lenient label-time wrench (paper-compatible, not a measure of picking)",
}
# The goal for how well the physical label predicts the env's verdict (results/label_physics.json).
LABEL_PHYSICS_AUC_GOAL = 0.9


@dataclass(frozen=True)
class APVariant:
    """One row of the paper-compatible table: a quality definition and an NMS radius (None: APConfig's)."""

    name: str
    description: str
    quality: str = HEADLINE_QUALITY
    nms_radius: float | None = None


# Where a 94-point AP can come from (docs/protocols.md): the public Diffusion_Suction test script's NMS (in effect
# none) and SuctionNet's label-time wrench, each alone and together, beside SuctionNet's evaluator as is.
PAPER_COMPAT_VARIANTS: tuple[APVariant, ...] = (
    APVariant("suctionnet", "(a) SuctionNet's evaluator as is"),
    APVariant("nms", f"(b) NMS at {PAPER_COMPAT_NMS_RADIUS * 1000:g} mm only", nms_radius=PAPER_COMPAT_NMS_RADIUS),
    APVariant("wrench", "(c) label-time wrench only (quality paper_compat)", quality="paper_compat"),
    APVariant("both", "(d) both", quality="paper_compat", nms_radius=PAPER_COMPAT_NMS_RADIUS),
)
PAPER_COMPAT_POLICIES: tuple[str, ...] = (ORACLE, DIFFUSION)  # evaluated under every variant, where available
# Fewer test scenes than this and a 3-point AP gap between methods is not resolved by the paired interval
# (per-scene AP spreads by about 10 points); the report says so beside its numbers.
MIN_AP_SCENES = 50


def label(name: str) -> str:
    return METHOD_LABELS.get(name, name)


@dataclass(frozen=True)
class ReportConfig:
    test_data: str
    policies: tuple[str, ...] = DEFAULT_POLICIES
    ap_scenes: int | None = None  # None: every stored test scene (the results command stores 64)
    ap_qualities: tuple[str, ...] = AP_QUALITIES  # one Table II per definition; HEADLINE_QUALITY among them
    episodes: int = DEFAULT_EPISODES  # clearance episodes per (object set, layout) cell
    parcels: int = 8
    objects: tuple[str, ...] = OBJECT_SETS
    layouts: tuple[str, ...] = LAYOUTS
    seed: int = 0
    workers: int = 1
    backend: str = "local"
    ray_address: str | None = None  # clearance on an existing Ray cluster ('auto', ray://host:port)
    out: str = "results/RESULTS.md"
    figures: str | None = None  # None: <out's folder>/figures
    skip_clearance: bool = False
    # record which parcel each clearance pick took and whether others rested on it (eval/pick_audit.py)
    audit_picks: bool = True
    # an earlier report's JSON whose clearance results are reused (labelled as such) instead of re-running them
    clearance_from: str | None = None
    skip_ablations: bool = False
    skip_paper_compat: bool = False
    label_physics: str = "results/label_physics.json"  # eval/label_physics.py's result, read when present
    diffusion_checkpoint: str | None = None  # None: the policy's shipped checkpoint
    ablation_dir: str = "runs/ablations"
    ablation_steps: tuple[int, ...] = (5, 10, 15, 20)  # inference-only step counts on the main checkpoint
    train_data: str = "data/train"  # only printed in the training commands of missing ablations
    train_args: str = ABLATION_TRAIN_ARGS  # the same settings for every variant, so each changes one thing only
    ablation_seeds: tuple[int, ...] = ABLATION_SEEDS  # one training run of every variant per seed
    progress: bool = True
    graspnet_root: str | None = None  # SuctionNet-1Billion root: adds Table I (eval/table_one.py); None: no section

    def __post_init__(self) -> None:
        if not self.policies:
            raise ValueError("policies must name at least one policy")
        if self.clearance_from is not None and self.skip_clearance:
            raise ValueError("clearance_from and skip_clearance exclude each other")
        if self.clearance_from is not None and not Path(self.clearance_from).is_file():
            raise ValueError(f"clearance_from {self.clearance_from} does not exist")
        if self.ap_scenes is not None and self.ap_scenes < 1:
            raise ValueError(f"ap_scenes must be >= 1 or None, got {self.ap_scenes}")
        if (any(q not in AP_DEFINITIONS for q in self.ap_qualities) or len(set(self.ap_qualities))
                != len(self.ap_qualities) or HEADLINE_QUALITY not in self.ap_qualities):
            raise ValueError(f"ap_qualities must be distinct names from {AP_DEFINITIONS} including "
                             f"{HEADLINE_QUALITY!r} (the paper's protocol), got {self.ap_qualities}")
        if self.episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {self.episodes}")
        if not 1 <= self.parcels <= 50:
            raise ValueError(f"parcels must be in [1, 50], got {self.parcels}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        if self.workers < 1:
            raise ValueError(f"workers must be >= 1, got {self.workers}")
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {self.backend!r}")
        if any(k < 1 for k in self.ablation_steps):
            raise ValueError(f"ablation_steps must be >= 1, got {self.ablation_steps}")
        if (not self.ablation_seeds or any(s < 0 for s in self.ablation_seeds)
                or len(set(self.ablation_seeds)) != len(self.ablation_seeds)):
            raise ValueError(f"ablation_seeds must be distinct seeds >= 0, got {self.ablation_seeds}")
        for name, values, allowed in (("objects", self.objects, OBJECT_SETS), ("layouts", self.layouts, LAYOUTS)):
            if not values or any(v not in allowed for v in values):
                raise ValueError(f"{name} must be a non-empty subset of {allowed}, got {values}")

    @property
    def figures_dir(self) -> Path:
        return Path(self.figures) if self.figures else Path(self.out).parent / "figures"
