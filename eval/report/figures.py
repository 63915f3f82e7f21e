"""The report's matplotlib figures: P@k curves, clearance rates with their intervals, and failure causes."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from eval.clearance import LAYOUTS, OBJECT_SETS
from eval.paper_results import TABLE_V
from eval.report.config import label
from eval.report.tables import failure_kinds


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    fig.clf()
    _pyplot().close(fig)
    return path


def plot_precision_at_k(policies: dict[str, dict[str, Any]], path: Path) -> Path | None:
    """Mean P@k against k, one panel per quality threshold, one line per policy."""
    curves = {n: e["ap"] for n, e in policies.items() if e.get("ap") is not None and "precision_at_k" in e["ap"]}
    if not curves:
        return None
    import numpy as np

    plt = _pyplot()

    thresholds = next(iter(curves.values()))["thresholds"]
    fig, axes = plt.subplots(1, len(thresholds), figsize=(3.6 * len(thresholds), 3.4), sharey=True, squeeze=False)
    for t, (ax, theta) in enumerate(zip(axes[0], thresholds)):
        for name, ap in curves.items():
            p = np.asarray(ap["precision_at_k"], dtype=float)
            ax.plot(np.arange(1, len(p) + 1), p[:, t], label=label(name))
        ax.set_title(f"quality ≥ {theta:g}")
        ax.set_xlabel("k")
        ax.set_ylim(0, 100)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("precision@k (%)")
    axes[0][-1].legend(fontsize=8)
    return _save(fig, path)


def plot_clearance(policies: dict[str, dict[str, Any]], path: Path) -> Path | None:
    """R_grasp and R_object per (object set, layout) cell: a bar per policy with its 95% interval over episodes,
    hatched grey for the paper's robot."""
    runs = {n: e["clearance"] for n, e in policies.items() if e.get("clearance") is not None}
    if not runs:
        return None
    import numpy as np

    plt = _pyplot()

    cells = [f"{o}/{la}" for o in OBJECT_SETS for la in LAYOUTS
             if any(f"{o}/{la}" in s["cells"] for s in runs.values())]
    series = [(label(n), [s["cells"].get(c) for c in cells]) for n, s in runs.items()]
    paper = [TABLE_V.get(tuple(c.split("/"))) for c in cells]
    width = 0.8 / (len(series) + 1)
    x = np.arange(len(cells))
    fig, axes = plt.subplots(2, 1, figsize=(max(6.0, 1.2 * len(cells) + 2), 6.5), sharex=True)
    for row, (ax, key) in enumerate(zip(axes, ("R_grasp", "R_object"))):
        for i, (name, values) in enumerate(series):
            heights = np.array([np.nan if v is None else v[key] for v in values])
            bounds = [(v or {}).get("intervals", {}).get(key) for v in values]
            err = np.array([[h - b["low"], b["high"] - h] if b else [np.nan, np.nan]
                            for h, b in zip(heights, bounds)]).T
            ax.bar(x + i * width, heights, width, label=name, yerr=np.clip(err, 0, None), capsize=2,
                   error_kw={"elinewidth": 0.8})
        ax.bar(x + len(series) * width, [np.nan if p is None else p[row] for p in paper], width, color="0.75",
               hatch="//", edgecolor="0.4", label="Diffusion-Suction (paper, real robot)")
        ax.set_ylabel(f"{key} (%)")
        ax.set_ylim(0, 105)
        ax.grid(axis="y", alpha=0.3)
    axes[1].set_xticks(x + 0.4 - width / 2, cells, rotation=30, ha="right")
    # Above the panels, so that no bar of a full cell hides behind it.
    axes[0].legend(fontsize=7, ncol=4, loc="lower center", bbox_to_anchor=(0.5, 1.02))
    return _save(fig, path)


def plot_failures(policies: dict[str, dict[str, Any]], path: Path) -> Path | None:
    """Failed attempts per (object set, layout) cell, stacked by failure kind: one panel per policy."""
    runs = {n: e["clearance"] for n, e in policies.items() if e.get("clearance") is not None}
    kinds = failure_kinds(policies)
    if not runs or not kinds:
        return None
    import numpy as np

    plt = _pyplot()
    cells = [f"{o}/{la}" for o in OBJECT_SETS for la in LAYOUTS
             if any(f"{o}/{la}" in s["cells"] for s in runs.values())]
    colours = plt.get_cmap("tab20")(np.linspace(0, 1, max(len(kinds), 2)))
    fig, axes = plt.subplots(len(runs), 1, figsize=(max(6.0, 1.1 * len(cells) + 3), 2.2 * len(runs) + 0.8),
                             sharex=True, squeeze=False)
    x = np.arange(len(cells))
    for ax, (name, summary) in zip(axes[:, 0], runs.items()):
        counts = np.array([[summary["cells"].get(c, {}).get("failures", {}).get(k, 0) for c in cells] for k in kinds])
        bottom = np.zeros(len(cells))
        for kind, row, colour in zip(kinds, counts, colours):
            ax.bar(x, row, 0.7, bottom=bottom, color=colour, label=kind)
            bottom += row
        ax.set_ylabel("failed attempts")
        ax.set_title(label(name), fontsize=9, loc="left")
        ax.grid(axis="y", alpha=0.3)
    axes[-1, 0].set_xticks(x, cells, rotation=30, ha="right")
    axes[0, 0].legend(fontsize=7, ncol=2, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return _save(fig, path)
