"""Writing the report: the markdown page (tables and figure links, in the paper's order) and its JSON dump."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from eval.clearance import tool_check_line
from eval.report.comparisons import comparisons_against
from eval.report.config import (
    CEILING,
    DIFFUSION,
    HEADLINE_QUALITY,
    LABEL_ORACLE,
    LABEL_PHYSICS_AUC_GOAL,
    MIN_AP_SCENES,
    QUALITY_TITLES,
)
from eval.report.figures import plot_clearance, plot_failures, plot_precision_at_k
from eval.report.seed_runs import MIN_SEEDS
from eval.report.splits import MORE_POINTS, MORE_POINTS_TRAIN_SCENES, report_split_sha
from eval.report.tables import (
    _unavailable,
    ablation_comparison_table,
    ablation_table,
    ap_results,
    channel_cost_table,
    comparison_table,
    cover_table,
    differences,
    distinct_results,
    failure_details,
    failure_table,
    glance_table,
    outcome_table,
    paper_compat_sentences,
    paper_compat_table,
    provenance_table,
    table_ii,
    table_v,
)
from eval.stats import CONFIDENCE, RESAMPLES


def cost_lines(report: dict[str, Any]) -> list[str]:
    """What this report's runs cost, from their own timings (seconds of one core per scene and episode)."""
    ap_s, ap_n, ep_s, ep_n = 0.0, 0, 0.0, 0
    runs = [r for entry in report["policies"].values() for r in ap_results(entry)]
    runs += [r for row in report.get("paper_compat") or [] for r in row.get("results", {}).values()]
    for result in distinct_results(runs):
        for scene in result.get("scenes", []):
            ap_s, ap_n = ap_s + scene.get("seconds", 0.0), ap_n + 1
    for entry in report["policies"].values():
        for episode in (entry.get("clearance") or {}).get("episodes", []):
            ep_s, ep_n = ep_s + episode.get("wall_time_s", 0.0), ep_n + 1
    out = []
    if ap_n:
        out.append(f"AP: {ap_n} method-scenes (every quality definition and paper-compatible variant), "
                   f"{ap_s:.0f} s in all ({ap_s / ap_n:.2f} s per scene per run)")
    if ep_n:
        out.append(f"clearance: {ep_n} episodes, {ep_s:.0f} s of one core in all ({ep_s / ep_n:.1f} s per episode)")
    return [f"Cost of these runs: {'; '.join(out)}.", ""] if out else []


def _figure(figures: dict[str, Path | None], key: str, alt: str, out: Path) -> list[str]:
    """A markdown image link to ``figures[key]``, relative to the page; nothing when that plot was not drawn."""
    path = figures.get(key)
    return [] if path is None else [f"![{alt}]({os.path.relpath(path, out.parent)})", ""]


def clearance_line(report: dict[str, Any]) -> str:
    """How this report's clearance numbers were made: run here, reused from an earlier report, or skipped."""
    cfg, source = report["config"], report.get("clearance_source")
    if cfg["skip_clearance"]:
        return "clearance skipped."
    if source:
        return (f"clearance **reused from `{source['path']}`** (generated {source['generated']}; {source['parcels']} "
                f"parcels, {source['episodes']} episode(s) per cell, seed {source['seed']}), not re-run with this "
                "report: where the cell changed since, those numbers are the earlier cell's.")
    return (f"clearance with {cfg['parcels']} parcels, {cfg['episodes']} episode(s) per cell, seed {cfg['seed']} "
            "(the same piles for every method).")


def _restored_split(src: dict[str, Any], ours: str | None) -> str:
    """Whether a restored source's rows read this report's test split: the restored split itself, the same
    manifest, or another (the asset library or the labels may have changed in between). Every restorable part
    but the split itself reads the split."""
    if "data/test" in src["parts"]:
        return ""
    theirs = src.get("test_split_sha256")
    if theirs is not None and theirs == ours:
        return " They were measured on this report's test split (the same manifest)."
    was = f"manifest {theirs[:12]}" if theirs else "which that report did not record"
    return (f" **They were measured on that report's test split ({was}), not on this report's** (manifest "
            f"{(ours or 'unknown')[:12]}, generated for it): where the parcels or the labels changed in between, "
            "those rows do not compare with this report's own.")


def restored_lines(report: dict[str, Any]) -> list[str]:
    """Which numbers ``make results --restore`` took from an earlier report instead of running them, and on which
    test split those were measured."""
    sources = (report.get("restored") or {}).get("sources") or []
    ours = report_split_sha(report)
    lines = [f"**Restored, not re-run:** {', '.join(f'`{n}`' for n in src['parts'])}, from `{src['path']}` "
             f"(generated {src['generated']}). These parts do not run the pick cell; their numbers and costs are that "
             f"run's, and every other number here was run for this report.{_restored_split(src, ours)}"
             for src in sources]
    return lines + [""] if lines else []


def render_markdown(report: dict[str, Any], figures: dict[str, Path | None], out: Path) -> str:
    """The whole page, from ``run_report``'s dict; ``figures`` maps names to PNGs (linked relative to ``out``)."""
    cfg = report["config"]
    policies = report["policies"]
    lines = ["# ParcelPick evaluation report", "",
             f"Generated {report['generated']}. Offline AP on `{cfg['test_data']}` "
             f"({'all' if cfg['ap_scenes'] is None else cfg['ap_scenes']} test scenes, the same for every method); "
             + clearance_line(report),
             "Where the paper has a number, the cell reads **ours / paper**. Our numbers come from simulated ParcelPick scenes and the "
             "simulated robot; the paper's from its Parcel-Suction-Dataset and, for clearance, its real robot.",
             f"Each figure of ours carries its {100 * CONFIDENCE:.0f}% percentile bootstrap interval in brackets "
             f"({RESAMPLES} resamples): over test scenes for AP, over episodes for clearance. A method is called "
             "ahead of another only where the interval of their paired difference (same scenes, same seeds) "
             "excludes 0.", ""]
    lines += cost_lines(report)
    lines += restored_lines(report)
    lines += ["## At a glance", "",
              "Each method's headline figures, from the sections below: the share of the label oracle's Top-50 AP, "
              "and the Table V cell where its R_grasp is lowest, to read against the oracle's in that cell.", "",
              glance_table(policies), ""]
    ap_scenes = [e["ap"]["num_scenes"] for e in policies.values() if e.get("ap")]
    if ap_scenes and min(ap_scenes) < MIN_AP_SCENES:
        lines += [f"Only {min(ap_scenes)} test scenes (fewer than {MIN_AP_SCENES}): AP gaps of a few points are "
                  "not resolved at this size.", ""]
    lines += ap_section(report)
    lines += _figure(figures, "precision_at_k", f"precision@k per policy ({HEADLINE_QUALITY})", out)
    lines += paper_compat_section(report)
    lines += table_one_lines(report)
    lines += label_physics_section(report, out)
    paired = comparisons_against(DIFFUSION, policies)
    if paired:
        lines += ["## Paired comparisons with Diffusion-Suction", "",
                  "Differences 'Diffusion-Suction − method' in points: Top-50 AP over the shared test scenes, "
                  "R_grasp and R_object over the shared clearance episodes (resampled within each cell).", "",
                  comparison_table(paired, policies), ""]
    lines += ["## Closed-loop clearance (paper Table V layout)", "",
              "Entries are R_grasp / R_object (%). '(paper robot)' is the paper's real-robot Diffusion-Suction, "
              "given beside every method for reference.", ""]
    if report.get("clearance_source"):
        lines += ["Clearance here is " + clearance_line(report), ""]
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
                lines += [table_v(entry, tuple(cfg["objects"]), tuple(cfg["layouts"])), "",
                          tool_check_line(entry["clearance"]), ""]
        lines += ["### Attempt outcomes", "", outcome_table(policies), ""]
        lines += _figure(figures, "clearance", "clearance per cell", out)
        lines += ["### Failure anatomy", "",
                  "Failed attempts by kind ('outcome: move or phase'), per method and cell; the most common "
                  "failures with the link or holding condition that failed below.", "",
                  failure_table(policies, tuple(cfg["objects"]), tuple(cfg["layouts"])), "",
                  *failure_details(policies), ""]
        lines += _figure(figures, "failures", "failure causes per cell", out)
        covers = cover_table(policies)
        if covers is not None:
            lines += ["### Which parcels were picked", "",
                      "Each attempt's parcel, read on the true scene just before the pick by the evaluator "
                      "(`--audit-picks`, eval/pick_audit.py; never shown to a policy): free, or covered (another "
                      "parcel rests on it, hangs over it or leans on it above its centre of mass; the oracle's own "
                      "geometry). Lifts of covered parcels are where the torsion drops of stacked piles come from.",
                      "", covers, ""]
    lines += ["## Diffusion-Suction ablations (paper Tables III and IV)", ""]
    if cfg["skip_ablations"]:
        lines += ["Skipped (--skip-ablations).", ""]
    else:
        seeds = ", ".join(str(k) for k in cfg.get("ablation_seeds", [0]))
        lines += ["Inference-step rows reuse the main checkpoint; the other rows need their own training runs "
                  f"under `{cfg['ablation_dir']}/<name>/seed<k>/best.pt`, one per seed ({seeds}), all with the same "
                  f"settings (`{cfg['train_args']}` plus the seed and the variant's flag), so read them against the "
                  "'reference' row, not the main checkpoint, which trained longer. A trained row is the mean over its "
                  "seeds, with its 95% interval over test scenes and its std over seeds; the last column is the best "
                  "validation top-k precision each run logged (the held-out part of the training data). The paper's "
                  "DGCNN row has no counterpart here.", "",
                  ablation_table(report.get("ablations", [])), "",
                  "Each trained variant against its baseline trained with the same seed, paired over the same test "
                  "scenes: the reference, or for the more-points variant the same settings on the same "
                  f"{MORE_POINTS_TRAIN_SCENES} piles at the reference's density, both tested on the test piles at "
                  f"{MORE_POINTS:,} points. A variant is called ahead or behind only when the seed-mean difference's interval "
                  f"excludes 0 and every seed's difference has its sign, over at least {MIN_SEEDS} seeds:", "",
                  ablation_comparison_table(report.get("ablations", [])), ""]
    if report.get("provenance"):
        lines += ["## Checkpoint provenance", "", provenance_table(report["provenance"]), ""]
    lines += ["## Where our numbers differ from the paper's", ""]
    gaps = differences(report)
    lines += gaps if gaps else ["Nothing to compare: no run produced a number with a counterpart in the paper."]
    lines.append("")
    return "\n".join(lines)


def ap_section(report: dict[str, Any]) -> list[str]:
    """One Table II per quality definition, then what each channel costs the label oracle."""
    policies = report["policies"]
    qualities = tuple(report["config"].get("ap_qualities") or (HEADLINE_QUALITY,))
    lines = ["## Offline AP (paper Table II layout)", "",
             "One table per quality definition (`eval/ap.py --quality`, docs/protocols.md), each with the same "
             f"rows: every method; the **{LABEL_ORACLE}**, the registered `oracle` run through `eval/ap.py`, which "
             "submits the best stored labels, so its row is what the labels themselves score; and the "
             f"**{CEILING}**, what every slot the protocol keeps (10 per parcel) scores at q = 1, which no method "
             "can pass. AP+vis multiplies in each parcel's visibility, as the paper does for parcel scenes.", ""]
    for quality in qualities:
        lines += [f"### `{quality}`: {QUALITY_TITLES.get(quality, quality)}", ""]
        if quality == HEADLINE_QUALITY:
            lines += ["The paper's protocol, so each Table II cell reads **ours / paper**; the paired comparisons, "
                      "ablations and gaps below use this definition.", ""]
        else:
            lines += ["This project's own definition, not the paper's: ours stand alone (no paper numbers), and "
                      "this is the table to read beside the closed-loop clearance.", ""]
        lines += [table_ii(policies, quality), ""]
    lines += ["### What each channel costs the label oracle", "",
              "The label oracle's Top-50 AP with each channel, minus its AP with that channel left out (points; "
              "negative: what the channel takes away), under each definition; visibility's cost is AP+vis − AP.",
              "", channel_cost_table(policies, qualities), ""]
    return lines


def table_one_lines(report: dict[str, Any]) -> list[str]:
    """The Table I section when the report was given --graspnet-root: the tables, or the one line why not."""
    result = report.get("table_one")
    if result is None:
        return []
    from eval.table_one import format_markdown

    lines = ["## SuctionNet-1Billion (paper Table I layout)", ""]
    if "absent" in result or "error" in result:
        return lines + [result.get("absent") or f"Table I failed: {result['error']}", ""]
    lines += [format_markdown(result), ""]
    lines += [f"Not available: {name} ({why})." for name, why in result.get("not_available", {}).items()]
    return lines + ([""] if result.get("not_available") else [])


def paper_compat_section(report: dict[str, Any]) -> list[str]:
    """The paper-compatible table, with what each change does to the label oracle, from the numbers."""
    lines = ["## Paper-compatible (not a measure of picking)", ""]
    if report["config"].get("skip_paper_compat"):
        return lines + ["Skipped (--skip-paper-compat).", ""]
    rows = report.get("paper_compat") or []
    if not rows:
        return lines + ["Not measured: neither the label oracle nor Diffusion-Suction was in this report.", ""]
    return lines + [
        "Where a 94-point AP can come from. (b) sets NMS to the radius of the public Diffusion_Suction test script, "
        "which calls its NMS with 0.02 on coordinates in millimetres, so in effect it suppresses nothing; "
        "(c) scores with SuctionNet's label-time wrench (`suction_annotation/wrench_annotate.py`, quality "
        "`paper_compat`), far more lenient than its evaluator's; (d) does both. These rows show how the protocol "
        "moves the figure; they are **paper-compatible, not a measure of picking**.", "",
        paper_compat_table(rows), "", *paper_compat_sentences(rows), ""]


def label_physics_section(report: dict[str, Any], out: Path) -> list[str]:
    """How well the physical label predicts the env's own verdict (eval/label_physics.py), when measured."""
    lines = ["## Labels vs physics", ""]
    found = report.get("label_physics")
    if not found:
        return lines + ["Not measured (no `eval/label_physics.py` result at "
                        f"`{report['config'].get('label_physics', 'results/label_physics.json')}`).", ""]
    if found.get("auc") is None:
        return lines + [f"Not measured: `{found['path']}` could not be read ({found.get('error')}).", ""]
    met = "meets" if found["auc"] >= LABEL_PHYSICS_AUC_GOAL else "falls short of"
    layouts = ", ".join(f"{name} {value:.3f}" for name, value in found.get("by_layout", {}).items())
    lines += [f"ROC-AUC of the `physical` label against the env's success over {found['picks']} random candidate "
              f"picks run in the env: **{found['auc']:.3f}** [{found['low']:.3f}, {found['high']:.3f}] ({met} the "
              f"goal of {LABEL_PHYSICS_AUC_GOAL})" + (f"; by layout {layouts}" if layouts else "")
              + f". From `{found['path']}` (`python -m eval.label_physics`; docs/labels.md).", ""]
    confusion = found.get("confusion") or {}
    if "precision" in confusion:
        lines += [f"At label > 0 (a predicted hold): precision {confusion['precision']:.3f}, recall "
                  f"{confusion['recall']:.3f} ({confusion['hold_failure']} predicted holds failed, "
                  f"{confusion['fail_success']} predicted failures succeeded).", ""]
    if found.get("plot"):
        lines += [f"![reliability of the physical label]({os.path.relpath(found['plot'], out.parent)})", ""]
    return lines


def write_report(report: dict[str, Any], out: str | os.PathLike, figures_dir: str | os.PathLike) -> dict[str, Path]:
    """Write the plots, the markdown and the JSON dump; return their paths."""
    out, figures_dir = Path(out), Path(figures_dir)
    out.parent.mkdir(parents=True, exist_ok=True)
    figures = {"precision_at_k": plot_precision_at_k(report["policies"], figures_dir / "precision_at_k.png"),
               "clearance": plot_clearance(report["policies"], figures_dir / "clearance.png"),
               "failures": plot_failures(report["policies"], figures_dir / "failures.png")}
    out.write_text(render_markdown(report, figures, out))
    json_path = out.with_suffix(".json")
    # compact: the dump holds every scene and episode of every run (MBs indented); read it with json.load
    json_path.write_text(json.dumps({**report, "figures": {k: str(v) if v else None for k, v in figures.items()}},
                                    separators=(",", ":"), default=str))
    return {"markdown": out, "json": json_path, **{k: v for k, v in figures.items() if v is not None}}
