"""One ablation variant trained with several seeds: its AP over seeds, and its paired difference to the reference.

A variant's figure is the mean over its seeds, with the spread over seeds (std) beside the interval over test
scenes. Against the reference, each seed is paired with the reference trained on the same seed, and both are
paired over the same test scenes. A variant is called ahead (or behind) only when the scene interval of the
seed-mean difference excludes 0 and every seed's own difference has that sign, over at least ``MIN_SEEDS``
seeds: what one lucky seed shows is not claimed.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from eval.report.comparisons import paired_ap
from eval.report.config import AP_METRICS
from eval.stats import TIE, bootstrap_mean, paired_difference

MIN_SEEDS = 3  # issue 14: 'at least 3 seeds each'
# The figures a seed-mean result carries: Table III's three and the Top-1 AP the ablation table prints.
SEED_METRICS: tuple[str, ...] = (*AP_METRICS, "top1_AP")


def _per_scene(ap: dict[str, Any], metric: str) -> dict[int, float]:
    values, scenes = ap.get("per_scene", {}).get(metric), ap.get("scenes")
    if values is None or scenes is None or len(values) != len(scenes):
        raise ValueError(f"an AP result without per-scene {metric!r} figures cannot be averaged over seeds")
    return {int(s["index"]): float(v) for s, v in zip(scenes, values)}


def seed_mean_ap(results: list[dict[str, Any]], seeds: list[int]) -> dict[str, Any]:
    """The mean over seeds of each figure, on the scenes every seed was evaluated on.

    It has the keys a one-run AP result has for the tables (the figures, their ``intervals`` over scenes,
    ``per_scene``, ``scenes``, ``num_scenes``), plus ``seed_std`` (each figure's std over seeds, ddof 1; None for
    one seed) and ``seeds``.
    """
    if not results or len(results) != len(seeds):
        raise ValueError(f"need one AP result per seed, got {len(results)} for seeds {seeds}")
    per_seed = {metric: [_per_scene(r, metric) for r in results] for metric in SEED_METRICS}
    common = sorted(set.intersection(*(set(p) for p in per_seed["AP"])))
    if not common:
        raise ValueError("the seeds' AP results share no test scene")
    out: dict[str, Any] = {"seeds": list(seeds), "scenes": [{"index": i} for i in common], "num_scenes": len(common),
                           "intervals": {}, "per_scene": {}, "seed_std": {}}
    for metric, values in per_seed.items():
        table = np.array([[p[i] for i in common] for p in values])  # (seeds, scenes)
        scene_means = table.mean(axis=0)
        out[metric] = float(scene_means.mean())
        out["intervals"][metric] = bootstrap_mean(scene_means).to_dict()
        out["per_scene"][metric] = scene_means.tolist()
        out["seed_std"][metric] = float(table.mean(axis=1).std(ddof=1)) if len(results) > 1 else None
    return out


def seed_paired_difference(variant: dict[int, dict[str, Any]], reference: dict[int, dict[str, Any]],
                           metric: str = "AP") -> dict[str, Any] | None:
    """``variant - reference`` per shared seed (each paired over scenes), and over seeds.

    ``variant`` and ``reference`` map a seed to its AP result. Returns ``per_seed`` (seed -> interval dict),
    ``mean`` and ``std`` (None for one seed) of the seeds' differences, ``pooled`` (the seed-mean difference's interval over
    scenes), ``seeds`` and ``direction`` (+1 / -1 where the claim holds, else 0); None without a shared seed.
    """
    seeds = sorted(set(variant) & set(reference))
    per_seed = {s: paired_ap(variant[s], reference[s], metric) for s in seeds}
    per_seed = {s: d for s, d in per_seed.items() if d is not None}
    if not per_seed:
        return None
    seeds = sorted(per_seed)
    a = seed_mean_ap([variant[s] for s in seeds], seeds)
    b = seed_mean_ap([reference[s] for s in seeds], seeds)
    index_a = {int(s["index"]): v for s, v in zip(a["scenes"], a["per_scene"][metric])}
    index_b = {int(s["index"]): v for s, v in zip(b["scenes"], b["per_scene"][metric])}
    common = sorted(set(index_a) & set(index_b))
    pooled = paired_difference([index_a[i] for i in common], [index_b[i] for i in common])
    estimates = np.array([per_seed[s].estimate for s in seeds])
    sign = 1 if pooled.low > 0 else -1 if pooled.high < 0 else 0
    agree = sign != 0 and len(seeds) >= MIN_SEEDS and bool(np.all(np.sign(estimates) == sign))
    return {"per_seed": {s: per_seed[s].to_dict() for s in seeds}, "seeds": seeds,
            "mean": float(estimates.mean()), "std": float(estimates.std(ddof=1)) if len(seeds) > 1 else None,
            "pooled": pooled.to_dict(), "direction": sign if agree else 0}


def seed_verdict(diff: dict[str, Any], first: str, second: str) -> str:
    """Who is ahead on ``first - second`` over seeds, or why no one is."""
    if diff["direction"] > 0:
        return f"{first} ahead"
    if diff["direction"] < 0:
        return f"{second} ahead"
    if len(diff["seeds"]) < MIN_SEEDS:
        return f"{TIE} (only {len(diff['seeds'])} of the {MIN_SEEDS} seeds a claim needs)"
    return TIE
