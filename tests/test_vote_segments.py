"""Vote segments on clouds with known answers: the votes split what geometry joins, the surface what votes join,
and a segment's visible top fixes a centre that every vote misses."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from centre_heads import constant_head
from policies.diffusion.checkpoint import DEFAULT_CHECKPOINT, load_model
from policies.diffusion.vote_policy import DiffusionCentreVotePolicy
from policies.diffusion.vote_segments import (bin_interior, covered_fraction, median_spacing, top_centres,
                                             vote_segments)
from policies.surface_segments import radius_components, segment_means

UP = (0.0, 0.0, 1.0)


def _plate(x0, x1, y0, y1, z, spacing=0.005):
    """A horizontal grid of points over [x0, x1) x [y0, y1) at height z."""
    u, v = np.meshgrid(np.arange(x0, x1 - 1e-9, spacing), np.arange(y0, y1 - 1e-9, spacing))
    return np.c_[u.ravel(), v.ravel(), np.full(u.size, z)]


def test_touching_tops_are_split_by_their_votes_and_joined_without_them():
    a, b = _plate(0.0, 0.10, 0.0, 0.10, 0.05), _plate(0.10, 0.20, 0.0, 0.10, 0.05)  # one flat surface, no gap
    points = np.r_[a, b]
    own = np.r_[np.tile((0.05, 0.05, 0.0), (len(a), 1)), np.tile((0.15, 0.05, 0.0), (len(b), 1))]
    labels = vote_segments(points, own, radius=0.01, vote_gap=0.08)
    assert len(np.unique(labels[: len(a)])) == 1 and len(np.unique(labels[len(a):])) == 1
    assert labels[0] != labels[-1]  # centres 10 cm apart: beyond the gap
    assert len(np.unique(vote_segments(points, own, radius=0.01, vote_gap=0.12))) == 1
    assert len(np.unique(vote_segments(points, np.zeros_like(points), radius=0.01, vote_gap=0.08))) == 1


def test_a_step_splits_tops_whose_votes_agree():
    low, high = _plate(0.0, 0.10, 0.0, 0.10, 0.0), _plate(0.10, 0.20, 0.0, 0.10, 0.03)  # a 3 cm step
    labels = vote_segments(np.r_[low, high], np.zeros((len(low) + len(high), 3)), radius=0.01, vote_gap=0.08)
    assert len(np.unique(labels)) == 2


def test_a_large_mailer_whose_votes_drift_is_one_segment_centred_on_its_top():
    """40 x 30 cm: every vote misses the centre by up to 4 cm, drifting across the face; the top's centroid is exact."""
    points = _plate(-0.20, 0.20, -0.15, 0.15, 0.02)
    centre = points.mean(axis=0)
    votes = centre + np.c_[0.1 * points[:, 0], 0.1 * points[:, 1] + 0.02, np.zeros(len(points))]
    labels = vote_segments(points, votes, radius=0.01, vote_gap=0.08)
    assert len(np.unique(labels)) == 1
    tops, found, shift = top_centres(points, np.tile(UP, (len(points), 1)), labels, up_cos=0.9, min_points=5)
    assert found.all() and not shift.any()  # no votes given: no shift
    np.testing.assert_allclose(tops, np.tile(centre, (len(points), 1)), atol=1e-9)


def test_a_top_is_its_up_facing_points_and_too_few_leave_the_votes():
    top = _plate(0.0, 0.10, 0.0, 0.10, 0.10)
    side = np.c_[np.full(40, 0.10), np.linspace(0.0, 0.095, 40), np.linspace(0.0, 0.095, 40)]  # a wall below it
    points = np.r_[top, side]
    normals = np.r_[np.tile(UP, (len(top), 1)), np.tile((1.0, 0.0, 0.0), (len(side), 1))]
    labels = np.zeros(len(points), dtype=np.int64)
    labels[-3:] = 1  # a fragment showing three up-facing points (its normals made up-facing below)
    normals[-3:] = UP
    tops, found, _ = top_centres(points, normals, labels, up_cos=0.9, min_points=5)
    np.testing.assert_allclose(tops[0], top.mean(axis=0), atol=1e-12)  # the wall does not pull the centre down
    np.testing.assert_allclose(tops[len(top)], top.mean(axis=0), atol=1e-12)
    assert found[: -3].all() and not found[-3:].any() and np.isnan(tops[-3:]).all()
    _, found, _ = top_centres(points, normals, labels, up_cos=0.9, min_points=3)
    assert found.all()


def test_median_spacing_is_the_typical_nearest_neighbour_distance():
    assert median_spacing(_plate(0.0, 0.10, 0.0, 0.10, 0.0, 0.005)) == pytest.approx(0.005)
    assert median_spacing(_plate(0.0, 0.30, 0.0, 0.30, 0.0, 0.015)) == pytest.approx(0.015)
    assert median_spacing(np.zeros((1, 3))) == 0.0 and median_spacing(np.zeros((3, 3))) == 0.0


def test_segment_means_and_radius_components_on_known_answers():
    means, counts = segment_means(np.array([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]]), np.array([0, 0, 2]), count=4)
    np.testing.assert_array_equal(counts, [2, 0, 1, 0])
    np.testing.assert_allclose(means[[0, 2]], [[2.0, 3.0], [5.0, 6.0]])
    assert np.isnan(means[[1, 3]]).all()
    row = np.c_[[0.0, 0.009, 0.018, 0.05], np.zeros(4), np.zeros(4)]
    np.testing.assert_array_equal(radius_components(row, 0.01), [0, 0, 0, 1])
    np.testing.assert_array_equal(radius_components(row, 0.01, lambda a, b: a != 0), [0, 1, 1, 2])
    with pytest.raises(ValueError, match="radius"):
        radius_components(row, 0.0)
    np.testing.assert_array_equal(radius_components(row, 0.01, tree=cKDTree(row)), [0, 0, 0, 1])  # a shared build
    with pytest.raises(ValueError, match="tree holds 3 points"):
        radius_components(row, 0.01, tree=cKDTree(row[:3]))


@pytest.mark.parametrize("spacing", [0.005, 0.01])
def test_the_policy_scores_about_the_segments_top_and_without_segments_about_the_votes(spacing):
    """At either density the segments' radius (2 spacings) joins the plate into one parcel."""
    model, _ = load_model(DEFAULT_CHECKPOINT)
    points = _plate(0.0, 0.12, 0.0, 0.08, 0.04, spacing).astype(np.float32)
    normals = np.tile(UP, (len(points), 1)).astype(np.float32)
    features, channels = torch.zeros(len(points), model.encode_width), np.ones((len(points), 3), dtype=np.float32)
    offset = (0.0, 0.0, -0.02)  # each point votes 2 cm under itself: the votes spread over the whole plate
    kwargs = dict(model=model, voters=0, record_trajectory=False)
    on = DiffusionCentreVotePolicy(centre_head=constant_head(model.encode_width, offset, 0.01, segment_spacings=2.0),
                                   **kwargs)
    assert on.centre_head.config.segment_vote_gap == 0.16
    quality = on.quality(points, normals, features, channels)
    centre = points.mean(axis=0)
    np.testing.assert_allclose(on.last_centres, np.tile(centre, (len(points), 1)), atol=1e-6)
    np.testing.assert_allclose(on.last_spread, 0.0, atol=1e-9)  # a whole top that its votes agree with: exact
    from_centre = np.linalg.norm(points[:, :2] - centre[:2], axis=1)
    assert quality[np.argmin(from_centre)] == pytest.approx(quality.max(), rel=1e-5)  # the middle first (exact: ties)
    assert quality.max() > 0
    assert quality[np.argmax(from_centre)] < quality.max()
    off = DiffusionCentreVotePolicy(centre_head=constant_head(model.encode_width, offset, 0.01, segment_spacings=2.0),
                                    segment_spacings=0.0, **kwargs)
    off.quality(points, normals, features, channels)
    np.testing.assert_allclose(off.last_centres, points + np.asarray(offset), atol=1e-6)
    np.testing.assert_allclose(off.last_spread, 0.01, rtol=1e-5)  # the votes' centres keep the votes' error


def test_the_votes_wrench_replaces_the_models_wrench_channel_unless_asked_to_keep_it():
    """Seal, wrench and collision channels (the labels' columns): a model wrench channel falling across the plate
    moves the ranking only with ``model_wrench``; the other channels always count."""
    model, _ = load_model(DEFAULT_CHECKPOINT)
    points = _plate(0.0, 0.12, 0.0, 0.08, 0.04).astype(np.float32)
    normals = np.tile(UP, (len(points), 1)).astype(np.float32)
    features = torch.zeros(len(points), model.encode_width)
    channels = np.ones((len(points), 3), dtype=np.float32)
    kwargs = dict(model=model, voters=0, record_trajectory=False)
    head = constant_head(model.encode_width, (0.0, 0.0, -0.02), segment_spacings=2.0)
    replaced = DiffusionCentreVotePolicy(centre_head=head, **kwargs)
    plain = replaced.quality(points, normals, features, channels)
    channels[:, 1] = np.linspace(1.0, 0.1, len(points))  # the model's wrench
    np.testing.assert_array_equal(replaced.quality(points, normals, features, channels), plain)
    channels[:, 0] = 0.5  # the seal still counts
    np.testing.assert_allclose(replaced.quality(points, normals, features, channels), 0.5 * plain, rtol=1e-6)
    kept = DiffusionCentreVotePolicy(centre_head=constant_head(model.encode_width, (0.0, 0.0, -0.02),
                                                               segment_spacings=2.0), model_wrench=True, **kwargs)
    assert kept.centre_head.config.model_wrench is True
    np.testing.assert_allclose(kept.quality(points, normals, features, channels), channels.prod(axis=1) * plain,
                               rtol=1e-6)


def test_a_top_that_sits_off_its_votes_is_doubted_by_half_their_gap():
    """A fragment of a tube: its visible top's centroid lies 2 cm off the mean of its votes (under the 4 cm test),
    so its spread is half of that, 1 cm, and half again with ``segment_shift_spread`` 0.25."""
    model, _ = load_model(DEFAULT_CHECKPOINT)
    points = _plate(0.0, 0.06, 0.0, 0.04, 0.05).astype(np.float32)
    normals = np.tile(UP, (len(points), 1)).astype(np.float32)
    features, channels = torch.zeros(len(points), model.encode_width), np.ones((len(points), 3), dtype=np.float32)
    head = constant_head(model.encode_width, (0.02, 0.0, -0.02), 0.03, segment_spacings=2.0)  # each vote 2 cm aside
    policy = DiffusionCentreVotePolicy(model=model, centre_head=head, voters=0, record_trajectory=False)
    policy.quality(points, normals, features, channels)
    np.testing.assert_allclose(policy.last_centres, np.tile(points.mean(axis=0), (len(points), 1)), atol=1e-6)
    np.testing.assert_allclose(policy.last_spread, 0.01, atol=1e-6)
    policy.centre_head.config = dataclasses.replace(policy.centre_head.config, segment_shift_spread=0.25)
    policy.quality(points, normals, features, channels)
    np.testing.assert_allclose(policy.last_spread, 0.005, atol=1e-6)


def test_a_parcel_half_under_another_is_covered_and_a_free_one_is_not():
    """A 10 x 10 cm carton whose right half lies under a second one 5 cm higher: its visible left half, mirrored about
    its centre (where its votes place it), lands under the second carton. The second and a free third are clear."""
    low = _plate(-0.05, 0.0, -0.05, 0.05, 0.05)  # the visible half of the covered carton, centred at the origin
    high = _plate(0.0, 0.10, -0.05, 0.05, 0.10)  # the carton resting on its right half
    free = _plate(0.30, 0.40, -0.05, 0.05, 0.05)
    points = np.r_[low, high, free]
    labels = np.repeat([0, 1, 2], [len(low), len(high), len(free)])
    votes = np.r_[np.zeros((len(low), 3)), np.tile((0.05, 0.0, 0.0), (len(high), 1)),
                  np.tile((0.35, 0.0, 0.0), (len(free), 1))]
    covered = covered_fraction(points, labels, votes, points[:, 2], margin=0.01)
    assert covered[: len(low)].min() > 0.8  # all but the mirrors that land back on its own seam
    assert not covered[len(low):].any()
    assert not covered_fraction(points, labels, votes, points[:, 2], margin=0.06).any()  # a 5 cm step, a 6 cm margin


def test_the_policy_ranks_a_covered_parcel_down_by_its_covered_share():
    """The segments' step finds the covered share from the votes it is given, and the score is scaled by 1 - it."""
    model, _ = load_model(DEFAULT_CHECKPOINT)
    low = _plate(-0.05, 0.0, -0.05, 0.05, 0.05)
    high = _plate(0.0, 0.10, -0.05, 0.05, 0.10)
    points = np.r_[low, high].astype(np.float32)
    normals = np.tile(UP, (len(points), 1)).astype(np.float32)
    votes = np.r_[np.zeros((len(low), 3)), np.tile((0.05, 0.0, 0.07), (len(high), 1))]  # the two cartons' centres
    policy = DiffusionCentreVotePolicy(model=model, voters=0, record_trajectory=False,
                                       centre_head=constant_head(model.encode_width, (0.0, 0.0, -0.02),
                                                                 segment_spacings=2.0))
    covered = policy._centre_on_tops(points, normals, votes.copy(), np.zeros(len(points)), None)
    assert covered[: len(low)].min() > 0.8 and not covered[len(low):].any()
    features, channels = torch.zeros(len(points), model.encode_width), np.ones((len(points), 3), dtype=np.float32)
    policy.quality(points, normals, features, channels)  # a constant head: each segment's votes agree, no cover
    assert policy.last_covered is not None and not policy.last_covered.any()
    for share in (0.0, 0.25):  # the step stubbed to leave the votes' centres and report this share
        policy._centre_on_tops = lambda *a, s=share, **k: np.full(len(points), s)  # type: ignore[method-assign]
        scores = policy.quality(points, normals, features, channels)
        if share == 0.0:
            free = scores
    assert free.max() > 0
    np.testing.assert_allclose(scores, 0.75 * free, rtol=1e-6)


def test_a_policys_overrides_leave_the_head_it_was_given_as_it_was():
    model, _ = load_model(DEFAULT_CHECKPOINT)
    head = constant_head(model.encode_width, (0.0, 0.0, -0.02), segment_spacings=2.0)
    policy = DiffusionCentreVotePolicy(model=model, centre_head=head, segment_spacings=0.0, model_wrench=True,
                                       record_trajectory=False)
    assert policy.centre_head.config.segment_spacings == 0.0 and policy.centre_head.config.model_wrench is True
    assert head.config.segment_spacings == 2.0 and head.config.model_wrench is False
    assert DiffusionCentreVotePolicy(model=model, centre_head=head).centre_head.config == head.config


def test_vote_segments_refuse_mismatched_votes_and_a_zero_gap():
    points = _plate(0.0, 0.02, 0.0, 0.02, 0.0)
    with pytest.raises(ValueError, match="one voted centre per point"):
        vote_segments(points, points[:-1], radius=0.01, vote_gap=0.08)
    with pytest.raises(ValueError, match="vote_gap"):
        vote_segments(points, points, radius=0.01, vote_gap=0.0)


def test_only_points_inside_the_bin_are_segmented():
    box = np.array([[-0.10, -0.10, 0.0], [0.10, 0.10, 1.0]])
    points = np.array([[0.0, 0.0, 0.002], [0.0, 0.0, 0.004], [-0.095, 0.0, 0.05], [0.0, 0.092, 0.05],
                       [0.05, -0.05, 0.2]])
    np.testing.assert_array_equal(bin_interior(points, box, floor_margin=0.003, wall_margin=0.01),
                                  [False, True, False, False, True])
    assert bin_interior(points, None, 0.003, 0.01).all()


def test_an_envelope_on_the_bare_floor_keeps_its_own_centre_when_the_bin_is_given():
    """6 mm thick, under the 1 cm radius (two of the floor's 5 mm spacings): without the bin it joins the floor and
    takes the floor's centre."""
    model, _ = load_model(DEFAULT_CHECKPOINT)
    floor = _plate(-0.10, 0.10, -0.10, 0.10, 0.0)
    floor = floor[~((floor[:, 0] >= 0.02) & (floor[:, 0] < 0.08) & (floor[:, 1] >= 0.0) & (floor[:, 1] < 0.06))]
    envelope = _plate(0.02, 0.08, 0.0, 0.06, 0.006)
    points = np.r_[floor, envelope].astype(np.float32)
    obs = {"points": points, "normals": np.tile(UP, (len(points), 1)).astype(np.float32)}
    info = {"workspace": np.array([[-0.10, -0.10, 0.0], [0.10, 0.10, 1.0]])}
    policy = DiffusionCentreVotePolicy(model=model, voters=0, record_trajectory=False, decode_points=0,
                                       centre_head=constant_head(model.encode_width, (0.0, 0.0, -0.003),
                                                                 segment_spacings=2.0))
    assert len(points) <= policy.config.num_points  # decoded as given, in order
    on_envelope = np.arange(len(floor), len(points))
    policy.predict(obs, info)
    np.testing.assert_allclose(policy.last_centres[on_envelope], np.tile(envelope.mean(axis=0), (len(envelope), 1)),
                               atol=1e-6)
    policy.predict(obs, None)
    np.testing.assert_allclose(policy.last_centres[on_envelope], np.tile(points.mean(axis=0), (len(envelope), 1)),
                               atol=1e-6)


def test_a_top_far_from_its_segments_votes_leaves_the_votes():
    """A tube half under another: its visible top's centroid lies 5 cm off the centre its votes agree on."""
    seen = _plate(0.0, 0.10, 0.0, 0.04, 0.05)  # the visible half of a 20 cm tube whose centre is at x = 0.10
    normals = np.tile(UP, (len(seen), 1))
    labels = np.zeros(len(seen), dtype=np.int64)
    at_centre = np.tile((0.10, 0.02, 0.03), (len(seen), 1))
    _, found, shift = top_centres(seen, normals, labels, 0.9, 5, votes=at_centre, max_shift=0.04)
    assert not found.any() and np.isnan(shift).all()
    tops, found, shift = top_centres(seen, normals, labels, 0.9, 5, votes=at_centre, max_shift=0.06)
    assert found.all()
    np.testing.assert_allclose(tops[0], seen.mean(axis=0), atol=1e-12)
    np.testing.assert_allclose(shift, np.hypot(0.10 - seen[:, 0].mean(), 0.02 - seen[:, 1].mean()), atol=1e-12)
    with pytest.raises(ValueError, match="a vote per point"):
        top_centres(seen, normals, labels, 0.9, 5, votes=at_centre[:-1])
