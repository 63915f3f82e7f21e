"""The learnt hold check (policies/hold): its features on known clouds, its checkpoint, its training and offline
report, its rehearsal-labelled data, and the ``diffusion_hold`` policy's re-ranking."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from policies.diffusion.config import DiffusionConfig
from policies.diffusion.model import build_model
from policies.hold import collect, train
from policies.hold.features import FEATURES, hold_features
from policies.hold.model import HoldNet, HoldNetConfig, load_hold, save_hold
from policies.hold.policy import DiffusionHoldPolicy

F = {name: i for i, name in enumerate(FEATURES)}
UP = np.array([0.0, 0.0, 1.0])


def grid(x0: float, x1: float, y0: float, y1: float, z: float, step: float = 0.005) -> np.ndarray:
    xs, ys = np.meshgrid(np.arange(x0, x1 + 1e-9, step), np.arange(y0, y1 + 1e-9, step))
    return np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, z)], axis=1)


@pytest.fixture(scope="module")
def floor_and_box():
    """A 40 x 40 cm floor at z = 0 with a 10 x 10 cm box top at z = 0.1 over its centre, all facing up."""
    floor = grid(-0.2, 0.2, -0.2, 0.2, 0.0)
    floor = floor[(np.abs(floor[:, 0]) > 0.05) | (np.abs(floor[:, 1]) > 0.05)]  # the box hides the floor under it
    points = np.concatenate([floor, grid(-0.05, 0.05, -0.05, 0.05, 0.1)])
    return points, np.tile(UP, (len(points), 1))


def test_features_of_picks_beside_and_on_a_box(floor_and_box):
    points, normals = floor_and_box
    picks = np.array([[0.08, 0.0, 0.0], [0.0, 0.0, 0.1], [0.04, 0.0, 0.1], [0.18, 0.0, 0.0]])
    box = np.array([[-0.2, -0.2, 0.0], [0.2, 0.2, 0.5]])
    f = hold_features(points, normals, picks, np.tile(UP, (4, 1)), np.array([0.9, 0.8, 0.7, 0.6]), box)
    assert f.shape == (4, len(FEATURES)) and f.dtype == np.float32
    np.testing.assert_allclose(f[:, F["score"]], [0.9, 0.8, 0.7, 0.6], rtol=1e-6)
    np.testing.assert_allclose(f[:, F["below_top"]], [0.1, 0.0, 0.0, 0.1], atol=1e-6)
    # beside the box: 10 cm of it rises within 5 cm; on its top nothing does; 18 cm out only the 15 cm ring sees it
    np.testing.assert_allclose(f[:, F["rise_5cm"]], [0.1, 0.0, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(f[:, F["rise_15cm"]], [0.1, 0.0, 0.0, 0.1], atol=1e-6)
    assert f[0, F["above_5cm"]] > 0.1 and f[1, F["above_15cm"]] == 0 and f[3, F["above_5cm"]] == 0
    np.testing.assert_allclose(f[:, F["normal_z"]], 1.0)
    np.testing.assert_allclose(f[:, F["wall_distance"]], [0.12, 0.2, 0.16, 0.02], atol=1e-6)
    # the box top's centroid is its centre: no lever at the centre, 4 cm at the pick 4 cm off it
    np.testing.assert_allclose(f[1:3, F["lever"]], [0.0, 0.04], atol=2e-3)
    assert f[1, F["surface_size"]] < f[0, F["surface_size"]]  # the box top is smaller than the floor


def test_features_ignore_dropouts_and_take_the_cloud_extent_without_a_workspace(floor_and_box):
    points, normals = floor_and_box
    pick = np.array([[0.0, 0.0, 0.1]])
    clean = hold_features(points, normals, pick, UP[None], np.ones(1), None)
    holes = np.concatenate([points, np.full((50, 3), np.nan)])
    dropped = hold_features(holes, np.concatenate([normals, np.full((50, 3), np.nan)]), pick, UP[None], np.ones(1),
                            None)
    np.testing.assert_array_equal(clean, dropped)
    assert clean[0, F["wall_distance"]] == pytest.approx(0.2)
    assert hold_features(points, normals, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), None).shape == (0, 12)
    with pytest.raises(ValueError, match="finite"):
        hold_features(np.full((5, 3), np.nan), np.full((5, 3), np.nan), pick, UP[None], np.ones(1), None)


def logistic(weights: dict[str, float]) -> HoldNet:
    """A hold net with no hidden layer whose logit is the sum of the named features times their weights."""
    net = HoldNet(HoldNetConfig(layers=0))
    with torch.no_grad():
        net.net[0].weight.zero_()
        net.net[0].bias.zero_()
        for name, w in weights.items():
            net.net[0].weight[0, F[name]] = w
    return net.eval()


def test_a_checkpoint_round_trips_and_bad_files_are_refused(tmp_path):
    net = HoldNet(HoldNetConfig(hidden=8, layers=1))
    net.fit_scaling(np.random.default_rng(0).normal(size=(20, len(FEATURES))))
    path = tmp_path / "hold.pt"
    save_hold(path, net, {"command": "test", "seed": 3})
    loaded, meta = load_hold(path)
    x = np.random.default_rng(1).normal(size=(5, len(FEATURES))).astype(np.float32)
    np.testing.assert_array_equal(loaded.hold_probability(x), net.hold_probability(x))
    assert meta == {"command": "test", "seed": 3} and loaded.config == net.config
    with pytest.raises(FileNotFoundError, match="policies.hold.train"):
        load_hold(tmp_path / "missing.pt")
    torch.save({"format": "something-else"}, tmp_path / "foreign.pt")
    with pytest.raises(ValueError, match="foreign.pt"):
        load_hold(tmp_path / "foreign.pt")
    with pytest.raises(ValueError, match="features"):
        HoldNetConfig(features=("score",))


def test_roc_auc_and_the_first_pick_of_a_ranking_on_known_answers():
    assert train.roc_auc(np.array([0.1, 0.4, 0.35, 0.8]), np.array([0, 0, 1, 1])) == pytest.approx(0.75)
    assert np.isnan(train.roc_auc(np.ones(3), np.ones(3)))
    picks = train.PickSet(features=np.zeros((5, len(FEATURES)), dtype=np.float32),
                          held=np.array([False, True, True, False, True]), state=np.array([0, 0, 0, 1, 1]),
                          order=np.array([0, 1, 2, 0, 1]))
    np.testing.assert_array_equal(train.first_held(picks, -picks.order.astype(float)), [0.0, 0.0])
    np.testing.assert_array_equal(train.first_held(picks, np.array([0, 1, 1, 0, 2.0])), [1.0, 1.0])  # ties: order


def fake_episode(path, rng: np.random.Generator, states: int = 4, k: int = 3) -> None:
    """A collect-format file whose picks hold exactly where they lie on a parcel's top (z = 0.1), not beside it."""
    points = np.concatenate([grid(-0.2, 0.2, -0.2, 0.2, 0.0, 0.01), grid(-0.05, 0.05, -0.05, 0.05, 0.1, 0.01)])
    cand = np.zeros((states, k, 3), dtype=np.float32)
    outcome = np.full((states, k), "", dtype="<U16")
    for s in range(states):
        on_top = rng.random(k) < 0.5
        cand[s, :, 0] = np.where(on_top, rng.uniform(-0.04, 0.04, k), rng.uniform(0.06, 0.15, k))
        cand[s, :, 2] = np.where(on_top, 0.1, 0.0)
        outcome[s] = np.where(on_top, "success", "dropped")
    outcome[0, -1] = ""  # a candidate not rehearsed (fewer passing picks than asked)
    np.savez_compressed(path, seed=np.int64(0), points=np.tile(points, (states, 1, 1)).astype(np.float32),
                        normals=np.tile(UP, (states, len(points), 1)).astype(np.float32),
                        workspace=np.tile(np.array([[-0.2, -0.2, 0], [0.2, 0.2, 0.5]], np.float32), (states, 1, 1)),
                        cand_points=cand, cand_normals=np.tile(UP, (states, k, 1)).astype(np.float32),
                        cand_scores=np.full((states, k), 0.5, np.float32), cand_rank=np.tile(np.arange(k), (states, 1)),
                        twin_outcome=outcome, twin_condition=np.full((states, k), "", "<U32"),
                        twin_peak=np.zeros((states, k), np.float32), env_outcome=np.full(states, "success", "<U16"))


def test_training_learns_a_separable_hold_and_records_where_it_came_from(tmp_path, capsys):
    rng = np.random.default_rng(0)
    for i in range(6):
        fake_episode(tmp_path / f"mixed-stacked-ep{i:03d}.npz", rng)
    picks = train.load_picks(sorted(tmp_path.glob("*.npz")))
    assert len(picks.held) == 6 * 4 * 3 - 6  # the unrehearsed candidates are left out
    out = tmp_path / "hold.pt"
    assert train.main(["--data", str(tmp_path), "--out", str(out), "--steps", "300", "--val-every", "3"]) == 0
    net, meta = load_hold(out)
    from policies.provenance import checkpoint_provenance

    record = checkpoint_provenance(out)
    assert record["seed"] == 0 and record["command"].startswith("python -m policies.hold.train --data")
    assert len(record["dataset_manifest_sha256"]) == 64 and record["source"] == "checkpoint"
    assert meta["held_out_files"] == [f"{tmp_path.name}/mixed-stacked-ep002.npz", f"{tmp_path.name}/mixed-stacked-ep005.npz"]
    assert meta["validation"]["auc"] > 0.95
    assert "by_hold_minus_policy" in capsys.readouterr().out
    assert train.main(["--data", str(tmp_path / "nowhere")]) == 2


def test_collect_rehearses_the_policys_passing_picks_and_records_the_env_step(tmp_path):
    from eval.clearance import ClearanceConfig, episode_tasks
    from parcelpick_env.envs.grasp import OUTCOMES

    config = ClearanceConfig(policy="diffusion", objects=("rectangular",), layouts=("stacked",), episodes=1,
                             num_parcels=2, seed=5)
    counts = collect.collect_episode(collect.CollectTask(episode_tasks(config)[0], str(tmp_path), 2))
    with np.load(tmp_path / "rectangular-stacked-ep000.npz", allow_pickle=False) as d:
        states = len(d["env_outcome"])
        assert counts["states"] == states >= 1 and d["points"].shape == (states, 4096, 3)
        assert d["twin_outcome"].shape == (states, 2) and d["cand_points"].shape == (states, 2, 3)
        rehearsed = d["twin_outcome"] != ""
        assert counts["rehearsed"] == rehearsed.sum() >= 1
        assert set(d["twin_outcome"][rehearsed]) <= set(OUTCOMES) and set(d["env_outcome"]) <= set(OUTCOMES)
        assert np.all(d["cand_rank"][rehearsed] >= 0) and np.all(np.isnan(d["cand_scores"][~rehearsed]))
    assert collect.main(["--out", str(tmp_path), "--candidates", "0"]) == 2
    assert collect.main(["--out", str(tmp_path), "--retry-radius", "-1"]) == 2  # the cell's rule, checked as clearance's


def test_collect_rehearses_only_picks_the_cell_would_take():
    passed = np.array([True, False, True, True, True])
    retried = np.array([False, False, True, False, False])  # the retry rule passes over row 2
    assert collect.rehearsal_candidates(passed, retried, 2).tolist() == [0, 3]
    assert collect.rehearsal_candidates(passed, np.zeros(5, dtype=bool), 6).tolist() == [0, 2, 3, 4]


@pytest.fixture(scope="module")
def stacked_view():
    """A 6-parcel stacked view of the env: the observation and info a policy gets."""
    from parcelpick_env.camera.config import CameraConfig
    from parcelpick_env.envs.parcel_pick import ParcelPickEnv

    env = ParcelPickEnv(num_parcels=6, layout="stacked", object_set="rectangular", num_points=1024,
                        camera=CameraConfig(width=160, height=120))
    obs, info = env.reset(seed=1)
    env.close()
    return obs, info


def test_the_policy_orders_its_first_candidates_by_the_hold_probability(stacked_view):
    from policies.diffusion.policy import DiffusionSuctionPolicy

    obs, info = stacked_view
    model = build_model(DiffusionConfig.tiny())
    inner = DiffusionSuctionPolicy(model=model)
    inner.reset(0)
    base = inner.predict(obs, info, top_k=30)
    plain = DiffusionHoldPolicy(model=model, hold_net=logistic({}), rerank=20)
    plain.reset(0)
    same = plain.predict(obs, info, top_k=30)
    np.testing.assert_array_equal(same.points, base.points)  # a constant hold keeps the model's order
    np.testing.assert_allclose(plain.last_hold, [0.5] * 20 + [1.0] * 10)
    assert np.all(np.diff(same.scores) <= 0) and same.scores[20:].max() < same.scores[:20].min()
    high = DiffusionHoldPolicy(model=model, hold_net=logistic({"below_top": -200.0}), rerank=20)
    high.reset(0)
    ranked = high.predict(obs, info, top_k=25)
    assert len(ranked) == 25 and np.all(np.diff(ranked.scores) <= 0)
    assert ranked.points[0, 2] == pytest.approx(base.points[:20, 2].max(), abs=1e-6)  # the highest of the 20 first
    np.testing.assert_array_equal(ranked.points[20:], base.points[20:25])  # the rest behind, in the model's order
    with pytest.raises(ValueError, match="rerank"):
        DiffusionHoldPolicy(model=model, hold_net=logistic({}), rerank=0)


def test_the_vote_hold_policy_orders_the_votes_ranking_by_the_hold_probability(stacked_view):
    from centre_heads import constant_head

    from policies.diffusion.checkpoint import DEFAULT_CHECKPOINT, load_model
    from policies.diffusion.policy import DiffusionSuctionPolicy
    from policies.diffusion.vote_policy import DiffusionCentreVotePolicy
    from policies.hold.vote_policy import DEFAULT_VOTE_HOLD, DiffusionVoteHoldPolicy
    from policies.registry import make_policy

    obs, info = stacked_view
    model, _ = load_model(DEFAULT_CHECKPOINT)  # trained: its scores are not all clamped to 0, as a fresh net's are
    head = constant_head(model.encode_width, (0.03, 0.0, -0.05))  # 3 cm of lever everywhere: the ranking moves

    def ranking(policy, top_k=30):
        policy.reset(0)
        return policy.predict(obs, info, top_k=top_k)

    base = ranking(DiffusionCentreVotePolicy(model=model, centre_head=head, voters=0, model_wrench=True))
    assert not np.array_equal(base.points, ranking(DiffusionSuctionPolicy(model=model)).points)  # the votes act
    same = ranking(DiffusionVoteHoldPolicy(model=model, centre_head=head, voters=0, hold_net=logistic({}), rerank=20))
    np.testing.assert_array_equal(same.points, base.points)  # a constant hold keeps the votes' order
    high = ranking(DiffusionVoteHoldPolicy(model=model, centre_head=head, voters=0,
                                           hold_net=logistic({"below_top": -200.0}), rerank=20), top_k=25)
    assert high.points[0, 2] == pytest.approx(base.points[:20, 2].max(), abs=1e-6)  # the highest of the votes' 20
    np.testing.assert_array_equal(high.points[20:], base.points[20:25])  # the rest in the votes' order
    shipped = make_policy("diffusion_vote_hold")  # the shipped model and head, with the hold check taught on them
    shipped_hold, _ = load_hold(DEFAULT_VOTE_HOLD)
    assert isinstance(shipped, DiffusionVoteHoldPolicy)
    assert all(torch.equal(a, b) for a, b in zip(shipped.hold_net.state_dict().values(),
                                                 shipped_hold.state_dict().values()))
    assert shipped.centre_head.config.segment_spacings == 0  # without vote segments, where its hold check learnt
    assert shipped.centre_head.config.model_wrench is True  # and with the model's wrench channel in the score
    votes = make_policy("diffusion_vote").centre_head.config
    assert votes.segment_spacings > 0 and votes.model_wrench is False
    assert make_policy("diffusion_vote_hold", segment_spacings=2.0).centre_head.config.segment_spacings == 2.0
