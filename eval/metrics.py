"""Offline AP metrics (SuctionNet protocol, docs/protocols.md), as pure vectorised functions.

Nothing here reads files or runs the scorer: ``eval/ap.py`` produces per-prediction scores, object
assignments and qualities, and these functions turn them into precision curves and AP numbers.
All AP values are reported in percent, like the paper's tables.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from eval.stats import bootstrap_means

DEFAULT_THRESHOLDS: tuple[float, ...] = (0.2, 0.4, 0.6, 0.8)
DEFAULT_MAX_K = 50


def _check_thresholds(thresholds: Sequence[float]) -> np.ndarray:
    th = np.asarray(thresholds, dtype=np.float64).reshape(-1)
    if th.size == 0 or not np.all(np.isfinite(th)) or np.any((th < 0) | (th > 1)):
        raise ValueError(f"thresholds must be a non-empty sequence in [0, 1], got {thresholds!r}")
    return th


def precision_at_k(qualities: np.ndarray, thresholds: Sequence[float] = DEFAULT_THRESHOLDS,
                   max_k: int = DEFAULT_MAX_K) -> np.ndarray:
    """``P[k-1, t] = #{i <= k : q_i >= thresholds[t]} / k`` for k = 1..max_k.

    ``qualities`` must already be sorted by descending predicted score. The denominator stays k when
    fewer than k predictions exist, so a policy that proposes little is not rewarded for it.
    """
    if max_k < 1:
        raise ValueError(f"max_k must be >= 1, got {max_k}")
    th = _check_thresholds(thresholds)
    q = np.asarray(qualities, dtype=np.float64).reshape(-1)
    if not np.all(np.isfinite(q)):
        raise ValueError("qualities contain NaN or inf")
    q = q[:max_k]
    hits = np.zeros((max_k, th.size), dtype=np.float64)
    hits[: q.size] = q[:, None] >= th[None, :]
    k = np.arange(1, max_k + 1, dtype=np.float64)[:, None]
    return np.cumsum(hits, axis=0) / k


@dataclass
class SceneAP:
    """Precision curves of one scene: overall and restricted to predictions on each object category."""

    precision: np.ndarray  # (max_k, T)
    thresholds: tuple[float, ...]
    category_precision: dict[str, np.ndarray] = field(default_factory=dict)  # category -> (max_k, T)
    num_predictions: int = 0


def scene_ap(scores: np.ndarray, qualities: np.ndarray, categories: Sequence[str] | np.ndarray | None = None,
             scene_categories: Sequence[str] | None = None,
             thresholds: Sequence[float] = DEFAULT_THRESHOLDS, max_k: int = DEFAULT_MAX_K) -> SceneAP:
    """Sort one scene's selected predictions by score and compute its precision curves.

    ``categories`` gives the category of the object each prediction was assigned to. A category's curve
    uses only the predictions on objects of that category. ``scene_categories`` lists the categories of
    the objects present in the scene: a present category with no prediction gets an all-zero curve
    (the policy missed those objects), which a categories-from-predictions view would silently skip.
    """
    s = np.asarray(scores, dtype=np.float64).reshape(-1)
    q = np.asarray(qualities, dtype=np.float64).reshape(-1)
    if s.shape != q.shape:
        raise ValueError(f"scores {s.shape} and qualities {q.shape} must have the same length")
    if not np.all(np.isfinite(s)):
        raise ValueError("scores contain NaN or inf")
    th = tuple(float(t) for t in _check_thresholds(thresholds))
    order = np.argsort(-s, kind="stable")
    result = SceneAP(precision=precision_at_k(q[order], th, max_k), thresholds=th, num_predictions=int(s.size))
    if categories is None:
        return result
    cats = np.asarray(categories, dtype=object).reshape(-1)
    if cats.shape != s.shape:
        raise ValueError(f"categories {cats.shape} must have one entry per prediction {s.shape}")
    present = set(scene_categories) if scene_categories is not None else set()
    present |= {str(c) for c in cats}
    sorted_cats = cats[order]
    sorted_q = q[order]
    for cat in sorted(present):
        result.category_precision[cat] = precision_at_k(sorted_q[sorted_cats == cat], th, max_k)
    return result


def per_scene_metrics(curves: np.ndarray, thresholds: tuple[float, ...]) -> dict[str, np.ndarray]:
    """Each AP figure of every scene (percent) from a (S, max_k, T) stack: the figure is the mean over scenes."""
    out = {"AP": curves.mean(axis=(1, 2)), "top1_AP": curves[:, 0, :].mean(axis=1)}
    for t, theta in enumerate(thresholds):
        out[f"AP{theta:g}"] = curves[:, :, t].mean(axis=1)
        out[f"top1_AP{theta:g}"] = curves[:, 0, t]
    return {name: 100.0 * values for name, values in out.items()}


def _summarise(curves: np.ndarray, thresholds: tuple[float, ...]) -> dict[str, Any]:
    """Mean precision (percent) over scenes, k and θ, for a (S, max_k, T) stack of curves, and each figure's
    bootstrap 95% interval over scenes (``intervals``; all figures from the same resamples)."""
    per_scene = per_scene_metrics(curves, thresholds)
    out: dict[str, Any] = {name: float(values.mean()) for name, values in per_scene.items()}
    out["num_scenes"] = int(curves.shape[0])
    intervals = bootstrap_means(np.stack(list(per_scene.values()), axis=1))
    out["intervals"] = {name: iv.to_dict() for name, iv in zip(per_scene, intervals)}
    return out


def aggregate_ap(per_scene: Sequence[SceneAP]) -> dict:
    """AP over scenes: AP (mean over scenes, k and θ), AP<θ> per threshold, and the same at k = 1 (Top-1).

    Keys: ``AP``, ``AP0.2``, ``AP0.4``, ... , ``top1_AP``, ``top1_AP0.4``, ..., ``num_scenes``,
    ``intervals`` (each figure's bootstrap 95% interval over scenes, ``eval.stats.Interval.to_dict``),
    ``per_scene`` (each figure per scene, in input order, for paired comparisons), ``precision_at_k`` (the
    mean curve over scenes, ``[k-1][t]`` in percent), and ``per_category`` mapping each category to the
    scalar keys and intervals, over the scenes containing it.
    """
    if len(per_scene) == 0:
        raise ValueError("aggregate_ap needs at least one scene")
    thresholds = per_scene[0].thresholds
    shape = per_scene[0].precision.shape
    for sc in per_scene:
        if sc.thresholds != thresholds or sc.precision.shape != shape:
            raise ValueError("all scenes must share thresholds and max_k")
    stack = np.stack([sc.precision for sc in per_scene])
    result = _summarise(stack, thresholds)
    result["per_scene"] = {name: v.tolist() for name, v in per_scene_metrics(stack, thresholds).items()}
    result["precision_at_k"] = (100.0 * stack.mean(axis=0)).tolist()  # (max_k, T) mean P@k curves, for plots
    result["thresholds"] = list(thresholds)
    result["max_k"] = int(shape[0])
    by_cat: dict[str, list[np.ndarray]] = {}
    for sc in per_scene:
        for cat, curve in sc.category_precision.items():
            by_cat.setdefault(cat, []).append(curve)
    result["per_category"] = {cat: _summarise(np.stack(curves), thresholds) for cat, curves in sorted(by_cat.items())}
    return result


@dataclass
class Selection:
    """Predictions kept for scoring, sorted by descending score; ``index`` points into the input arrays."""

    points: np.ndarray
    normals: np.ndarray
    scores: np.ndarray
    object_ids: np.ndarray
    index: np.ndarray

    def __len__(self) -> int:
        return int(self.scores.shape[0])


def select_predictions(points: np.ndarray, normals: np.ndarray, scores: np.ndarray, object_ids: np.ndarray,
                       per_object: int = 10) -> Selection:
    """Keep the ``per_object`` best-scored predictions assigned to each object (ids < 0 are dropped).

    Capping per object stops a policy from filling the top-50 with near-duplicates on one easy parcel.
    """
    if per_object < 1:
        raise ValueError(f"per_object must be >= 1, got {per_object}")
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    nrm = np.asarray(normals, dtype=np.float32).reshape(-1, 3)
    s = np.asarray(scores, dtype=np.float64).reshape(-1)
    ids = np.asarray(object_ids).reshape(-1).astype(np.int64)
    if not (pts.shape[0] == nrm.shape[0] == s.shape[0] == ids.shape[0]):
        raise ValueError(f"points {pts.shape}, normals {nrm.shape}, scores {s.shape} and object_ids {ids.shape} "
                         "must have the same length")
    if not np.all(np.isfinite(s)):
        raise ValueError("scores contain NaN or inf")
    # Group by object, best score first within each group (stable, so ties keep input order).
    order = np.lexsort((np.arange(s.size), -s, ids))
    sorted_ids = ids[order]
    group_start = np.r_[0, np.flatnonzero(np.diff(sorted_ids)) + 1] if s.size else np.zeros(0, dtype=np.int64)
    group_len = np.diff(np.r_[group_start, s.size])
    rank = np.arange(s.size) - np.repeat(group_start, group_len)
    keep = order[(rank < per_object) & (sorted_ids >= 0)]
    keep = keep[np.argsort(-s[keep], kind="stable")]
    return Selection(points=pts[keep], normals=nrm[keep], scores=s[keep].astype(np.float32),
                     object_ids=ids[keep], index=keep)

