"""The report's settings in one dataclass, with the defaults the issue sizes for resolvable comparisons."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from eval.clearance import DEFAULT_EPISODES, LAYOUTS, OBJECT_SETS
from eval.paper_results import METHOD_LABELS
from eval.report.variants import ABLATION_TRAIN_ARGS
from parcelpick_env.parallel import BACKENDS

DEFAULT_POLICIES: tuple[str, ...] = ("oracle", "diffusion", "cao", "normal_std", "dexnet", "random", "sb3")
AP_METRICS: tuple[str, ...] = ("AP", "AP0.8", "AP0.4")  # the paper's Table II columns, in its order
DIFFUSION = "diffusion"
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
    skip_ablations: bool = False
    diffusion_checkpoint: str | None = None  # None: the policy's shipped checkpoint
    ablation_dir: str = "runs/ablations"
    ablation_steps: tuple[int, ...] = (5, 10, 15, 20)  # inference-only step counts on the main checkpoint
    train_data: str = "data/train"  # only printed in the training commands of missing ablations
    train_args: str = ABLATION_TRAIN_ARGS  # the same settings for every variant, so each changes one thing only
    progress: bool = True

    def __post_init__(self) -> None:
        if not self.policies:
            raise ValueError("policies must name at least one policy")
        if self.ap_scenes is not None and self.ap_scenes < 1:
            raise ValueError(f"ap_scenes must be >= 1 or None, got {self.ap_scenes}")
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
        for name, values, allowed in (("objects", self.objects, OBJECT_SETS), ("layouts", self.layouts, LAYOUTS)):
            if not values or any(v not in allowed for v in values):
                raise ValueError(f"{name} must be a non-empty subset of {allowed}, got {values}")

    @property
    def figures_dir(self) -> Path:
        return Path(self.figures) if self.figures else Path(self.out).parent / "figures"
