"""Paired comparisons between methods: the same test scenes for AP, the same episode seeds for clearance.

Every method's AP result keeps its per-scene figures with the stored scene index, and every clearance
summary keeps its episodes with their grid position and seed, so two methods are matched unit by unit and
``eval.stats`` bootstraps the difference over the shared units. A method is called ahead only where that
interval excludes 0 (``eval.stats.verdict``).
"""

from __future__ import annotations

from typing import Any

from eval.clearance import RATES
from eval.stats import Interval, paired_difference, paired_ratio_difference, verdict
from eval.report.config import HEADLINE_QUALITY

# Episode fields behind each pooled rate's numerator and denominator (EpisodeResult names).
_EPISODE_FIELDS = {"successes": "successes", "attempts": "attempts", "cleared": "parcels_cleared",
                   "placed": "parcels_placed"}


def _scene_values(ap: dict[str, Any], metric: str) -> dict[int, float]:
    values = ap.get("per_scene", {}).get(metric)
    scenes = ap.get("scenes")
    if values is None or scenes is None or len(values) != len(scenes):
        return {}
    return {int(s["index"]): float(v) for s, v in zip(scenes, values)}


def paired_ap(ap_a: dict[str, Any] | None, ap_b: dict[str, Any] | None, metric: str = "AP") -> Interval | None:
    """``metric(a) - metric(b)`` over the scenes both were evaluated on; None when they share none."""
    if ap_a is None or ap_b is None:
        return None
    a, b = _scene_values(ap_a, metric), _scene_values(ap_b, metric)
    common = sorted(set(a) & set(b))
    if not common:
        return None
    return paired_difference([a[i] for i in common], [b[i] for i in common])


def _episode_key(e: dict[str, Any]) -> tuple:
    return e["objects"], e["layout"], e["episode"], e["seed"]


def paired_rate(clear_a: dict[str, Any] | None, clear_b: dict[str, Any] | None, rate: str,
                cell: str | None = None) -> Interval | None:
    """``rate(a) - rate(b)`` (pooled, percent) over the episodes both ran, optionally in one 'objects/layout'
    cell; pooled over cells, each resample keeps every cell's episode count."""
    if clear_a is None or clear_b is None:
        return None
    num, den = (_EPISODE_FIELDS[f] for f in RATES[rate])
    a = {_episode_key(e): e for e in clear_a.get("episodes", [])}
    b = {_episode_key(e): e for e in clear_b.get("episodes", [])}
    common = sorted(k for k in set(a) & set(b) if cell is None or f"{k[0]}/{k[1]}" == cell)
    if not common:
        return None
    col = {(side, f): [float(d[k][f]) for k in common] for side, d in (("a", a), ("b", b)) for f in (num, den)}
    return paired_ratio_difference(col["a", num], col["a", den], col["b", num], col["b", den], scale=100.0,
                                   strata=[f"{k[0]}/{k[1]}" for k in common])


def compare(first: dict[str, Any], second: dict[str, Any]) -> dict[str, Any]:
    """Top-50 AP (under the headline definition as ``AP``, under each other one as ``AP:<quality>``), R_grasp and
    R_object of ``first - second``: each an interval dict and a verdict (or None)."""
    out: dict[str, Any] = {"first": first["name"], "second": second["name"]}
    diffs = {"AP": paired_ap(first.get("ap"), second.get("ap"), "AP")}
    # the same Top-50 AP under each further quality definition the entries carry ("AP:physical", ...)
    theirs = second.get("ap_by_quality") or {}
    diffs.update({f"AP:{quality}": paired_ap(result, theirs.get(quality), "AP")
                  for quality, result in (first.get("ap_by_quality") or {}).items() if quality != HEADLINE_QUALITY})
    diffs.update({rate: paired_rate(first.get("clearance"), second.get("clearance"), rate) for rate in RATES})
    for key, diff in diffs.items():
        out[key] = None if diff is None else {**diff.to_dict(),
                                              "verdict": verdict(diff, first["label"], second["label"])}
    return out


def comparisons_against(reference: str, policies: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """``reference`` against every other evaluated method, in the report's order."""
    if reference not in policies:
        return []
    ref = policies[reference]
    return [compare(ref, entry) for name, entry in policies.items()
            if name != reference and (entry.get("ap") is not None or entry.get("clearance") is not None)]
