"""Diffusion-Suction training runs the report refers to, as data: the shipped run's flags and the ablations.

Each ablation is the same training command with one flag added, so a variant changes one thing only and is
read against the 'reference' variant (the same budget, no flag), not the longer-trained shipped model. Every
variant is trained once per seed in ``ABLATION_SEEDS`` (runs/ablations/<name>/seed<k>/best.pt), and read against the
reference trained with the same seed. A variant that changes the data (more points per scene) trains and is tested on
splits of its own, and is read against a baseline variant trained on the same piles at the reference's density.
"""

from __future__ import annotations

from dataclasses import dataclass

from eval.paper_results import TABLE_III_ABLATION, TABLE_IV_STEPS
from eval.report.splits import MORE_POINTS, TEST_MORE_POINTS, TRAIN_MORE_POINTS, TRAIN_MORE_POINTS_BASELINE, DataSplit


def train_args(steps: int, seed: int | None = 0) -> str:
    """The shipped Diffusion-Suction run's training flags at ``steps`` optimisation steps (no ``--seed`` if None)."""
    seed_flag = "" if seed is None else f" --seed {seed}"
    return f"--preset cpu --steps {steps} --batch-size 4 --lr 1e-3{seed_flag} --threads 1 --workers 0"


# How the shipped Diffusion-Suction checkpoint was trained (README, "Reproducing the checkpoints").
MAIN_TRAIN_ARGS = train_args(7000) + " --val-every 500 --val-scenes 16 --label-set paper"
# The trained ablations: the main run's settings on a shorter, matched budget (75 min each would not fit a
# 2-core day); the 'reference' variant changes nothing, so each ablation is read against it, not the main model.
# The seed is not in these flags: each run adds its own (``ABLATION_SEEDS``).
ABLATION_STEPS = 1000
ABLATION_TRAIN_ARGS = train_args(ABLATION_STEPS, seed=None)
ABLATION_SEEDS: tuple[int, ...] = (0, 1, 2)  # issue 14: at least 3 seeds per variant
REFERENCE = "reference"


@dataclass(frozen=True)
class TrainedVariant:
    """A Diffusion-Suction ablation that needs its own training run (runs/ablations/<name>/best.pt)."""

    name: str
    description: str
    train_flags: tuple[str, ...]
    paper: tuple[float, ...] | None  # (AP, AP0.8, AP0.4[, ms]) from the paper's Table III / IV
    steps: int | None = None  # the DDIM step count a step-count variant trains and samples with
    train_split: DataSplit | None = None  # its own training data (None: the report's)
    test_split: DataSplit | None = None  # its own test data (None: the report's)
    baseline: str | None = REFERENCE  # the variant it is read against, on the same test split; None: none


TRAINED_VARIANTS: tuple[TrainedVariant, ...] = (
    TrainedVariant(REFERENCE, "reference: the main settings at the ablation budget", (),
                   TABLE_III_ABLATION["full"]),
    TrainedVariant("no_segment_levers", "w/o surface-segment lever arms (not in the paper)", ("--no-segment-levers",),
                   None),
    TrainedVariant("segment_size", "with a surface-segment size channel (not in the paper)", ("--segment-size",), None),
    TrainedVariant("levers_in_encoder", "with the lever arms as encoder input too (not in the paper)",
                   ("--levers-in-encoder",), None),
    TrainedVariant("no_normals", "w/o normals", ("--no-normals",), TABLE_III_ABLATION["no_normals"]),
    TrainedVariant("no_visibility", "w/o visibility", ("--no-visibility",), TABLE_III_ABLATION["no_visibility"]),
    TrainedVariant("pointnet", "PointNet encoder", ("--encoder", "pointnet"), TABLE_III_ABLATION["pointnet"]),
    TrainedVariant("physical_labels", "trained on the physical labels (not in the paper)",
                   ("--label-set", "physical"), None),
    TrainedVariant("points4096_400", f"{TRAIN_MORE_POINTS_BASELINE.points:,} points, {TRAIN_MORE_POINTS.scenes} "
                   "scenes (the more-points baseline; "
                   f"tested at {MORE_POINTS:,})", (), None, train_split=TRAIN_MORE_POINTS_BASELINE,
                   test_split=TEST_MORE_POINTS, baseline=None),
    TrainedVariant("points8192", f"with {MORE_POINTS:,} points, the same {TRAIN_MORE_POINTS.scenes} scenes (not in "
                   f"the paper; tested at {MORE_POINTS:,})", ("--num-points", str(MORE_POINTS)), None,
                   train_split=TRAIN_MORE_POINTS, test_split=TEST_MORE_POINTS, baseline="points4096_400"),
    *(TrainedVariant(f"steps{k}", f"trained and sampled with {k} DDIM steps", ("--inference-steps", str(k)),
                     TABLE_IV_STEPS[(k, k)], steps=k) for k in (5, 10, 15)),
)
