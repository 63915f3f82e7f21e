"""The report's markdown tables: the paper's layouts with ours beside the paper's, each figure of ours with
its bootstrap 95% interval, plus paired comparisons, failure anatomy and checkpoint provenance."""

from __future__ import annotations

import json
from itertools import pairwise
from typing import Any

import numpy as np

from eval.clearance import LAYOUTS, OBJECT_SETS, OUTCOMES, rate_pair
from eval.paper_results import TABLE_II_TOP1, TABLE_II_TOP50, TABLE_V
from eval.report.comparisons import paired_ap
from eval.report.config import (
    AP_METRICS,
    CEILING,
    DIFFUSION,
    HEADLINE_QUALITY,
    LABEL_ORACLE,
    ORACLE,
    PAPER_COMPAT_VARIANTS,
    label,
)
from eval.report.seed_runs import seed_paired_difference, seed_verdict
from eval.report.variants import REFERENCE
from eval.stats import format_interval
from policies.provenance import FIELDS as PROVENANCE_FIELDS


def _fmt(value: float | None) -> str:
    return "–" if value is None else f"{value:.2f}"


def _pair(ours: float | None, paper: float | None) -> str:
    return f"{_fmt(ours)} / {_fmt(paper)}"


def _ours(result: dict[str, Any], key: str) -> str:
    """Our figure with its interval where the result carries one (older dumps and hand-made rows may not)."""
    interval = result.get("intervals", {}).get(key)
    return format_interval(interval) if interval else _fmt(result[key])


def _ap_pair(result: dict[str, Any], key: str, paper: float | None) -> str:
    return f"{_ours(result, key)} / {_fmt(paper)}"


def _unavailable(entry: dict[str, Any]) -> str | None:
    if entry["status"] == "ok":
        return None
    return f"{entry['status']}: {entry['reason']}"


# Table II's figures in its order (Top-50, then Top-1), then the visibility column the paper adds for parcels.
TABLE_II_KEYS: tuple[str, ...] = (*AP_METRICS, *(f"top1_{m}" for m in AP_METRICS))
TABLE_II_HEAD: tuple[str, ...] = (*(f"Top-50 {m}" for m in AP_METRICS), *(f"Top-1 {m}" for m in AP_METRICS), "AP+vis")


def ap_result(entry: dict[str, Any], quality: str = HEADLINE_QUALITY) -> dict[str, Any] | None:
    """An entry's AP under one definition; older entries hold only the headline one, as ``ap``."""
    by_quality = entry.get("ap_by_quality") or {}
    if quality in by_quality:
        return by_quality[quality]
    return entry.get("ap") if quality == HEADLINE_QUALITY else None


def distinct_results(results: list[dict[str, Any] | None]) -> list[dict[str, Any]]:
    """Each AP run once: ``ap`` is one of ``ap_by_quality``'s, and a paper-compatible row (a) the entry's own,
    also after a JSON round trip has made them separate copies (the same policy, data and protocol)."""
    unique: dict[Any, dict[str, Any]] = {}
    for r in results:
        if r is not None:
            key = (json.dumps([r.get("policy"), r.get("data"), r.get("config")], sort_keys=True, default=str)
                   if "config" in r else id(r))
            unique.setdefault(key, r)
    return list(unique.values())


def ap_results(entry: dict[str, Any]) -> list[dict[str, Any]]:
    """Every AP result an entry holds, each once."""
    return distinct_results([entry.get("ap"), *(entry.get("ap_by_quality") or {}).values()])


def ap_label(name: str, entry: dict[str, Any]) -> str:
    """A method's name in the AP tables, where the registered oracle submits the best stored labels."""
    return LABEL_ORACLE if name == ORACLE else entry.get("label", label(name))


def ceiling_of(policies: dict[str, dict[str, Any]], quality: str = HEADLINE_QUALITY) -> dict[str, Any] | None:
    """The q = 1 ceiling's figures from the first result that carries one (it depends on the scenes only)."""
    for entry in policies.values():
        result = ap_result(entry, quality)
        if result is not None and result.get("ceiling"):
            return result["ceiling"]
    return None


def _why_missing(entry: dict[str, Any], quality: str) -> str:
    unavailable = _unavailable(entry)
    if unavailable:
        return unavailable
    error = (entry.get("ap_errors") or {}).get(quality) or (entry.get("ap_error") if quality == HEADLINE_QUALITY
                                                            else None)
    return f"failed: {error}" if error else "not measured"


def _ceiling_vis(ceiling: dict[str, Any]) -> dict[str, Any]:
    """The ceiling holds for AP+vis too: q = 1 on every kept slot, visibility included."""
    return {**ceiling, "AP+vis": ceiling["AP"],
            "intervals": {**ceiling.get("intervals", {}), "AP+vis": ceiling.get("intervals", {}).get("AP")}}


def table_ii(policies: dict[str, dict[str, Any]], quality: str = HEADLINE_QUALITY) -> str:
    """Paper Table II layout under one quality definition, plus AP+vis: every figure of ours with its 95% interval
    over scenes, the label oracle's row and a last q = 1 ceiling row. Under ``suctionnet`` (the paper's protocol)
    each Table II cell reads 'ours / paper'; under any other definition ours stand alone."""
    with_paper = quality == HEADLINE_QUALITY
    lines = ["| method | " + " | ".join(TABLE_II_HEAD) + " |", "|---" * (len(TABLE_II_HEAD) + 1) + "|"]

    def cells(result: dict[str, Any] | None, paper: tuple[float | None, ...] | None) -> list[str]:
        ours = [None if result is None else _ours(result, key) for key in (*TABLE_II_KEYS, "AP+vis")]
        ours = ["–" if cell is None else cell for cell in ours]
        if not with_paper or paper is None:
            return ours
        return [f"{cell} / {_fmt(p)}" for cell, p in zip(ours, paper)] + ours[len(paper):]

    for name, entry in policies.items():
        result = ap_result(entry, quality)
        if result is not None and "AP+vis" not in result:
            result = {**result, "AP+vis": None}  # an older result, before the visibility column
        method = ap_label(name, entry) + ("" if result is not None else f" ({_why_missing(entry, quality)})")
        paper = (*TABLE_II_TOP50.get(name, (None,) * 3), *TABLE_II_TOP1.get(name, (None,) * 3))
        lines.append(f"| {method} | " + " | ".join(cells(result, paper)) + " |")
    ceiling = ceiling_of(policies, quality)
    lines.append(f"| {CEILING} | " + " | ".join(cells(None if ceiling is None else _ceiling_vis(ceiling), None))
                 + " |")
    return "\n".join(lines)


def channel_cost_table(policies: dict[str, dict[str, Any]], qualities: tuple[str, ...]) -> str:
    """What each channel costs the label oracle, per definition: its Top-50 AP with the channel minus without it
    (``channel_cost`` negated), and visibility's cost, AP+vis minus AP (points)."""
    from eval.ap import CHANNELS

    head = ["definition", "label oracle Top-50 AP", *CHANNELS, "visibility (AP+vis − AP)"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    entry = policies.get(ORACLE, {})
    for quality in qualities:
        result = ap_result(entry, quality)
        if result is None:
            reason = _why_missing(entry, quality) if entry else "the oracle was not in this report"
            lines.append(f"| `{quality}` | {reason} |" + " – |" * (len(head) - 2))
            continue
        costs = result.get("channel_cost") or {}
        vis = result.get("AP+vis")
        cells = [_ours(result, "AP"), *(_fmt(None if c not in costs else 0.0 - costs[c]) for c in CHANNELS),
                 _fmt(None if vis is None else vis - result["AP"])]
        lines.append(f"| `{quality}` | " + " | ".join(cells) + " |")
    return "\n".join(lines)


PAPER_COMPAT_KEYS: tuple[str, ...] = ("AP", "AP0.8", "AP0.4", "top1_AP", "AP+vis")


def paper_compat_table(rows: list[dict[str, Any]]) -> str:
    """The label oracle (and Diffusion-Suction) under SuctionNet's evaluator and the paper-compatible variants."""
    head = ["method", "protocol", "Top-50 AP", "Top-50 AP0.8", "Top-50 AP0.4", "Top-1 AP", "AP+vis"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for row in rows:
        method = ap_label(row["name"], row)
        if row["status"] != "ok":
            lines.append(f"| {method} | {row['status']}: {row['reason']} |" + " – |" * (len(head) - 2))
            continue
        for variant in PAPER_COMPAT_VARIANTS:
            result = row["results"].get(variant.name)
            if result is None:
                why = row["errors"].get(variant.name, "not measured")
                lines.append(f"| {method} | {variant.description} (failed: {why}) |" + " – |" * (len(head) - 2))
                continue
            cells = [_ours(result, key) if result.get(key) is not None else "–" for key in PAPER_COMPAT_KEYS]
            lines.append(f"| {method} | {variant.description} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _change(result: dict[str, Any], base: dict[str, Any]) -> str:
    """'raises its Top-50 AP from X to Y (+d points; paired over the same scenes [..])'."""
    diff = result["AP"] - base["AP"]
    paired = paired_ap(result, base, "AP")
    interval = "" if paired is None else f"; paired over the same scenes {format_interval(paired)}"
    if diff == 0:
        return (f"leaves its Top-50 AP at {_fmt(base['AP'])} (0 points{interval}): its candidates already differ "
                "wherever this change would act (a policy's own NMS spreads them out)")
    return (f"{'raises' if diff > 0 else 'lowers'} its Top-50 AP from {_fmt(base['AP'])} to {_fmt(result['AP'])} "
            f"({diff:+.2f} points{interval})")


PAPER_COMPAT_EFFECTS: dict[str, str] = {  # what each variant changes, said beside the measured change
    "nms": "NMS at the public Diffusion_Suction script's radius (in effect none) lets near-duplicates of the best "
           "points fill every parcel's 10 slots",
    "wrench": "SuctionNet's label-time wrench passes off-centre picks its evaluator rejects",
    "both": "the two changes together",
}


def paper_compat_sentences(rows: list[dict[str, Any]]) -> list[str]:
    """One sentence per paper-compatible change, for each method measured, from its numbers."""
    out = []
    for row in rows:
        base = row.get("results", {}).get(PAPER_COMPAT_VARIANTS[0].name)
        if row["status"] != "ok" or base is None:
            continue
        method = ap_label(row["name"], row)
        for variant in PAPER_COMPAT_VARIANTS[1:]:
            result = row["results"].get(variant.name)
            if result is not None:
                out.append(f"- {method}, {variant.description}: {PAPER_COMPAT_EFFECTS[variant.name]}; this "
                           + _change(result, base) + ".")
    paper = TABLE_II_TOP50.get(DIFFUSION)
    if out and paper:
        out.append(f"- For scale: the paper reports {paper[0]:.2f} Top-50 AP for Diffusion-Suction.")
    return out


def table_v(entry: dict[str, Any], objects=OBJECT_SETS, layouts=LAYOUTS) -> str:
    """Paper Table V layout for one policy: R_grasp / R_object (%) per cell, ours (with 95% intervals over
    episodes) beside the paper's robot."""
    summary = entry["clearance"]
    head = ["object set"] + [f"{layout} {who}" for layout in layouts for who in ("(ours)", "(paper robot)")]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for obj in objects:
        cells = []
        for layout in layouts:
            cell = summary["cells"].get(f"{obj}/{layout}")
            paper = TABLE_V.get((obj, layout))
            cells.append("–" if cell is None else rate_pair(cell))
            cells.append("–" if paper is None else f"{paper[0]:.2f} / {paper[1]:.2f}")
        lines.append(f"| {obj} | " + " | ".join(cells) + " |")
    o = summary["overall"]
    pushes = f"; {o['pushes']} parting pushes, which are no attempts" if o.get("pushes") else ""
    lines.append(f"\nOverall (ours): R_grasp {_ours(o, 'R_grasp')}%, R_object {_ours(o, 'R_object')}% "
                 f"({o['successes']}/{o['attempts']} attempts, {o['cleared']}/{o['placed']} parcels{pushes}).")
    return "\n".join(lines)


GLANCE_HEAD: tuple[str, ...] = ("method", f"Top-50 AP `{HEADLINE_QUALITY}`", "of the label oracle's",
                                 "Top-50 AP `physical`", "R_grasp", "R_object", "lowest Table V cell, R_grasp")


def glance_table(policies: dict[str, dict[str, Any]]) -> str:
    """One row per method, the page's headline figures side by side: Top-50 AP under both definitions (and the
    share of the label oracle's, issue 14's offline goal), the pooled clearance rates, and the Table V cell where
    R_grasp is lowest (the closed-loop goal is per cell). The oracle's row reads its label oracle offline and its
    own picks in the cell; '–' where a part was not measured."""
    oracle = ap_result(policies.get(ORACLE, {}))
    lines = ["| " + " | ".join(GLANCE_HEAD) + " |", "|---" * len(GLANCE_HEAD) + "|"]
    for name, entry in policies.items():
        headline, physical = ap_result(entry), ap_result(entry, "physical")
        share = ("–" if headline is None or oracle is None or not oracle["AP"]
                 else f"{100.0 * headline['AP'] / oracle['AP']:.1f}%")
        summary = entry.get("clearance")
        rates, lowest = ["–", "–"], "–"
        if summary is not None:
            rates = [_ours(summary["overall"], key) for key in ("R_grasp", "R_object")]
            if summary["cells"]:
                cell, worst = min(summary["cells"].items(), key=lambda kv: kv[1]["R_grasp"])
                lowest = f"{cell.replace('/', ' ')}: {worst['R_grasp']:.2f}"
        method = f"{ap_label(name, entry)} / {entry['label']}" if name == ORACLE else entry["label"]
        cells = ["–" if headline is None else _ours(headline, "AP"), share,
                 "–" if physical is None else _ours(physical, "AP"), *rates, lowest]
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def outcome_table(policies: dict[str, dict[str, Any]]) -> str:
    """Where the attempts went, per policy: the failure modes the rates hide."""
    head = ["method", "attempts", *OUTCOMES]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for entry in policies.values():
        if entry.get("clearance") is None:
            continue
        o = entry["clearance"]["overall"]
        lines.append(f"| {entry['label']} | {o['attempts']} | "
                     + " | ".join(str(o["outcomes"].get(k, 0)) for k in OUTCOMES) + " |")
    return "\n".join(lines)


def _seed_cell(ap: dict[str, Any], key: str) -> str:
    """A seed-mean figure with its interval over scenes and, for several seeds, its std over seeds."""
    std = ap.get("seed_std", {}).get(key)
    spread = f" ± {std:.2f} (std, {len(ap['seeds'])} seeds)" if std is not None and len(ap["seeds"]) > 1 else ""
    return _ours(ap, key) + spread


def ablation_table(rows: list[dict[str, Any]]) -> str:
    """Table III / IV layout: each variant's AP (the mean over its seeds when trained) and best validation figure."""
    head = ["variant", "status", "AP (ours / paper)", "AP0.8", "AP0.4", "Top-1 AP (ours)", "best val top-k precision"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for row in rows:
        paper = row.get("paper") or (None, None, None)
        ap = row.get("ap")
        runs = row.get("runs") or []
        status = row["status"] + (f": {row['reason']}" if row.get("reason") else "")
        missing = [run for run in runs if run["status"] == "not trained"]
        if missing:
            status += " — train with " + "; ".join(f"`{run['command']}`" for run in missing)
        if ap is None:
            cells = [_pair(None, p) for p in paper[:3]] + ["–"]
        elif "seeds" in ap:
            cells = [f"{_seed_cell(ap, m)} / {_fmt(p)}" for m, p in zip(AP_METRICS, paper[:3])]
            cells.append(_seed_cell(ap, "top1_AP"))
        else:
            cells = [_ap_pair(ap, m, p) for m, p in zip(AP_METRICS, paper[:3])] + [_ours(ap, "top1_AP")]
        val = [run["val_ap_proxy"] for run in runs if run.get("val_ap_proxy") is not None]
        cells.append("–" if not val else f"{np.mean(val):.3f}" + (f" ± {np.std(val, ddof=1):.3f}" if len(val) > 1
                                                                    else ""))
        lines.append(f"| {row['description']} | {status} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _diff_cell(diff: dict[str, Any] | None) -> list[str]:
    return ["–", "–"] if diff is None else [format_interval(diff), diff["verdict"]]


def comparison_table(rows: list[dict[str, Any]], policies: dict[str, dict[str, Any]]) -> str:
    """Paired differences 'first - second' with their 95% intervals and who, if anyone, is ahead."""
    extra = sorted({key for row in rows for key in row if key.startswith("AP:")})
    keys = ("AP", *extra, "R_grasp", "R_object")
    titles = {"AP": f"Top-50 AP ({HEADLINE_QUALITY})", "R_grasp": "R_grasp", "R_object": "R_object",
              **{key: f"Top-50 AP ({key[3:]})" for key in extra}}
    head = ["comparison", *(f"{titles[key]} {part}" for key in keys for part in ("diff", "verdict"))]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for row in rows:
        name = f"{policies[row['first']]['label']} − {policies[row['second']]['label']}"
        cells = [c for key in keys for c in _diff_cell(row.get(key))]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def ablation_comparison_table(rows: list[dict[str, Any]]) -> str:
    """Each measured trained variant against its baseline (the 'reference', or for a variant with its own data the
    variant trained on the same piles at the reference's density), trained with the same seeds and paired over the
    same test scenes (``seed_runs.seed_paired_difference``); the verdict needs every seed to agree."""
    by_name = {row["name"]: row for row in rows}
    lines = ["| variant | read against | seeds | Top-50 AP diff: mean ± std over seeds | seed-mean diff [95% over "
             "scenes] | per seed | verdict |", "|---|---|---|---|---|---|---|"]
    for row in rows:
        name = row.get("baseline", REFERENCE)  # rows stored before baselines existed: the reference
        if row["kind"] != "trained" or name in (None, row["name"]) or row.get("ap") is None:
            continue
        base = by_name.get(name, {})
        baseline = {run["seed"]: run["ap"] for run in base.get("runs", []) if run["ap"]}
        label = name  # the baseline by its short name: its description is in the table above
        if not baseline:
            lines.append(f"| {row['description']} | {label} | 0 | – | – | – | its baseline '{name}' was not measured |")
            continue
        if base.get("test_data") != row.get("test_data"):  # scene k of one split is not scene k of the other
            lines.append(f"| {row['description']} | {label} | 0 | – | – | – | not paired: tested on "
                         f"{row.get('test_data')}, its baseline on {base.get('test_data')} |")
            continue
        diff = seed_paired_difference({run["seed"]: run["ap"] for run in row["runs"] if run["ap"]}, baseline)
        if diff is None:
            lines.append(f"| {row['description']} | {label} | 0 | – | – | – | no seed shared with its baseline |")
            continue
        per_seed = ", ".join(f"{seed}: {d['estimate']:+.2f}" for seed, d in diff["per_seed"].items())
        spread = "" if diff["std"] is None else f" ± {diff['std']:.2f}"
        lines.append(f"| {row['description']} | {label} | {len(diff['seeds'])} | {diff['mean']:+.2f}{spread} | "
                     f"{format_interval(diff['pooled'])} | {per_seed} | "
                     f"{seed_verdict(diff, row['description'], label)} |")
    return "\n".join(lines)


def failure_kinds(policies: dict[str, dict[str, Any]]) -> list[str]:
    """Every failure kind any method's clearance met, most frequent first."""
    totals: dict[str, int] = {}
    for entry in policies.values():
        for kind, n in ((entry.get("clearance") or {}).get("overall", {}).get("failures") or {}).items():
            totals[kind] = totals.get(kind, 0) + n
    return sorted(totals, key=lambda k: (-totals[k], k))


def _held(row: dict[str, int] | None) -> str:
    return "–" if not row else f"{row['successes']}/{row['attempts']} ({100 * row['successes'] / row['attempts']:.0f}%)"


def cover_table(policies: dict[str, dict[str, Any]]) -> str | None:
    """Held / picks on free parcels and on parcels others rest or lean on (``--audit-picks``, eval/pick_audit.py),
    per method whose every cell was audited; None when none was."""
    head = ["method", "held / picks of free parcels", "held / picks of covered parcels",
            "covered, taken while a free one was left", "held / picks off every parcel"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for entry in policies.values():
        summary = entry.get("clearance")
        if summary is None or not all("by_cover" in cell for cell in summary["cells"].values()):
            continue
        rows = summary["overall"]["by_cover"]
        lines.append(f"| {entry['label']} | {_held(rows.get('free'))} | {_held(rows.get('covered'))} | "
                     f"{rows.get('covered', {}).get('while_free_left', 0)} | {_held(rows.get('none'))} |")
    return "\n".join(lines) if len(lines) > 2 else None


def failure_table(policies: dict[str, dict[str, Any]], objects=OBJECT_SETS, layouts=LAYOUTS) -> str:
    """Failed attempts per method, failure kind ('outcome: phase') and cell, and over all cells."""
    cells = [f"{o}/{la}" for o in objects for la in layouts]
    head = ["method", "failure", *cells, "all"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    kinds = failure_kinds(policies)
    for entry in policies.values():
        summary = entry.get("clearance")
        if summary is None:
            continue
        for kind in kinds:
            total = summary["overall"].get("failures", {}).get(kind, 0)
            if not total:
                continue
            counts = [str(summary["cells"].get(c, {}).get("failures", {}).get(kind, 0)) for c in cells]
            lines.append(f"| {entry['label']} | {kind} | " + " | ".join(counts) + f" | {total} |")
    return "\n".join(lines)


def failure_details(policies: dict[str, dict[str, Any]], top: int = 5) -> list[str]:
    """Each method's most common failures with the link or holding condition that failed."""
    out = []
    for entry in policies.values():
        causes = ((entry.get("clearance") or {}).get("overall", {}).get("causes") or {})
        if causes:
            ranked = sorted(causes.items(), key=lambda kv: (-kv[1], kv[0]))[:top]
            out.append(f"- {entry['label']}: " + "; ".join(f"{k} × {n}" for k, n in ranked) + ".")
    return out


def _wall(value: Any) -> str:
    return f"{value:.0f} s" if isinstance(value, (int, float)) else str(value)


def provenance_table(records: dict[str, dict[str, Any]]) -> str:
    """Where each evaluated checkpoint came from; 'not recorded' where nobody wrote it down."""
    head = ["method", "checkpoint", *PROVENANCE_FIELDS, "recorded in"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for name, rec in records.items():
        values = [f"`{rec['checkpoint']}`"] + [
            _wall(rec[k]) if k == "wall_time_s" else f"`{rec[k]}`" if k == "command" else str(rec[k])
            for k in PROVENANCE_FIELDS] + [str(rec.get("source"))]
        lines.append(f"| {label(name)} | " + " | ".join(values) + " |")
    notes = [f"- {label(name)}: {rec['note']}" for name, rec in records.items() if rec.get("note")]
    return "\n".join(lines + ([""] + notes if notes else []))


def _gap(what: str, result: dict[str, Any], key: str, paper: float) -> str:
    """One signed gap to the paper; ours with its interval where the result carries one."""
    diff = result[key] - paper
    word = "above" if diff > 0 else "below" if diff < 0 else "equal to"
    return f"- {what}: ours {_ours(result, key)}, paper {paper:.2f} ({diff:+.2f} points, {word} the paper)."


def differences(report: dict[str, Any]) -> list[str]:
    """Every number we can set beside the paper's, and whether the methods rank as in the paper."""
    out: list[str] = []
    policies = report["policies"]
    for name, entry in policies.items():
        ap = entry.get("ap")
        if ap is None:
            if name in TABLE_II_TOP50:
                why = _unavailable(entry) or f"failed: {entry.get('ap_error')}"
                out.append(f"- {label(name)}: no AP of ours to compare ({why}).")
            continue
        for table, prefix in ((TABLE_II_TOP50, ""), (TABLE_II_TOP1, "top1_")):
            if name in table:
                for metric, paper in zip(AP_METRICS, table[name]):
                    out.append(_gap(f"{label(name)} {'Top-1' if prefix else 'Top-50'} {metric}",
                                    ap, prefix + metric, paper))
    ours = {n: e["ap"]["AP"] for n, e in policies.items() if e.get("ap") is not None and n in TABLE_II_TOP50}
    if len(ours) >= 2:
        our_rank = sorted(ours, key=lambda n: -ours[n])
        paper_rank = sorted(ours, key=lambda n: -TABLE_II_TOP50[n][0])
        same = "the same as" if our_rank == paper_rank else "NOT the same as"
        out.append(f"- Top-50 AP ranking: ours {' > '.join(map(label, our_rank))}; this is {same} the paper's "
                   f"({' > '.join(map(label, paper_rank))}).")
        resolved = []
        for first, second in pairwise(our_rank):
            diff = paired_ap(policies[first]["ap"], policies[second]["ap"], "AP")
            if diff is not None:
                word = "resolved" if diff.excludes(0.0) else "NOT resolved"
                resolved.append(f"{label(first)} over {label(second)} {word} "
                                f"(paired difference {format_interval(diff)})")
        if resolved:
            out.append("- Each step of that ranking, on the same scenes: " + "; ".join(resolved) + ".")
    diffusion = policies.get(DIFFUSION, {})
    if diffusion.get("clearance") is not None:
        for (obj, layout), (grasp, obj_rate) in TABLE_V.items():
            cell = diffusion["clearance"]["cells"].get(f"{obj}/{layout}")
            if cell is not None:
                out.append(_gap(f"Diffusion-Suction clearance {obj}/{layout} R_grasp (simulation vs real robot)",
                                cell, "R_grasp", grasp))
                out.append(_gap(f"Diffusion-Suction clearance {obj}/{layout} R_object (simulation vs real robot)",
                                cell, "R_object", obj_rate))
    for row in report.get("ablations", []):
        if row.get("ap") is not None and row.get("paper"):
            for metric, paper in zip(AP_METRICS, row["paper"][:3]):
                out.append(_gap(f"ablation '{row['description']}' {metric}", row["ap"], metric, paper))
    return out
