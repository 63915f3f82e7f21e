"""Writing the report: the markdown page (tables and figure links, in the paper's order) and its JSON dump."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from eval.report.comparisons import comparisons_against
from eval.report.config import DIFFUSION, MIN_AP_SCENES
from eval.report.figures import plot_clearance, plot_failures, plot_precision_at_k
from eval.report.tables import (
    _unavailable,
    ablation_comparison_table,
    ablation_table,
    comparison_table,
    differences,
    failure_details,
    failure_table,
    outcome_table,
    provenance_table,
    table_ii,
    table_v,
)
from eval.stats import CONFIDENCE, RESAMPLES


def cost_lines(report: dict[str, Any]) -> list[str]:
    """What this report's runs cost, from their own timings (seconds of one core per scene and episode)."""
    ap_s, ap_n, ep_s, ep_n = 0.0, 0, 0.0, 0
    for entry in report["policies"].values():
        for scene in (entry.get("ap") or {}).get("scenes", []):
            ap_s, ap_n = ap_s + scene.get("seconds", 0.0), ap_n + 1
        for episode in (entry.get("clearance") or {}).get("episodes", []):
            ep_s, ep_n = ep_s + episode.get("wall_time_s", 0.0), ep_n + 1
    out = []
    if ap_n:
        out.append(f"AP: {ap_n} method-scenes, {ap_s:.0f} s in all ({ap_s / ap_n:.2f} s per scene per method)")
    if ep_n:
        out.append(f"clearance: {ep_n} episodes, {ep_s:.0f} s of one core in all ({ep_s / ep_n:.1f} s per episode)")
    return [f"Cost of these runs: {'; '.join(out)}.", ""] if out else []


def _figure(figures: dict[str, Path | None], key: str, alt: str, out: Path) -> list[str]:
    """A markdown image link to ``figures[key]``, relative to the page; nothing when that plot was not drawn."""
    path = figures.get(key)
    return [] if path is None else [f"![{alt}]({os.path.relpath(path, out.parent)})", ""]


def render_markdown(report: dict[str, Any], figures: dict[str, Path | None], out: Path) -> str:
    """The whole page, from ``run_report``'s dict; ``figures`` maps names to PNGs (linked relative to ``out``)."""
    cfg = report["config"]
    policies = report["policies"]
    lines = ["# ParcelPick evaluation report", "",
             f"Generated {report['generated']}. Offline AP on `{cfg['test_data']}` "
             f"({'all' if cfg['ap_scenes'] is None else cfg['ap_scenes']} test scenes, the same for every method); "
             + ("clearance skipped." if cfg["skip_clearance"] else
                f"clearance with {cfg['parcels']} parcels, {cfg['episodes']} episode(s) per cell, seed {cfg['seed']} "
                "(the same piles for every method)."),
             "Every cell reads **ours / paper**. Our numbers come from simulated ParcelPick scenes and the "
             "simulated robot; the paper's from its Parcel-Suction-Dataset and, for clearance, its real robot.",
             f"Each figure of ours carries its {100 * CONFIDENCE:.0f}% percentile bootstrap interval in brackets "
             f"({RESAMPLES} resamples): over test scenes for AP, over episodes for clearance. A method is called "
             "ahead of another only where the interval of their paired difference (same scenes, same seeds) "
             "excludes 0.", ""]
    lines += cost_lines(report)
    ap_scenes = [e["ap"]["num_scenes"] for e in policies.values() if e.get("ap")]
    if ap_scenes and min(ap_scenes) < MIN_AP_SCENES:
        lines += [f"Only {min(ap_scenes)} test scenes (fewer than {MIN_AP_SCENES}): AP gaps of a few points are "
                  "not resolved at this size.", ""]
    lines += ["## Offline AP (paper Table II layout)", "", table_ii(policies), ""]
    lines += _figure(figures, "precision_at_k", "precision@k per policy", out)
    paired = comparisons_against(DIFFUSION, policies)
    if paired:
        lines += ["## Paired comparisons with Diffusion-Suction", "",
                  "Differences 'Diffusion-Suction − method' in points: Top-50 AP over the shared test scenes, "
                  "R_grasp and R_object over the shared clearance episodes (resampled within each cell).", "",
                  comparison_table(paired, policies), ""]
    lines += ["## Closed-loop clearance (paper Table V layout)", "",
              "Entries are R_grasp / R_object (%). '(paper robot)' is the paper's real-robot Diffusion-Suction, "
              "given beside every method for reference.", ""]
    if cfg["skip_clearance"]:
        lines += ["Skipped (--skip-clearance).", ""]
    else:
        for name, entry in policies.items():
            lines.append(f"### {entry['label']}")
            lines.append("")
            if entry.get("clearance") is None:
                why = _unavailable(entry) or f"failed: {entry.get('clearance_error')}"
                lines += [why, ""]
            else:
                lines += [table_v(entry, tuple(cfg["objects"]), tuple(cfg["layouts"])), ""]
        lines += ["### Attempt outcomes", "", outcome_table(policies), ""]
        lines += _figure(figures, "clearance", "clearance per cell", out)
        lines += ["### Failure anatomy", "",
                  "Failed attempts by kind ('outcome: move or phase'), per method and cell; the most common "
                  "failures with the link or holding condition that failed below.", "",
                  failure_table(policies, tuple(cfg["objects"]), tuple(cfg["layouts"])), "",
                  *failure_details(policies), ""]
        lines += _figure(figures, "failures", "failure causes per cell", out)
    lines += ["## Diffusion-Suction ablations (paper Tables III and IV)", ""]
    if cfg["skip_ablations"]:
        lines += ["Skipped (--skip-ablations).", ""]
    else:
        lines += ["Inference-step rows reuse the main checkpoint; the other rows need their own training run "
                  f"under `{cfg['ablation_dir']}/<name>/best.pt`, all with the same settings (`{cfg['train_args']}` "
                  "plus the variant's flag), so read them against the 'reference' row, not the main checkpoint, "
                  "which trained longer. The paper's DGCNN row has no counterpart here.", "",
                  ablation_table(report.get("ablations", [])), "",
                  "Each trained variant against the reference, paired over the same test scenes:", "",
                  ablation_comparison_table(report.get("ablations", [])), ""]
    if report.get("provenance"):
        lines += ["## Checkpoint provenance", "", provenance_table(report["provenance"]), ""]
    lines += ["## Where our numbers differ from the paper's", ""]
    gaps = differences(report)
    lines += gaps if gaps else ["Nothing to compare: no run produced a number with a counterpart in the paper."]
    lines.append("")
    return "\n".join(lines)


def write_report(report: dict[str, Any], out: str | os.PathLike, figures_dir: str | os.PathLike) -> dict[str, Path]:
    """Write the plots, the markdown and the JSON dump; return their paths."""
    out, figures_dir = Path(out), Path(figures_dir)
    out.parent.mkdir(parents=True, exist_ok=True)
    figures = {"precision_at_k": plot_precision_at_k(report["policies"], figures_dir / "precision_at_k.png"),
               "clearance": plot_clearance(report["policies"], figures_dir / "clearance.png"),
               "failures": plot_failures(report["policies"], figures_dir / "failures.png")}
    out.write_text(render_markdown(report, figures, out))
    json_path = out.with_suffix(".json")
    json_path.write_text(json.dumps({**report, "figures": {k: str(v) if v else None for k, v in figures.items()}},
                                    indent=2, default=str))
    return {"markdown": out, "json": json_path, **{k: v for k, v in figures.items() if v is not None}}
