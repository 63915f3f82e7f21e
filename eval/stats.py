"""Bootstrap intervals and paired comparisons for the evaluation's figures, as pure numpy functions.

Why a bootstrap: AP is a mean over scenes and a clearance rate is a ratio pooled over episodes
(``sum(successes) / sum(attempts)``); neither is a plain binomial proportion, and the units that vary
between runs are the scenes and the episodes. Resampling those units, with every resample drawn at once
as one ``(resamples, n)`` index array, gives a percentile interval for either kind of figure.

Methods are compared on the same scenes and the same episode seeds, so the comparison resamples the shared
units once and recomputes both methods' figures on each resample: the interval of the *paired* difference,
which is much narrower than the two intervals set side by side. ``verdict`` calls a method ahead only when
that interval excludes 0.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

CONFIDENCE = 0.95
RESAMPLES = 2000  # percentile endpoints of a 95% interval move by well under 0.1 point beyond this
SEED = 0  # the same resamples every run: a report's intervals do not change when nothing else does
TIE = "no resolved difference"


@dataclass(frozen=True)
class Interval:
    """A point estimate with its percentile bootstrap interval over ``n`` resampled units."""

    estimate: float
    low: float
    high: float
    n: int
    confidence: float = CONFIDENCE
    resamples: int = RESAMPLES

    def excludes(self, value: float = 0.0) -> bool:
        return bool(self.low > value or self.high < value)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Interval:
        return cls(**{k: d[k] for k in ("estimate", "low", "high", "n", "confidence", "resamples")})


def _check(resamples: int, confidence: float) -> None:
    if resamples < 1:
        raise ValueError(f"resamples must be >= 1, got {resamples}")
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")


def resample_indices(n: int, resamples: int = RESAMPLES, seed: int = SEED,
                     strata: Sequence[Any] | np.ndarray | None = None) -> np.ndarray:
    """``(resamples, n)`` indices drawn with replacement; with ``strata``, each unit's stratum keeps its size.

    Stratifying keeps a fixed design fixed: pooled over clearance cells, every resample still holds each
    cell's episode count, as every real run does.
    """
    if n < 1:
        raise ValueError(f"need at least one unit to resample, got {n}")
    rng = np.random.default_rng(seed)
    if strata is None:
        return rng.integers(0, n, size=(resamples, n))
    labels = np.asarray(strata).reshape(-1)
    if labels.size != n:
        raise ValueError(f"strata has {labels.size} entries for {n} units")
    _, codes = np.unique(labels, return_inverse=True)
    order = np.argsort(codes, kind="stable")  # units grouped by stratum
    counts = np.bincount(codes)
    starts = np.repeat(np.r_[0, np.cumsum(counts)[:-1]], counts)  # each sorted slot's stratum start and size
    sizes = np.repeat(counts, counts)
    slots = starts + np.floor(rng.random((resamples, n)) * sizes).astype(np.int64)
    return order[slots]


def _interval(estimate: float, stats: np.ndarray, n: int, confidence: float, resamples: int) -> Interval:
    alpha = 1.0 - confidence
    finite = stats[np.isfinite(stats)]
    if finite.size == 0 or n < 2:  # one unit has no spread to resample: no interval, so no claim either
        return Interval(float(estimate), float("nan"), float("nan"), n, confidence, resamples)
    low, high = np.quantile(finite, [alpha / 2, 1 - alpha / 2])
    return Interval(float(estimate), float(low), float(high), n, confidence, resamples)


def _as_units(values: Any, name: str) -> np.ndarray:
    v = np.asarray(values, dtype=np.float64)
    if v.ndim == 0 or v.shape[0] < 1:
        raise ValueError(f"{name} must hold at least one unit, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name} contains NaN or inf")
    return v


def _ratio(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)


def bootstrap_means(values: Any, resamples: int = RESAMPLES, confidence: float = CONFIDENCE, seed: int = SEED,
                    strata: Any = None) -> list[Interval]:
    """Intervals of the column means of ``values`` (units x metrics), all from the same resamples."""
    _check(resamples, confidence)
    v = _as_units(values, "values")
    v2 = v.reshape(v.shape[0], -1)
    idx = resample_indices(v2.shape[0], resamples, seed, strata)
    stats = v2[idx].mean(axis=1)  # (resamples, metrics)
    return [_interval(v2[:, m].mean(), stats[:, m], v2.shape[0], confidence, resamples) for m in range(v2.shape[1])]


def bootstrap_mean(values: Any, resamples: int = RESAMPLES, confidence: float = CONFIDENCE, seed: int = SEED,
                   strata: Any = None) -> Interval:
    """Interval of the mean of one value per unit (per-scene AP, say)."""
    v = _as_units(values, "values").reshape(-1)
    return bootstrap_means(v[:, None], resamples, confidence, seed, strata)[0]


def bootstrap_ratio(numerators: Any, denominators: Any, scale: float = 1.0, resamples: int = RESAMPLES,
                    confidence: float = CONFIDENCE, seed: int = SEED, strata: Any = None) -> Interval:
    """Interval of the pooled ratio ``scale * sum(num) / sum(den)``, resampling the units (episodes).

    A resample whose denominators are all zero has no ratio and is left out of the percentiles.
    """
    _check(resamples, confidence)
    num, den = _as_units(numerators, "numerators").reshape(-1), _as_units(denominators, "denominators").reshape(-1)
    if num.shape != den.shape:
        raise ValueError(f"numerators {num.shape} and denominators {den.shape} must pair up")
    if np.any(den < 0):
        raise ValueError("denominators must be >= 0")
    idx = resample_indices(num.size, resamples, seed, strata)
    stats = scale * _ratio(num[idx].sum(axis=1), den[idx].sum(axis=1))
    estimate = scale * float(_ratio(np.array(num.sum()), np.array(den.sum())))
    return _interval(estimate, stats, num.size, confidence, resamples)


def paired_difference(a: Any, b: Any, resamples: int = RESAMPLES, confidence: float = CONFIDENCE,
                      seed: int = SEED, strata: Any = None) -> Interval:
    """Interval of ``mean(a) - mean(b)`` where ``a[i]`` and ``b[i]`` were measured on the same unit."""
    va, vb = _as_units(a, "a").reshape(-1), _as_units(b, "b").reshape(-1)
    if va.shape != vb.shape:
        raise ValueError(f"paired values need the same units: a has {va.size}, b has {vb.size}")
    return bootstrap_mean(va - vb, resamples, confidence, seed, strata)


def paired_ratio_difference(num_a: Any, den_a: Any, num_b: Any, den_b: Any, scale: float = 1.0,
                            resamples: int = RESAMPLES, confidence: float = CONFIDENCE, seed: int = SEED,
                            strata: Any = None) -> Interval:
    """Interval of ``ratio_a - ratio_b`` (pooled ratios), both recomputed on the same resampled episodes."""
    _check(resamples, confidence)
    arrays = [_as_units(x, name).reshape(-1) for x, name in ((num_a, "num_a"), (den_a, "den_a"),
                                                             (num_b, "num_b"), (den_b, "den_b"))]
    if len({x.size for x in arrays}) != 1:
        raise ValueError(f"paired ratios need the same episodes, got sizes {[x.size for x in arrays]}")
    na, da, nb, db = arrays
    idx = resample_indices(na.size, resamples, seed, strata)
    stats = scale * (_ratio(na[idx].sum(1), da[idx].sum(1)) - _ratio(nb[idx].sum(1), db[idx].sum(1)))
    estimate = scale * float(_ratio(np.array(na.sum()), np.array(da.sum())) - _ratio(np.array(nb.sum()),
                                                                                      np.array(db.sum())))
    return _interval(estimate, stats, na.size, confidence, resamples)


def verdict(difference: Interval, first: str, second: str) -> str:
    """Who is ahead on ``first - second``: a name only when the paired interval excludes 0, else a tie."""
    if not (np.isfinite(difference.low) and np.isfinite(difference.high)):
        return TIE
    if difference.low > 0:
        return f"{first} ahead"
    if difference.high < 0:
        return f"{second} ahead"
    return TIE


def format_interval(interval: Interval | dict[str, Any] | None, digits: int = 2) -> str:
    """``12.34 [10.10, 14.60]``; ``12.34 [no interval, n=1]`` from a single unit; '–' for a missing figure."""
    if interval is None:
        return "–"
    iv = interval if isinstance(interval, Interval) else Interval.from_dict(interval)
    if not (np.isfinite(iv.low) and np.isfinite(iv.high)):
        return f"{iv.estimate:.{digits}f} [no interval, n={iv.n}]"
    return f"{iv.estimate:.{digits}f} [{iv.low:.{digits}f}, {iv.high:.{digits}f}]"
