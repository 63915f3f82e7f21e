"""Offline AP metrics: hand-computed cases and the protocol's edge rules."""

import numpy as np
import pytest

from eval.metrics import aggregate_ap, precision_at_k, scene_ap, select_predictions


def test_oracle_scores_100_and_colliding_predictions_score_0():
    oracle = scene_ap(scores=np.linspace(1, 0.5, 60), qualities=np.ones(60))
    colliding = scene_ap(scores=np.linspace(1, 0.5, 60), qualities=np.zeros(60))
    best = aggregate_ap([oracle])
    worst = aggregate_ap([colliding])
    for key in ("AP", "AP0.4", "AP0.8", "top1_AP", "top1_AP0.4", "top1_AP0.8"):
        assert best[key] == pytest.approx(100.0)
        assert worst[key] == pytest.approx(0.0)


def test_two_object_toy_scene_by_hand():
    # Object 0 (rectangular) gets predictions with qualities 0.9 and 0.5, object 1 (planar) 0.3.
    # Ranked by score the qualities are [0.9, 0.3, 0.5]; with max_k = 4:
    #   θ=0.2 hits 1,1,1 -> P = 1, 1, 1, 3/4        mean 0.9375
    #   θ=0.4 hits 1,0,1 -> P = 1, 1/2, 2/3, 2/4    mean 0.666...
    #   θ=0.6 hits 1,0,0 -> P = 1, 1/2, 1/3, 1/4    mean 0.520833...
    #   θ=0.8 same as 0.6                           mean 0.520833...
    # AP = mean of the four = 0.661458333 -> 66.1458 %; Top-1 = 100 for every θ.
    scores = np.array([0.5, 0.8, 0.6])  # deliberately not pre-sorted
    qualities = np.array([0.5, 0.9, 0.3])
    cats = ["rectangular", "rectangular", "planar"]
    sc = scene_ap(scores, qualities, categories=cats, max_k=4)
    expected = np.array([[1, 1, 1, 1], [1, 1 / 2, 1 / 2, 1 / 2], [1, 2 / 3, 1 / 3, 1 / 3],
                         [3 / 4, 2 / 4, 1 / 4, 1 / 4]])
    np.testing.assert_allclose(sc.precision, expected)
    res = aggregate_ap([sc])
    assert res["AP"] == pytest.approx(100 * (0.9375 + 2.6666666 / 4 + 2 * 2.0833333 / 4) / 4, abs=1e-4)
    assert res["AP"] == pytest.approx(66.1458333, abs=1e-4)
    assert res["AP0.4"] == pytest.approx(100 * 2.6666666 / 4, abs=1e-4)
    assert res["AP0.8"] == pytest.approx(100 * 2.0833333 / 4, abs=1e-4)
    assert res["top1_AP"] == pytest.approx(100.0)
    # Rectangular alone: qualities [0.9, 0.5] -> θ0.2: 1,1,2/3,2/4; θ0.4 same; θ0.6/0.8: 1,1/2,1/3,1/4.
    rect = res["per_category"]["rectangular"]
    assert rect["AP0.4"] == pytest.approx(100 * (1 + 1 + 2 / 3 + 1 / 2) / 4)
    assert rect["AP0.8"] == pytest.approx(100 * (1 + 1 / 2 + 1 / 3 + 1 / 4) / 4)
    # Planar alone: quality [0.3] -> θ0.2: 1,1/2,1/3,1/4; higher θ: 0.
    planar = res["per_category"]["planar"]
    assert planar["AP0.2"] == pytest.approx(100 * (1 + 1 / 2 + 1 / 3 + 1 / 4) / 4)
    assert planar["AP0.4"] == pytest.approx(0.0)
    assert planar["top1_AP"] == pytest.approx(25.0)


def test_denominator_stays_k_with_few_predictions():
    p = precision_at_k(np.array([1.0, 1.0]), thresholds=(0.5,), max_k=50)
    assert p.shape == (50, 1)
    np.testing.assert_allclose(p[:, 0], np.minimum(1.0, 2.0 / np.arange(1, 51)))
    empty = precision_at_k(np.zeros(0), max_k=5)
    assert empty.shape == (5, 4) and not empty.any()


def test_scene_average_and_missed_category():
    a = scene_ap(np.array([1.0]), np.array([1.0]), categories=["planar"], scene_categories=["planar", "cylindrical"],
                 max_k=1)
    b = scene_ap(np.array([1.0]), np.array([0.0]), categories=["planar"], max_k=1)
    res = aggregate_ap([a, b])
    assert res["AP"] == pytest.approx(50.0)
    assert res["num_scenes"] == 2
    assert res["per_category"]["cylindrical"]["AP"] == 0.0  # present but never predicted
    assert res["per_category"]["cylindrical"]["num_scenes"] == 1


def test_select_top10_per_object():
    rng = np.random.default_rng(0)
    n = 40
    ids = np.repeat([0, 1, 2, -1], [25, 3, 7, 5])
    scores = rng.permutation(n).astype(np.float64)
    pts = rng.normal(size=(n, 3))
    sel = select_predictions(pts, pts, scores, ids, per_object=10)
    assert len(sel) == 10 + 3 + 7
    assert np.all(np.diff(sel.scores) <= 0)
    assert np.bincount(sel.object_ids).tolist() == [10, 3, 7]
    # Object 0 keeps exactly its 10 best scores.
    best0 = np.sort(scores[ids == 0])[::-1][:10]
    np.testing.assert_allclose(np.sort(sel.scores[sel.object_ids == 0])[::-1], best0)
    np.testing.assert_array_equal(sel.points, pts[sel.index].astype(np.float32))
    empty = select_predictions(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, int))
    assert len(empty) == 0


@pytest.mark.parametrize("bad", [dict(max_k=0), dict(thresholds=(1.5,)), dict(thresholds=())])
def test_bad_arguments_raise(bad):
    with pytest.raises(ValueError):
        precision_at_k(np.ones(3), **bad)


def test_mismatched_lengths_and_nan_raise():
    with pytest.raises(ValueError):
        scene_ap(np.ones(3), np.ones(2))
    with pytest.raises(ValueError):
        scene_ap(np.array([np.nan]), np.ones(1))
    with pytest.raises(ValueError):
        select_predictions(np.zeros((2, 3)), np.zeros((2, 3)), np.ones(2), np.zeros(3), per_object=10)


def test_every_ap_figure_carries_a_bootstrap_interval_over_scenes():
    rng = np.random.default_rng(0)
    scenes = [scene_ap(rng.random(20), rng.random(20), categories=["planar"] * 20) for _ in range(30)]
    result = aggregate_ap(scenes)
    for key in ("AP", "AP0.4", "AP0.8", "top1_AP", "top1_AP0.8"):
        iv = result["intervals"][key]
        assert iv["low"] <= result[key] <= iv["high"] and iv["n"] == 30 and iv["estimate"] == pytest.approx(result[key])
        assert np.mean(result["per_scene"][key]) == pytest.approx(result[key])  # the unit the interval resamples
    assert result["intervals"]["AP"]["high"] - result["intervals"]["AP"]["low"] > 0
    assert result["per_category"]["planar"]["intervals"]["AP"] == result["intervals"]["AP"]  # the same 30 scenes
