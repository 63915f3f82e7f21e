"""The report's markdown tables: the paper's layouts with ours beside the paper's, each figure of ours with
its bootstrap 95% interval, plus paired comparisons, failure anatomy and checkpoint provenance."""

from __future__ import annotations

from itertools import pairwise
from typing import Any

from eval.clearance import LAYOUTS, OBJECT_SETS, OUTCOMES, rate_pair
from eval.paper_results import TABLE_II_TOP1, TABLE_II_TOP50, TABLE_V
from eval.report.comparisons import paired_ap
from eval.report.config import AP_METRICS, DIFFUSION, label
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


def table_ii(policies: dict[str, dict[str, Any]]) -> str:
    """Paper Table II layout, every cell 'ours [95% interval over scenes] / paper'."""
    head = ["method"] + [f"Top-50 {m}" for m in AP_METRICS] + [f"Top-1 {m}" for m in AP_METRICS]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for name, entry in policies.items():
        ap = entry.get("ap")
        paper50, paper1 = TABLE_II_TOP50.get(name, (None,) * 3), TABLE_II_TOP1.get(name, (None,) * 3)
        method = entry.get("label", label(name))
        if ap is None:
            method += f" ({_unavailable(entry) or 'failed: ' + str(entry.get('ap_error'))})"
            cells = [_pair(None, p) for p in (*paper50, *paper1)]
        else:
            cells = [_ap_pair(ap, m, p) for m, p in zip(AP_METRICS, paper50)]
            cells += [_ap_pair(ap, f"top1_{m}", p) for m, p in zip(AP_METRICS, paper1)]
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


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
    lines.append(f"\nOverall (ours): R_grasp {_ours(o, 'R_grasp')}%, R_object {_ours(o, 'R_object')}% "
                 f"({o['successes']}/{o['attempts']} attempts, {o['cleared']}/{o['placed']} parcels).")
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


def ablation_table(rows: list[dict[str, Any]]) -> str:
    head = ["variant", "status", "AP (ours / paper)", "AP0.8", "AP0.4", "Top-1 AP (ours)"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for row in rows:
        paper = row.get("paper") or (None, None, None)
        ap = row.get("ap")
        if ap is None:
            status = row["status"] + (f": {row['reason']}" if row.get("reason") else "")
            if row["status"] == "not trained":
                status += f" — train with `{row['command']}`"
            cells = [_pair(None, p) for p in paper[:3]] + ["–"]
        else:
            status = "ok" + (f" ({row['reason']})" if row.get("reason") else "")
            cells = [_ap_pair(ap, m, p) for m, p in zip(AP_METRICS, paper[:3])] + [_ours(ap, "top1_AP")]
        lines.append(f"| {row['description']} | {status} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _diff_cell(diff: dict[str, Any] | None) -> list[str]:
    return ["–", "–"] if diff is None else [format_interval(diff), diff["verdict"]]


def comparison_table(rows: list[dict[str, Any]], policies: dict[str, dict[str, Any]]) -> str:
    """Paired differences 'first - second' with their 95% intervals and who, if anyone, is ahead."""
    head = ["comparison", "Top-50 AP diff", "AP verdict", "R_grasp diff", "R_grasp verdict", "R_object diff",
            "R_object verdict"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for row in rows:
        name = f"{policies[row['first']]['label']} − {policies[row['second']]['label']}"
        cells = [c for key in ("AP", "R_grasp", "R_object") for c in _diff_cell(row.get(key))]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def ablation_comparison_table(rows: list[dict[str, Any]]) -> str:
    """Each measured trained variant against the 'reference' variant, paired over the same test scenes."""
    from eval.stats import verdict

    by_name = {row["name"]: row for row in rows}
    reference = by_name.get(REFERENCE, {}).get("ap")
    if reference is None:
        return "No 'reference' variant was measured, so no variant can be compared with it."
    lines = ["| variant | Top-50 AP diff vs reference | verdict |", "|---|---|---|"]
    for row in rows:
        if row["kind"] == "inference_steps" or row["name"] == REFERENCE or row.get("ap") is None:
            continue
        diff = paired_ap(row["ap"], reference, "AP")
        cells = ["–", "–"] if diff is None else [format_interval(diff), verdict(diff, row["description"], REFERENCE)]
        lines.append(f"| {row['description']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def failure_kinds(policies: dict[str, dict[str, Any]]) -> list[str]:
    """Every failure kind any method's clearance met, most frequent first."""
    totals: dict[str, int] = {}
    for entry in policies.values():
        for kind, n in ((entry.get("clearance") or {}).get("overall", {}).get("failures") or {}).items():
            totals[kind] = totals.get(kind, 0) + n
    return sorted(totals, key=lambda k: (-totals[k], k))


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
