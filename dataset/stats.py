"""Summary statistics of a generated dataset: a printed table and a PNG of label histograms.

    python -m dataset.stats data/train --out stats.png
"""

from __future__ import annotations

import argparse
import os
import sys
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dataset.annotate import LABEL_CHANNELS
from dataset.storage import open_dataset
from parcelpick_env.cli import check_input_dir, check_output_path, run_cli

BINS = 20
BACKGROUND = "background"
CHANNELS = LABEL_CHANNELS + ("total",)


@dataclass
class DatasetStats:
    num_scenes: int
    split: str
    parcels_per_scene: np.ndarray
    layouts: Counter
    object_sets: Counter
    histograms: dict[str, np.ndarray]  # channel -> counts over BINS equal bins of [0, 1]
    category_means: dict[str, np.ndarray]  # category -> mean of CHANNELS over its points
    category_points: dict[str, int] = field(default_factory=dict)


def compute_stats(root: str | os.PathLike, verify: bool = True) -> DatasetStats:
    """One pass over the dataset, reading only labels and per-object metadata (every scene checked unless not
    ``verify``: see ``dataset.storage``)."""
    store = open_dataset(root, verify=verify)
    edges = np.linspace(0.0, 1.0, BINS + 1)
    histograms = {c: np.zeros(BINS, dtype=np.int64) for c in CHANNELS}
    sums: dict[str, np.ndarray] = {}
    counts: Counter = Counter()
    parcels, layouts, object_sets = [], Counter(), Counter()
    for i in range(len(store)):
        s = store.scene(i, ("labels", "score", "object_ids", "object_categories", "num_parcels", "layout",
                            "object_set"))
        parcels.append(int(s["num_parcels"]))
        layouts[str(s["layout"])] += 1
        object_sets[str(s["object_set"])] += 1
        values = np.concatenate([s["labels"], s["score"][:, None]], axis=1).astype(np.float64)
        for c, channel in enumerate(CHANNELS):
            histograms[channel] += np.histogram(values[:, c], bins=edges)[0]
        categories = np.append(s["object_categories"].astype(str), BACKGROUND)
        point_category = categories[np.where(s["object_ids"] >= 0, s["object_ids"], len(categories) - 1)]
        for name in np.unique(point_category):
            mask = point_category == name
            sums[name] = sums.get(name, np.zeros(len(CHANNELS))) + values[mask].sum(axis=0)
            counts[name] += int(mask.sum())
    return DatasetStats(
        num_scenes=len(store), split=store.config["split"], parcels_per_scene=np.asarray(parcels),
        layouts=layouts, object_sets=object_sets, histograms=histograms,
        category_means={k: sums[k] / counts[k] for k in sorted(sums)}, category_points=dict(counts),
    )


def format_table(stats: DatasetStats) -> str:
    p = stats.parcels_per_scene
    lines = [
        f"scenes: {stats.num_scenes} ({stats.split})",
        f"parcels per scene: mean {p.mean():.1f}, min {p.min()}, max {p.max()}, total {p.sum()}",
        f"layouts: {dict(stats.layouts)}   object sets: {dict(stats.object_sets)}",
        "",
        "| category | points | " + " | ".join(CHANNELS) + " |",
        "|---|---|" + "---|" * len(CHANNELS),
    ]
    for name, means in stats.category_means.items():
        lines.append(f"| {name} | {stats.category_points[name]} | " + " | ".join(f"{m:.3f}" for m in means) + " |")
    return "\n".join(lines)


def plot_stats(stats: DatasetStats, path: str | os.PathLike) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(13, 7))
    p = stats.parcels_per_scene
    axes[0, 0].hist(p, bins=np.arange(p.min(), p.max() + 2) - 0.5)
    axes[0, 0].set(title="parcels per scene", xlabel="parcels", ylabel="scenes")
    centres = (np.arange(BINS) + 0.5) / BINS
    for ax, channel in zip(axes.flat[1:], CHANNELS):
        ax.bar(centres, stats.histograms[channel], width=1.0 / BINS)
        ax.set(title=f"{channel} score", xlabel="score", ylabel="points", yscale="log", xlim=(0, 1))
    fig.suptitle(f"{stats.num_scenes} {stats.split} scenes")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dataset.stats", description=__doc__.split("\n\n")[0])
    parser.add_argument("root", type=Path, help="dataset directory")
    parser.add_argument("--out", type=Path, default=None, help="PNG path (default: ROOT/stats.png)")
    parser.add_argument("--no-verify", action="store_true", help="skip the per-array checksums (faster)")
    args = parser.parse_args(argv)
    check_input_dir(args.root, "root")
    out = check_output_path(args.out or args.root / "stats.png", "--out")
    stats = compute_stats(args.root, verify=not args.no_verify)
    print(format_table(stats))
    plot_stats(stats, out)
    print(f"saved {out}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
