"""Centre votes (policies/diffusion/centre_vote.py): the clustering, the targets and the wrench on known answers, the
head's training, its pairing with one Diffusion-Suction checkpoint, and the ``diffusion_vote`` policy's score."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from centre_heads import constant_head
from generated_records import generate_tiny

from dataset.scene_record import scene_from_record
from dataset.storage import open_dataset
from parcelpick_env.cli import run_cli
from parcelpick_env.suction.quality import definition_config, definition_scorer
from policies.diffusion.centre_vote import (DEFAULT_CENTRE_VOTE, CentreVoteConfig, CentreVoteHead, cluster_centres,
                                            file_sha256, load_centre_vote, spread_draws, vote_wrench)
from policies.diffusion.checkpoint import DEFAULT_CHECKPOINT, load_model, save_checkpoint
from policies.diffusion.config import DiffusionConfig
from policies.diffusion.model import build_model
from policies.diffusion.policy import DiffusionSuctionPolicy
from policies.diffusion.synthetic import synthetic_scene
from policies.diffusion.train_centre_vote import CentreVoteTraining, fit, fit_spread, main, vote_targets
from policies.diffusion.vote_policy import DiffusionCentreVotePolicy, spread_indices


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return generate_tiny(tmp_path_factory.mktemp("centre_vote") / "data", split="train", seed=3)


@pytest.fixture(scope="module")
def record(data):
    store = open_dataset(data)
    try:
        return store.scene(0)
    finally:
        store.close()


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    path = tmp_path_factory.mktemp("centre_vote_model") / "tiny.pt"
    save_checkpoint(path, build_model(DiffusionConfig.tiny(), seed=1))
    return path


def test_each_vote_is_averaged_with_its_nearest_votes_within_the_radius():
    votes = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.025, 0.0, 0.0], [1.0, 1.0, 1.0]])
    every, spread = cluster_centres(votes, radius=0.02, neighbours=8)
    np.testing.assert_allclose(every[:, 0], [0.005, 0.035 / 3, 0.0175, 1.0])  # {0,1}, {0,1,2}, {1,2}, alone
    np.testing.assert_allclose(every[3], votes[3])
    np.testing.assert_array_equal(spread, 0.0)  # no predicted errors: equal weights, no spread
    np.testing.assert_array_equal(cluster_centres(votes, radius=0.02, neighbours=8, workers=2)[0], every)  # threads
    nearest = cluster_centres(votes, radius=0.02, neighbours=2)[0]  # the middle vote keeps its nearer partner only
    np.testing.assert_allclose(nearest[:, 0], [0.005, 0.005, 0.0175, 1.0])
    np.testing.assert_allclose(cluster_centres(votes, radius=0.02, neighbours=1)[0], votes)
    np.testing.assert_array_equal(cluster_centres(np.zeros((0, 3)), 0.04, 64)[0].shape, (0, 3))
    # weighted by 1 / error^2: vote 0 (error 1 cm) counts four times vote 1 (2 cm); the typical error is their mean
    weighted, typical = cluster_centres(votes, radius=0.02, neighbours=8, spreads=np.array([0.01, 0.02, 0.02, 0.05]))
    assert weighted[0, 0] == pytest.approx((4 * 0.0 + 0.01) / 5)
    assert typical[0] == pytest.approx((4 * 0.01 + 0.02) / 5)
    assert typical[3] == pytest.approx(0.05) and weighted[3] == pytest.approx(votes[3])
    with pytest.raises(ValueError, match="spreads"):
        cluster_centres(votes, 0.02, 8, spreads=np.array([0.01, -0.01, 0.01, 0.01]))
    with pytest.raises(ValueError, match="radius"):
        cluster_centres(votes, 0.0, 8)
    with pytest.raises(ValueError, match="neighbours"):
        cluster_centres(votes, 0.02, 0)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        cluster_centres(votes[:, :2], 0.04, 8)


def test_targets_point_at_the_surface_centroid_and_its_wrench_is_the_evaluators(record):
    """The head learns the centre the evaluator's wrench is about: vote_wrench there is the scorer's wrench."""
    points = np.asarray(record["points"], dtype=np.float64)
    normals = np.asarray(record["normals"], dtype=np.float64)
    object_ids = np.asarray(record["object_ids"], dtype=np.int64)
    offsets, on_parcel = vote_targets(record, points, object_ids)
    np.testing.assert_array_equal(on_parcel, object_ids >= 0)
    assert on_parcel.any() and not on_parcel.all()  # the bin floor is in the cloud, and has no centre
    scorer = definition_scorer("suctionnet", scene_from_record(record))
    np.testing.assert_allclose((points + offsets)[on_parcel], scorer.surface_centroids[object_ids[on_parcel]],
                               atol=1e-9)
    np.testing.assert_array_equal(offsets[~on_parcel], 0.0)
    p, n, ids = points[on_parcel], normals[on_parcel], object_ids[on_parcel]
    np.testing.assert_allclose(vote_wrench(p, n, p + offsets[on_parcel], "suctionnet"), scorer.wrench(p, n, ids),
                               atol=1e-6)


def test_a_vote_beside_an_upward_contact_costs_the_torque_of_the_unit_weight_on_that_lever():
    """Known answer: a level contact, its centre d to the side: load m g d over the threshold (SuctionNet's frame)."""
    config = definition_config("suctionnet")
    d = 0.004
    wrench = vote_wrench(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), np.array([[d, 0.0, -0.05]]), "suctionnet")
    expected = 1.0 - config.unit_mass * config.gravity * d / config.torque_threshold
    assert 0.0 < expected < 1.0
    assert wrench[0] == pytest.approx(expected, rel=1e-6)
    below = vote_wrench(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), np.array([[0.0, 0.0, -0.05]]), "suctionnet")
    assert below[0] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="definition"):
        vote_wrench(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), np.zeros((1, 3)), "physical")


def test_the_expected_wrench_averages_the_score_over_the_centres_error():
    """Known answer: a level contact over its centre, the centre known to within s an axis. A shift (dx, dy) bends
    the cup by m g s (dx, dy) in SuctionNet's frame, so the score is the draws' mean of 1 - m g s max(|dx|, |dy|)
    over the threshold."""
    config = definition_config("suctionnet")
    up, below = np.array([[0.0, 0.0, 1.0]]), np.array([[0.0, 0.0, -0.05]])
    draws = spread_draws(16)
    for s in (0.002, 0.01):
        load = config.unit_mass * config.gravity * s * np.abs(draws).max(axis=1) / config.torque_threshold
        got = vote_wrench(np.zeros((1, 3)), up, below, "suctionnet", spread=np.array([s]), draws=16)
        assert got[0] == pytest.approx(np.mean(1.0 - np.minimum(1.0, load)), rel=1e-6)
        assert got[0] < 1.0  # an uncertain centre costs score even right above it
    # zero spread is the wrench about the centre; on a random cloud the mean over draws is the loop's
    rng = np.random.default_rng(0)
    points = rng.normal(size=(200, 3)) * 0.1
    normals = rng.normal(size=(200, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    centres, spread = points + rng.normal(size=(200, 3)) * 0.03, rng.uniform(0.0, 0.03, 200)
    np.testing.assert_allclose(vote_wrench(points, normals, centres, "paper", spread=np.zeros(200)),
                               vote_wrench(points, normals, centres, "paper"), atol=1e-7)
    for definition in ("suctionnet", "paper", "paper_compat"):
        loop = np.mean([vote_wrench(points, normals, centres + np.column_stack([spread * dx, spread * dy,
                                                                                 np.zeros(200)]), definition)
                        for dx, dy in spread_draws(8)], axis=0)
        np.testing.assert_allclose(vote_wrench(points, normals, centres, definition, spread=spread, draws=8), loop,
                                   atol=1e-6)


def test_the_spread_draws_sample_a_unit_normal_the_same_way_every_time():
    for count in (4, 16, 256):
        draws = spread_draws(count)
        assert draws.shape == (count, 2)
        np.testing.assert_array_equal(draws, spread_draws(count))
        np.testing.assert_allclose(draws.mean(axis=0), 0.0, atol=1e-12)  # the moments of N(0, I), exactly
        np.testing.assert_allclose(draws.var(axis=0), 1.0, rtol=1e-12)
        assert abs(np.mean(draws[:, 0] * draws[:, 1])) < 1e-12
    radii = np.linalg.norm(spread_draws(256), axis=1)  # and the rings' radii spread as a 2-D normal's do
    assert np.median(radii) == pytest.approx(np.sqrt(2 * np.log(2)), rel=0.05)
    for count in (0, 6):
        with pytest.raises(ValueError, match="count"):
            spread_draws(count)


@pytest.mark.parametrize("fields, message", [({"cluster_radius": 0.0}, "cluster_radius"),
                                             ({"cluster_neighbours": 0}, "cluster_neighbours"),
                                             ({"wrench_definition": "physical"}, "wrench_definition"),
                                             ({"voters": -1}, "voters"),
                                             ({"hidden": ()}, "hidden"), ({"hidden": (8, 0)}, "hidden"),
                                             ({"spread_hidden": ()}, "spread_hidden"),
                                             ({"spread_scale": -1.0}, "spread_scale"),
                                             ({"spread_draws": 0}, "spread_draws"),
                                             ({"spread_draws": 6}, "spread_draws"),
                                             ({"segment_spacings": -1.0}, "segment_spacings"),
                                             ({"segment_spacings": float("nan")}, "segment_spacings"),
                                             ({"segment_vote_gap": 0.0}, "segment_vote_gap"),
                                             ({"segment_up_cos": 1.5}, "segment_up_cos"),
                                             ({"segment_min_points": 0}, "segment_min_points"),
                                             ({"segment_floor_margin": -0.001}, "segment_floor_margin"),
                                             ({"segment_max_shift": 0.0}, "segment_max_shift"),
                                             ({"model_wrench": 1}, "model_wrench"),
                                             ({"segment_shift_spread": -0.5}, "segment_shift_spread")])
def test_bad_vote_configs_name_the_field(fields, message):
    with pytest.raises(ValueError, match=message):
        CentreVoteConfig(**fields)


def test_the_head_learns_offsets_that_its_inputs_determine_and_where_they_are_noisy():
    rng = np.random.default_rng(0)
    inputs = torch.from_numpy(rng.normal(size=(4000, 11)).astype(np.float32))
    targets = inputs[:, :3] * 0.5 - inputs[:, 3:6] * 0.3  # in LEVER_UNIT
    head = CentreVoteHead(8, CentreVoteConfig(hidden=(32, 32), spread_hidden=(32, 32)))
    training = CentreVoteTraining(steps=400, batch_points=256, lr=3e-3, spread_steps=400)
    losses = fit(head, inputs, targets, training, seed=0)
    assert losses[-1] < 0.15 * losses[0]
    # noise that the offsets cannot learn, ten times larger where the 7th input is positive: the spread sees it
    noisy = inputs[:, 6] > 0
    scale = torch.where(noisy, 1.0, 0.1)[:, None]
    spread_losses = fit_spread(head, inputs, targets + scale * torch.from_numpy(rng.normal(size=(4000, 3))).float(),
                               training, seed=0)
    assert spread_losses[-1] < spread_losses[0]
    with torch.inference_mode():
        spread = torch.exp(head.log_spread_units(inputs))
    ratio = float(spread[noisy].median() / spread[~noisy].median())
    assert 5.0 < ratio < 20.0, ratio
    with pytest.raises(ValueError, match="no parcel points"):
        fit(head, inputs[:0], targets[:0], CentreVoteTraining(steps=1), seed=0)


def test_the_policy_weights_its_channels_by_the_wrench_about_the_voted_centre():
    model, _ = load_model(DEFAULT_CHECKPOINT)  # trained: its scores are not all clamped to 0, as a fresh net's are
    obs = {k: v for k, v in synthetic_scene(np.random.default_rng(4), 2048).items() if k in ("points", "normals")}
    base = DiffusionSuctionPolicy(model=model, record_trajectory=False).predict(obs)
    assert base.scores.max() > 0
    m, n = 64, np.tile([0.0, 0.0, 1.0], (64, 1)).astype(np.float32)
    points = np.random.default_rng(1).uniform(-0.1, 0.1, (m, 3)).astype(np.float32)
    channels = np.random.default_rng(2).uniform(0.2, 1.0, (m, 3)).astype(np.float32)
    features = torch.zeros(m, model.encode_width)
    config = definition_config("suctionnet")
    for offset, factor in (((0.0, 0.0, -0.05), 1.0),
                           ((0.003, 0.0, -0.05), 1.0 - config.unit_mass * config.gravity * 0.003 / config.torque_threshold),
                           ((0.5, 0.0, 0.0), 0.0)):
        policy = DiffusionCentreVotePolicy(model=model, centre_head=constant_head(model.encode_width, offset),
                                           voters=0, record_trajectory=False, model_wrench=True)  # votes: own centre
        np.testing.assert_allclose(policy.quality(points, n, features, channels), channels.prod(axis=1) * factor,
                                   rtol=1e-5, atol=1e-7)
        replaced = DiffusionCentreVotePolicy(model=model, centre_head=constant_head(model.encode_width, offset),
                                             voters=0, record_trajectory=False)  # by default, the model's wrench out
        np.testing.assert_allclose(replaced.quality(points, n, features, channels),
                                   channels[:, [0, 2]].prod(axis=1) * factor, rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(policy.last_centres, points + np.asarray(offset), atol=1e-6)
        picks = policy.predict(obs)  # predict ranks by the same score
        if factor == 1.0:
            np.testing.assert_array_equal(picks.points, base.points)
            np.testing.assert_array_equal(picks.scores, base.scores)
        if factor == 0.0:  # half a metre of lever: only contacts whose frame nearly hides that torque keep a score
            assert picks.scores.max() < 0.5 * base.scores.max()
    # a vote known to within 1 cm an axis: the wrench expected over that error, below the wrench at the centre
    offset = (0.003, 0.0, -0.05)
    policy = DiffusionCentreVotePolicy(model=model, centre_head=constant_head(model.encode_width, offset, 0.01),
                                       voters=0, record_trajectory=False)
    expected = vote_wrench(points, n, points + np.asarray(offset), "suctionnet", spread=np.full(m, 0.01), draws=16)
    np.testing.assert_allclose(policy.quality(points, n, features, channels), channels[:, [0, 2]].prod(axis=1) * expected,
                               rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(policy.last_spread, 0.01, rtol=1e-5)
    assert expected.max() < 1.0 - config.unit_mass * config.gravity * 0.003 / config.torque_threshold


def test_spread_indices_cover_the_range_evenly_and_zero_takes_every_one():
    np.testing.assert_array_equal(spread_indices(10, 4), [0, 3, 6, 9])
    np.testing.assert_array_equal(spread_indices(5, 0), np.arange(5))
    np.testing.assert_array_equal(spread_indices(5, 8), np.arange(5))
    picked = spread_indices(16384, 4096)
    assert len(np.unique(picked)) == 4096 and picked[0] == 0 and picked[-1] == 16383
    assert set(np.diff(picked)) <= {4, 5}


def test_points_between_the_voters_take_their_nearest_voters_centre():
    """Votes cast at every third point: each other point's centre is its nearest voter's, not its own vote."""
    model, _ = load_model(DEFAULT_CHECKPOINT)
    m = 64
    points = np.zeros((m, 3), dtype=np.float32)
    points[:, 0] = np.arange(m) * 0.01  # a row of points 1 cm apart: voters at 0, 3, 6, ... (spread_indices(64, 22))
    normals = np.tile([0.0, 0.0, 1.0], (m, 1)).astype(np.float32)
    channels = np.ones((m, 3), dtype=np.float32)
    offset = np.array([0.0, 0.0, -0.05])
    features = torch.zeros(m, model.encode_width)
    every = DiffusionCentreVotePolicy(model=model, centre_head=constant_head(model.encode_width, tuple(offset)),
                                      voters=0, record_trajectory=False)
    every.quality(points, normals, features, channels)
    np.testing.assert_allclose(every.last_centres, points + offset, atol=1e-6)
    some = DiffusionCentreVotePolicy(model=model, centre_head=constant_head(model.encode_width, tuple(offset)),
                                     voters=22, record_trajectory=False)
    assert some.centre_head.config.voters == 22
    some.quality(points, normals, features, channels)
    voters = spread_indices(m, 22)
    nearest = voters[np.abs(points[:, :1] - points[voters, 0][None, :]).argmin(axis=1)]
    np.testing.assert_allclose(some.last_centres, points[nearest] + offset, atol=1e-6)
    assert not np.allclose(some.last_centres, every.last_centres)


def test_the_trainer_writes_a_head_that_only_its_own_model_reads(data, tiny_checkpoint, tmp_path):
    out = tmp_path / "head.pt"
    args = ["--data", str(data), "--checkpoint", str(tiny_checkpoint), "--out", str(out), "--steps", "30",
            "--batch-points", "256", "--threads", "1", "--seed", "3", "--no-progress"]
    assert run_cli(main, args) == 0
    head, payload = load_centre_vote(out, file_sha256(tiny_checkpoint))
    provenance = payload["extra"]["provenance"]
    assert provenance["seed"] == 3 and "train_centre_vote" in provenance["command"]
    assert head.in_features == build_model(DiffusionConfig.tiny()).encode_width
    obs = {k: v for k, v in synthetic_scene(np.random.default_rng(5), 512).items() if k in ("points", "normals")}
    picks = DiffusionCentreVotePolicy(checkpoint=tiny_checkpoint, centre_vote=out, record_trajectory=False).predict(obs)
    assert len(picks) > 0 and np.all(np.isfinite(picks.scores))
    twice = tmp_path / "twice.pt"  # several directories: every one's parcel points
    assert run_cli(main, [*args[:2], str(data), *args[2:5], str(twice), *args[6:]]) == 0
    assert load_centre_vote(twice)[1]["extra"]["points"] == 2 * payload["extra"]["points"]
    other = tmp_path / "other.pt"
    save_checkpoint(other, build_model(DiffusionConfig.tiny(), seed=9))
    with pytest.raises(ValueError, match="retrain"):
        DiffusionCentreVotePolicy(checkpoint=other, centre_vote=out)


def test_the_same_seed_trains_the_same_head(data, tiny_checkpoint, tmp_path):
    def train(seed: int, name: str) -> dict:
        out = tmp_path / name
        assert run_cli(main, ["--data", str(data), "--checkpoint", str(tiny_checkpoint), "--out", str(out), "--steps",
                              "5", "--batch-points", "64", "--threads", "1", "--seed", str(seed), "--no-progress"]) == 0
        return load_centre_vote(out)[0].state_dict()

    first, again, other = train(0, "a.pt"), train(0, "b.pt"), train(1, "c.pt")
    assert all(torch.equal(first[k], again[k]) for k in first)
    assert not all(torch.equal(first[k], other[k]) for k in first)


@pytest.mark.parametrize("extra, message", [(["--steps", "0"], "steps"), (["--scenes", "0"], "--scenes")])
def test_the_trainer_refuses_bad_arguments_in_one_line(data, tiny_checkpoint, tmp_path, capsys, extra, message):
    args = ["--data", str(data), "--checkpoint", str(tiny_checkpoint), "--out", str(tmp_path / "h.pt"), *extra]
    assert run_cli(main, args) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1
    assert not (tmp_path / "h.pt").exists()


def test_the_shipped_head_reads_the_shipped_model_and_refuses_another(tmp_path):
    policy = DiffusionCentreVotePolicy(record_trajectory=False)
    assert policy.centre_head.in_features == policy.model.encode_width
    physical = DEFAULT_CENTRE_VOTE.parent / "diffusion_suction_physical_labels.pt"
    with pytest.raises(ValueError, match="retrain"):
        DiffusionCentreVotePolicy(checkpoint=physical)
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="corrupt"):
        DiffusionCentreVotePolicy(centre_vote=corrupt)
    older = tmp_path / "v1.pt"  # a head from before the spread: refused by name, not loaded without it
    payload = torch.load(DEFAULT_CENTRE_VOTE, weights_only=True)
    torch.save(dict(payload, version=1), older)
    with pytest.raises(ValueError, match="format version 1"):
        DiffusionCentreVotePolicy(centre_vote=older)
