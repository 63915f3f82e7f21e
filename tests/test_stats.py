"""Bootstrap intervals and paired verdicts (eval.stats) on cases with a known answer."""

from __future__ import annotations

import numpy as np
import pytest

from eval.stats import (
    TIE,
    Interval,
    bootstrap_mean,
    bootstrap_means,
    bootstrap_ratio,
    format_interval,
    paired_difference,
    paired_ratio_difference,
    resample_indices,
    verdict,
)


def test_interval_covers_a_known_bernoulli_p_about_95_percent_of_the_time():
    p, n, draws = 0.3, 120, 300
    rng = np.random.default_rng(7)
    covered = 0
    widths = []
    for d in range(draws):
        iv = bootstrap_mean(rng.random(n) < p, resamples=800, seed=d)
        covered += iv.low <= p <= iv.high
        widths.append(iv.high - iv.low)
    assert 0.90 <= covered / draws <= 0.985
    normal_width = 2 * 1.959964 * np.sqrt(p * (1 - p) / n)
    assert np.mean(widths) == pytest.approx(normal_width, rel=0.15)


def test_ratio_interval_matches_the_binomial_width_when_every_episode_has_one_attempt():
    rng = np.random.default_rng(1)
    successes = (rng.random(400) < 0.5).astype(float)
    iv = bootstrap_ratio(successes, np.ones_like(successes), scale=100.0)
    assert iv.estimate == pytest.approx(100.0 * successes.mean())
    assert iv.high - iv.low == pytest.approx(2 * 1.959964 * 100 * np.sqrt(0.25 / 400), rel=0.15)


def test_ratio_is_pooled_not_averaged_per_episode():
    iv = bootstrap_ratio([1, 9], [10, 10], scale=100.0)
    assert iv.estimate == pytest.approx(50.0) and iv.low <= 50.0 <= iv.high
    assert bootstrap_ratio([0, 0], [0, 0]).estimate != bootstrap_ratio([0, 0], [0, 0]).estimate  # no attempts: NaN


def test_a_policy_compared_with_itself_is_never_ahead():
    rng = np.random.default_rng(3)
    for seed in range(20):
        ap = rng.random(50) * 100
        d = paired_difference(ap, ap, seed=seed)
        assert (d.estimate, d.low, d.high) == (0.0, 0.0, 0.0)
        assert verdict(d, "A", "A") == TIE
        s, a = rng.integers(0, 5, 30), rng.integers(5, 10, 30)
        assert verdict(paired_ratio_difference(s, a, s, a, seed=seed), "A", "A") == TIE


def test_a_clear_paired_gap_is_resolved_where_the_unpaired_intervals_overlap():
    rng = np.random.default_rng(0)
    scene_difficulty = rng.random(50) * 60  # shared by both methods: it dominates the spread
    a, b = scene_difficulty + 3.0 + rng.normal(0, 1, 50), scene_difficulty + rng.normal(0, 1, 50)
    ia, ib = bootstrap_mean(a), bootstrap_mean(b)
    assert ia.low < ib.high  # side by side the intervals overlap ...
    d = paired_difference(a, b)
    assert d.low > 0 and verdict(d, "A", "B") == "A ahead" and verdict(paired_difference(b, a), "B", "A") == "A ahead"


def test_stratified_resamples_keep_each_stratum_size():
    strata = np.array(["x"] * 3 + ["y"] * 7)
    idx = resample_indices(10, 500, seed=0, strata=strata)
    assert idx.shape == (500, 10)
    assert np.all((strata[idx] == "x").sum(axis=1) == 3)
    assert set(np.unique(idx[strata[idx] == "y"])) == set(range(3, 10))


def test_seeded_and_vectorised_over_metrics():
    v = np.random.default_rng(0).random((40, 3))
    first, again = bootstrap_means(v), bootstrap_means(v)
    assert first == again and [iv.estimate for iv in first] == pytest.approx(v.mean(axis=0).tolist())
    one = bootstrap_mean(v[:, 1])  # the same resamples whichever way it is asked
    assert (one.low, one.high) == pytest.approx((first[1].low, first[1].high), abs=1e-12)


def test_bad_input_raises_and_formatting():
    with pytest.raises(ValueError, match="at least one unit"):
        bootstrap_mean([])
    with pytest.raises(ValueError, match="NaN"):
        bootstrap_mean([1.0, float("nan")])
    with pytest.raises(ValueError, match="same units"):
        paired_difference([1, 2], [1])
    with pytest.raises(ValueError, match="confidence"):
        bootstrap_mean([1, 2], confidence=1.5)
    iv = Interval(12.345, 10.1, 14.6, n=5)
    assert format_interval(iv) == "12.35 [10.10, 14.60]" == format_interval(iv.to_dict())
    assert format_interval(None) == "–"


def test_a_single_unit_gives_no_interval_and_no_claim():
    """One episode (make demo) has no spread to resample: printing [50, 50] would claim certainty."""
    one = bootstrap_ratio([2], [4], scale=100.0)
    assert one.estimate == 50.0 and not one.excludes(0.0)
    assert format_interval(one) == "50.00 [no interval, n=1]"
