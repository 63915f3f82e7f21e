"""Diffusion-Suction: scheduler math, neighbourhoods, model, training signal, checkpoints, policy, trainer CLI.

Everything runs at 512 points with narrow layers and one torch thread (the CI box has 2 shared cores).
"""

from __future__ import annotations

import warnings

import diffusers
import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree
from torch.utils.data import default_collate

from policies.base import Candidates
from policies.diffusion.checkpoint import DEFAULT_CHECKPOINT, load_checkpoint, load_model, save_checkpoint
from policies.diffusion.config import LEGACY_SAMPLER, TIMESTEP_SPACINGS, DiffusionConfig
from policies.diffusion.metrics import topk_precision
from policies.diffusion.model import build_model
from policies.diffusion.neighbourhood import NeighbourhoodTransform, compute_neighbourhoods, grid_sample, model_inputs
from policies.diffusion import pointnet2
from policies.diffusion.pointnet2 import FeaturePropagation, fold_batchnorm, gather
from policies.diffusion import policy as diffusion_policy
from policies.diffusion.policy import DiffusionSuctionPolicy
from policies.diffusion.scheduler import DiffusionSchedule
from policies.diffusion.synthetic import synthetic_scene
from policies.postprocess import nms_indices, select_candidates
from policies.surface_segments import LEVER_UNIT, offsets_to_centroids, segment_levers, segment_sizes

N = 512


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def cfg() -> DiffusionConfig:
    return DiffusionConfig.tiny(inference_steps=5)


def make_batch(cfg: DiffusionConfig, seeds=(3,)) -> dict[str, torch.Tensor]:
    t = NeighbourhoodTransform(cfg)
    return default_collate([t(synthetic_scene(np.random.default_rng(s), N)) for s in seeds])


def obs_from(seed: int = 3, n: int = N) -> dict[str, np.ndarray]:
    scene = synthetic_scene(np.random.default_rng(seed), n)
    return {"points": scene["points"], "normals": scene["normals"]}


# -- scheduler ----------------------------------------------------------------------------------------------------
def schedule(prediction="eps", spacing="trailing", eta=0.0, beta_schedule="linear") -> DiffusionSchedule:
    return DiffusionSchedule(1000, beta_schedule, 1e-4, 0.02, prediction, spacing, eta)


def reference_ddim(prediction, spacing, beta_schedule, steps) -> diffusers.DDIMScheduler:
    """diffusers' own DDIM as the project means it: its names for our settings, no clipping of x0."""
    ref = diffusers.DDIMScheduler(num_train_timesteps=1000, beta_start=1e-4, beta_end=0.02,
                                  beta_schedule={"linear": "linear", "cosine": "squaredcos_cap_v2"}[beta_schedule],
                                  prediction_type={"eps": "epsilon", "x0": "sample"}[prediction],
                                  timestep_spacing=spacing, clip_sample=False)
    ref.set_timesteps(steps)
    return ref


def fake_network(x: torch.Tensor, t: int) -> torch.Tensor:
    """A fixed stand-in for the decoder: depends on x and t, exceeds [-1, 1] (so any clipping would show)."""
    return 1.5 * torch.tanh(x) * (1.0 - t / 2000.0) + 0.3


@pytest.mark.parametrize("beta_schedule", ["linear", "cosine"])
def test_alphas_cumprod_monotone_in_unit_interval(beta_schedule):
    abar = schedule(beta_schedule=beta_schedule).alphas_cumprod
    assert abar.shape == (1000,)
    assert torch.all(abar[1:] < abar[:-1])
    assert 0.0 < float(abar[-1]) < 0.01 and 0.99 < float(abar[0]) < 1.0


@pytest.mark.parametrize("spacing", TIMESTEP_SPACINGS)
@pytest.mark.parametrize("steps", [1, 3, 5, 7, 20])
def test_timesteps_match_diffusers(spacing, steps):
    ours = schedule(spacing=spacing).timesteps(steps)
    assert torch.equal(ours, reference_ddim("eps", spacing, "linear", steps).timesteps)
    assert ours.dtype == torch.long and torch.all(ours[1:] < ours[:-1])


def test_trailing_starts_at_the_last_training_step_and_leading_does_not():
    """Issue #14: 5 'leading' steps start at t = 800 and end at 0; 5 'trailing' ones run 999 .. 199."""
    assert schedule(spacing="leading").timesteps(5).tolist()[::4] == [800, 0]
    assert schedule(spacing="trailing").timesteps(5).tolist()[::4] == [999, 199]
    assert DiffusionConfig().timestep_spacing == DiffusionConfig.cpu().timestep_spacing == "leading"  # measured
    with pytest.raises(ValueError, match="inference_steps"):
        schedule().timesteps(1001)


@pytest.mark.parametrize("beta_schedule", ["linear", "cosine"])
def test_add_noise_matches_diffusers(beta_schedule):
    g = torch.Generator().manual_seed(0)
    x0, noise = torch.rand((3, 4, 50), generator=g) - 0.5, torch.randn((3, 4, 50), generator=g)
    t = torch.tensor([0, 517, 999])
    ref = reference_ddim("eps", "trailing", beta_schedule, 5)
    ours = schedule(beta_schedule=beta_schedule)
    assert torch.equal(ours.alphas_cumprod, ref.alphas_cumprod)
    assert torch.equal(ours.add_noise(x0, noise, t), ref.add_noise(x0, noise, t))
    assert torch.allclose(ours.add_noise(x0, noise, 0), x0, atol=0.05)  # t = 0: almost clean (noise std 0.01)
    assert (ours.add_noise(x0, noise, 999) - noise).abs().max() < 0.01  # t = T-1: almost pure noise


@pytest.mark.parametrize("eta", [0.0, 0.7])
@pytest.mark.parametrize("spacing", TIMESTEP_SPACINGS)
@pytest.mark.parametrize("prediction", ["eps", "x0"])
@pytest.mark.parametrize("steps", [5, 6])
def test_ddim_trajectory_matches_diffusers(steps, prediction, spacing, eta):
    """A multi-step run with the same network through our wrapper and diffusers' DDIMScheduler called directly."""
    ours, ref = schedule(prediction, spacing, eta), reference_ddim(prediction, spacing, "linear", steps)
    start = torch.randn((2, 4, 40), generator=torch.Generator().manual_seed(3))

    def run(seed: int) -> tuple[torch.Tensor, torch.Tensor]:
        g, x, x0 = torch.Generator().manual_seed(seed), start, start
        for t in ours.timesteps(steps).tolist():
            x, x0 = ours.step(fake_network(x, t), t, x, steps, g)
        return x, x0

    g, expected = torch.Generator().manual_seed(11), start
    for t in ref.timesteps.tolist():
        expected = ref.step(fake_network(expected, t), t, expected, eta=eta, generator=g).prev_sample
    x, x0 = run(11)
    assert torch.equal(x, expected)
    if ours.timesteps(steps)[-1] < 1000 // steps:  # the last step lands on alpha-bar = 1 (6 'trailing' steps stop
        assert torch.equal(x, x0)  # at t = 0, diffusers #12633): there x_prev is the x0 prediction
    assert torch.equal(run(11)[0], x)  # deterministic under the generator
    assert torch.equal(run(12)[0], x) == (eta == 0.0)  # eta > 0 draws noise from the generator, eta = 0 none


@pytest.mark.parametrize("spacing", ["leading", "trailing"])
@pytest.mark.parametrize("prediction", ["eps", "x0"])
@pytest.mark.parametrize("beta_schedule", ["linear", "cosine"])
def test_ddim_with_perfect_predictor_recovers_x0(prediction, beta_schedule, spacing):
    """Known answer, independent of diffusers: a network that predicts the truth is denoised to x0 (float32)."""
    s = schedule(prediction, spacing, eta=0.5, beta_schedule=beta_schedule)
    g = torch.Generator().manual_seed(0)
    x0 = torch.rand((2, 4, 64), generator=g) - 0.5
    x = torch.randn(x0.shape, generator=g)
    for t in s.timesteps(10).tolist():
        abar = s.alphas_cumprod[t]
        out = (x - abar.sqrt() * x0) / (1 - abar).sqrt() if prediction == "eps" else x0
        x, x0_pred = s.step(out, t, x, 10, g)
        assert torch.allclose(x0_pred, x0, atol=2e-6 / float(abar.sqrt()))  # eps -> x0 divides float32 x by sqrt(abar)
    assert torch.allclose(x, x0, atol=1e-5)


def test_schedule_and_config_refuse_bad_sampler_settings():
    for bad in ({"spacing": "uniform"}, {"eta": -0.1}, {"eta": 1.5}, {"prediction": "v"}, {"beta_schedule": "sqrt"}):
        with pytest.raises(ValueError):
            schedule(**bad)
    for bad in ({"timestep_spacing": "uniform"}, {"eta": 2.0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            DiffusionConfig.tiny(**bad)


def test_shipped_checkpoint_stores_its_sampler_and_samples_deterministically():
    """The shipped weights name their DDIM sampler ('leading', eta 0) in the stored config rather than inheriting
    LEGACY_SAMPLER; the same generator gives the same map, and overriding the spacing changes it.

    Until 10523eb the shipped checkpoint (trained before the diffusers wrapper) was pinned here to the hand-written
    DDIM's recorded outputs, to 2e-6; those weights are retired, and the wrapper is checked against diffusers itself
    above."""
    stored = torch.load(DEFAULT_CHECKPOINT, map_location="cpu", weights_only=True)["config"]  # as saved, no defaults
    assert {k: stored.get(k) for k in LEGACY_SAMPLER} == {"timestep_spacing": "leading", "eta": 0.0}
    model, _ = load_model(DEFAULT_CHECKPOINT)
    features = torch.randn((1, 16, model.decoder.cond[0].in_channels), generator=torch.Generator().manual_seed(14))
    with torch.inference_mode():
        scores = model.sample(features, generator=torch.Generator().manual_seed(0))
        again = model.sample(features, generator=torch.Generator().manual_seed(0))
    assert scores.shape == (1, 16, model.config.num_channels) and torch.equal(scores, again)
    assert float(scores.min()) >= 0.0 and float(scores.max()) <= 1.0
    trailing, _ = load_model(DEFAULT_CHECKPOINT, timestep_spacing="trailing")  # a sampler setting, overridable
    with torch.inference_mode():
        other = trailing.sample(features, generator=torch.Generator().manual_seed(0))
    assert (other - scores).abs().max() > 0.01


def test_checkpoint_without_sampler_fields_loads_as_leading_eta0(tmp_path):
    cfg = DiffusionConfig.tiny(timestep_spacing="trailing", eta=0.3)
    path = save_checkpoint(tmp_path / "m.pt", build_model(cfg))
    assert load_checkpoint(path)["config"] == cfg  # stored and read back
    old = torch.load(path, weights_only=True)
    for key in LEGACY_SAMPLER:
        del old["config"][key]
    torch.save(old, tmp_path / "old.pt")
    model, payload = load_model(tmp_path / "old.pt")
    assert (payload["config"].timestep_spacing, payload["config"].eta) == ("leading", 0.0)
    assert model.scheduler.timesteps(5)[0] == 800


# -- neighbourhoods -----------------------------------------------------------------------------------------------
def test_neighbourhoods_are_valid_indices_inside_their_balls(cfg):
    pts = synthetic_scene(np.random.default_rng(0), N)["points"].astype(np.float64)
    nb = compute_neighbourhoods(pts, cfg)
    level = pts
    for l, radii in enumerate(cfg.sa_radii, start=1):
        c, g = nb[f"sa{l}_centres"], nb[f"sa{l}_groups"]
        assert c.shape == (cfg.sa_npoints[l - 1],) and len(np.unique(c)) == len(c)
        assert g.shape == (len(c), len(radii), cfg.nsample) and g.min() >= 0 and g.max() < len(level)
        centres = level[c]
        for s, r in enumerate(radii):
            d = np.linalg.norm(level[g[:, s]] - centres[:, None], axis=-1)
            assert np.all(d <= r + 1e-9)
            assert np.all(g[:, s, 0] == c)  # nearest neighbour of a centre is itself (the padding value)
        w = nb[f"fp{l}_weight"]
        assert w.shape == (len(level), 3) and np.allclose(w.sum(1), 1, atol=1e-5) and nb[f"fp{l}_index"].max() < len(c)
        level = centres


def test_grid_sample_is_uniform_and_deterministic():
    rng = np.random.default_rng(0)
    dense = np.c_[rng.uniform(0, 0.1, 900), rng.uniform(0, 0.1, 900), np.zeros(900)]  # dense corner
    sparse = np.c_[rng.uniform(0.1, 1, 100), rng.uniform(0.1, 1, 100), np.zeros(100)]
    pts = np.concatenate([dense, sparse])
    idx = grid_sample(pts, 100)
    assert len(idx) == 100 and len(np.unique(idx)) == 100
    assert np.array_equal(idx, grid_sample(pts, 100))
    assert (idx >= 900).sum() > 40  # a random sample would take ~10 of the sparse points
    assert np.array_equal(grid_sample(pts, 5000), np.arange(1000))


# -- model --------------------------------------------------------------------------------------------------------
def test_model_shapes_ranges_and_trajectory(cfg):
    batch = make_batch(cfg, seeds=(1, 2))
    model = build_model(cfg).eval()
    with torch.inference_mode():
        feats = model.encode(batch)
        scores, traj = model.sample(feats, generator=torch.Generator().manual_seed(0), return_trajectory=True)
        sub = model.sample(feats, steps=2, point_index=torch.arange(100).repeat(2, 1))
    assert feats.shape == (2, N, cfg.feature_dim)
    assert scores.shape == (2, N, 4) and traj.shape == (cfg.inference_steps + 1, 2, N, 4)
    assert float(scores.min()) >= 0 and float(scores.max()) <= 1
    assert torch.equal(traj[-1], scores)
    assert sub.shape == (2, 100, 4)
    losses = build_model(cfg).forward_train(batch, torch.Generator().manual_seed(0))
    assert set(losses) == {"denoise", "map", "loss"} and torch.isfinite(losses["loss"])


@pytest.mark.parametrize("overrides", [{}, {"segment_levers": True, "segment_size": True}, {"encoder": "pointnet"}])
def test_encoding_only_the_decoded_rows_gives_those_rows_features(cfg, overrides):
    """``encode(batch, rows)`` runs the finest level on those rows alone: the same features, so the same scores."""
    config = DiffusionConfig.from_dict({**cfg.to_dict(), **overrides})
    batch = make_batch(config, seeds=(1, 2))
    model = build_model(config).eval()
    rows = torch.stack([torch.randperm(N, generator=torch.Generator().manual_seed(s))[:100] for s in (0, 1)])
    with torch.inference_mode():
        whole = model.encode(batch)
        part = model.encode(batch, rows)
        assert part.shape == (2, 100, whole.shape[-1])
        assert torch.allclose(part, gather(whole, rows), atol=1e-6), float((part - gather(whole, rows)).abs().max())
        before = model.sample(whole, steps=2, generator=torch.Generator().manual_seed(0), point_index=rows)
        now = model.sample(part, steps=2, generator=torch.Generator().manual_seed(0))
    assert torch.allclose(before, now, atol=1e-5)


def test_the_finest_interpolation_at_the_decoded_rows_only_changes_no_feature(cfg):
    """``model_inputs(..., rows=...)`` computes ``fp1_*`` at those rows alone: the same rows of the whole cloud's, to
    the bit, and the encoder given them returns the same features as given every point's."""
    scene = synthetic_scene(np.random.default_rng(4), N)
    rows = np.sort(np.random.default_rng(5).choice(N, 100, replace=False))
    whole = model_inputs(scene["points"], scene["normals"], cfg)
    part = model_inputs(scene["points"], scene["normals"], cfg, rows=rows)
    assert part["fp1_index"].shape == (100, 3) and whole["fp1_index"].shape == (N, 3)
    for key in whole:
        expected = whole[key][rows] if key in ("fp1_index", "fp1_weight") else whole[key]
        assert np.array_equal(part[key], expected), key
    assert np.array_equal(model_inputs(scene["points"], scene["normals"], cfg, rows=np.arange(N))["fp1_index"],
                          whole["fp1_index"])  # rows of every point: the whole cloud's arrays
    model = build_model(cfg).eval()
    as_tensors = lambda inputs: {k: torch.from_numpy(np.asarray(v)).unsqueeze(0)  # noqa: E731
                                 for k, v in {**scene, **inputs}.items()}
    index = torch.from_numpy(rows).unsqueeze(0)
    with torch.inference_mode():
        assert torch.equal(model.encode(as_tensors(part), index), model.encode(as_tensors(whole), index))


def test_folded_batchnorm_encoder_matches(cfg):
    batch = make_batch(cfg, seeds=(1, 2))
    model = build_model(cfg)
    model.train()
    model.forward_train(batch)  # move the running statistics off their initial values
    model.eval()
    with torch.inference_mode():
        ref = model.encode(batch)
        folded = fold_batchnorm(model.encoder)(batch)
    assert not any(isinstance(m, torch.nn.BatchNorm1d) for m in fold_batchnorm(model.encoder).modules())
    assert torch.allclose(ref, folded, atol=1e-4), float((ref - folded).abs().max())
    with torch.inference_mode():
        twice = fold_batchnorm(fold_batchnorm(model.encoder))(batch)
    assert torch.equal(twice, folded)  # idempotent: a policy built on a folded model folds nothing more
    wide = fold_batchnorm(model.encoder.double())  # the fused layers keep their dtype (and device: a GPU model's)
    assert {p.dtype for p in wide.parameters()} == {torch.float64}


def test_gather_picks_the_indexed_rows_of_each_cloud_in_the_batch():
    values = torch.arange(2 * 5 * 3, dtype=torch.float32).reshape(2, 5, 3)
    index = torch.tensor([[[4, 0], [1, 1]], [[0, 2], [3, 4]]])
    out = gather(values, index)
    assert out.shape == (2, 2, 2, 3)
    for b in range(2):  # cloud b's rows only, never the other cloud's
        assert torch.equal(out[b], values[b][index[b]])


def test_chunked_inference_of_the_set_abstractions_matches_one_pass(cfg, monkeypatch):
    batch = make_batch(cfg, seeds=(1, 2))
    model = build_model(cfg)
    model.train()
    model.forward_train(batch)  # running statistics off their initial values
    model.eval()
    with torch.inference_mode():
        whole = model.encode(batch)  # the tiny config's centres fit one chunk
        monkeypatch.setattr(pointnet2, "INFERENCE_GROUP_ROWS", 3 * cfg.nsample)  # 3 centres a chunk, a short last one
        chunked = model.encode(batch)
    assert torch.allclose(whole, chunked, atol=1e-6), float((whole - chunked).abs().max())


@pytest.mark.parametrize("with_skip", [True, False])
def test_feature_propagation_is_the_mlp_of_the_interpolated_coarse_features_and_the_skip(with_skip):
    """The coarse half of the first layer runs before the interpolation: the same as the textbook order."""
    torch.manual_seed(0)
    fp = FeaturePropagation([6 + (4 if with_skip else 0), 8, 5]).train()
    coarse, skip = torch.randn(2, 7, 6), (torch.randn(2, 20, 4) if with_skip else None)
    index = torch.randint(0, 7, (2, 20, 3))
    weight = torch.softmax(torch.randn(2, 20, 3), dim=-1)
    up = (coarse.unsqueeze(1).expand(-1, 20, -1, -1).gather(2, index.unsqueeze(-1).expand(-1, -1, -1, 6))
          * weight.unsqueeze(-1)).sum(dim=2)
    expected = fp.mlp(up if skip is None else torch.cat([up, skip], dim=-1))
    assert torch.allclose(fp(skip, coarse, index, weight), expected, atol=1e-5)


def test_ablation_configs_build_and_run():
    for cfg in (DiffusionConfig.tiny(inference_steps=2, use_visibility=False),
                DiffusionConfig.tiny(inference_steps=2, use_normals=False, schedule="cosine", prediction="x0"),
                DiffusionConfig.tiny(inference_steps=2, encoder="pointnet", map_loss_weight=0.0)):
        batch = make_batch(cfg)
        model = build_model(cfg)
        assert torch.isfinite(model.forward_train(batch)["loss"])
        with torch.inference_mode():
            assert model.eval().sample(model.encode(batch)).shape == (1, N, cfg.num_channels)


def test_segment_levers_condition_the_decoder_in_training_and_in_the_policy():
    cfg = DiffusionConfig.tiny(inference_steps=2, prediction="x0", map_loss_weight=0.0, segment_levers=True)
    batch = make_batch(cfg)
    levers = batch["surface_levers"]
    assert levers.shape == (1, N, 4) and float(levers[..., 3].max()) > 0.01  # box tops have real lever arms
    model = build_model(cfg)
    assert model.decoder.cond[0].in_channels == cfg.feature_dim + 4
    with torch.inference_mode():
        feats = model.eval().encode(batch)
    assert feats.shape == (1, N, cfg.feature_dim + 4)
    assert torch.allclose(feats[..., -4:], levers / LEVER_UNIT)
    assert torch.isfinite(model.train().forward_train(batch)["loss"])
    with pytest.raises(KeyError, match="surface_levers"):
        model.encode({k: v for k, v in batch.items() if k != "surface_levers"})
    candidates = DiffusionSuctionPolicy(model=model, seed=0).predict(obs_from(), top_k=5)
    assert len(candidates.points) == 5


def test_segment_size_is_the_radius_of_gyration_of_each_points_face():
    square = np.array([[1, 1, 0], [1, -1, 0], [-1, 1, 0], [-1, -1, 0], [5, 5, 1], [5, 5, 3]], dtype=float)
    labels = np.array([0, 0, 0, 0, 1, 1])
    sizes = segment_sizes(square, labels)
    assert sizes.shape == (6, 1) and sizes.dtype == np.float32
    assert np.allclose(sizes[:4], np.sqrt(2.0)) and np.allclose(sizes[4:], 1.0)
    assert np.allclose(segment_sizes(square * 3.0, labels), 3.0 * sizes)  # metres, not point counts
    assert segment_sizes(np.zeros((0, 3)), np.zeros(0, dtype=int)).shape == (0, 1)
    offsets = offsets_to_centroids(square, labels)  # shared by the levers and the sizes (model_inputs)
    assert np.array_equal(segment_sizes(square, labels, offsets), sizes)
    assert np.array_equal(segment_levers(square, labels, offsets), segment_levers(square, labels))


def test_segment_size_and_encoder_levers_reach_the_networks():
    base = dict(inference_steps=2, prediction="x0", map_loss_weight=0.0, segment_levers=True)
    sized = DiffusionConfig.tiny(**base, segment_size=True)
    batch = make_batch(sized)
    assert batch["surface_size"].shape == (1, N, 1) and float(batch["surface_size"].min()) >= 0.0
    model = build_model(sized)
    assert model.decoder.cond[0].in_channels == sized.feature_dim + 4 + 1
    with torch.inference_mode():
        feats = model.eval().encode(batch)
    assert torch.allclose(feats[..., -1:], batch["surface_size"] / LEVER_UNIT)
    both = DiffusionConfig.tiny(**base, segment_size=True, levers_in_encoder=True)
    for encoder in ("pointnet2", "pointnet"):
        cfg = DiffusionConfig.tiny(**{**base, "segment_size": True, "levers_in_encoder": True, "encoder": encoder})
        model = build_model(cfg)
        first = model.encoder.sa[0].first[0] if encoder == "pointnet2" else model.encoder.local[0]
        assert first.in_features == 3 + 3 + 4 + 1  # xyz, normals, levers, size
        assert torch.isfinite(model.train().forward_train(make_batch(cfg))["loss"])
    # the encoder reads the levers: changing them changes its features (the decoder's copy left aside)
    model = build_model(both).eval()
    moved = {**batch, "surface_levers": batch["surface_levers"] + 0.05}
    with torch.inference_mode():
        a, b = model.encoder(batch), model.encoder(moved)
    assert not torch.allclose(a, b)
    with pytest.raises(KeyError, match="surface_size"):
        model.encode({k: v for k, v in batch.items() if k != "surface_size"})
    candidates = DiffusionSuctionPolicy(model=model, seed=0).predict(obs_from(), top_k=5)
    assert len(candidates.points) == 5


@pytest.mark.filterwarnings("ignore:precision='bfloat16' on a CPU without")  # CI's host may emulate it
def test_bfloat16_inference_ranks_like_float32_and_returns_float32_scores():
    cfg = DiffusionConfig.tiny(inference_steps=2, prediction="x0", map_loss_weight=0.0)
    model = build_model(cfg)
    exact = DiffusionSuctionPolicy(model=model, seed=0).predict(obs_from(), top_k=20)
    low = DiffusionSuctionPolicy(model=model, seed=0, precision="bfloat16").predict(obs_from(), top_k=20)
    assert low.scores.dtype == np.float32 and len(low.points) == 20
    assert not np.array_equal(exact.scores, low.scores)  # the matmuls really ran in bfloat16
    assert np.abs(np.sort(exact.scores) - np.sort(low.scores)).max() < 0.05
    with pytest.raises(ValueError, match="precision must be one of"):
        DiffusionSuctionPolicy(model=model, precision="float16")


@pytest.mark.parametrize("native", [True, False])
def test_bfloat16_warns_where_the_cpu_would_emulate_it(native, monkeypatch):
    monkeypatch.setattr(diffusion_policy, "cpu_runs_bfloat16_natively", lambda: native)
    model = build_model(DiffusionConfig.tiny())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        DiffusionSuctionPolicy(model=model, precision="bfloat16")
        DiffusionSuctionPolicy(model=model, precision="float32")
    emulated = [w for w in caught if "emulated" in str(w.message)]
    assert len(emulated) == (0 if native else 1)


def test_config_validation():
    for bad in ({"num_points": 0}, {"encoder": "dgcnn"}, {"schedule": "sqrt"}, {"scale": -1},
                {"segment_radius": 0.0}, {"segment_min_cos": 1.5},
                {"inference_steps": 2000}, {"sa_npoints": (600, 32, 16, 8)}, {"sa_radii": ((-0.01, 0.02, 0.03),) * 4}):
        with pytest.raises(ValueError):
            DiffusionConfig.tiny(**bad)
    c = DiffusionConfig.tiny()
    assert DiffusionConfig.from_dict(c.to_dict()) == c
    with pytest.raises(ValueError, match="unknown"):
        DiffusionConfig.from_dict({**c.to_dict(), "bogus": 1})


def test_same_seed_same_prediction(cfg):
    batch = make_batch(cfg)
    a, b = build_model(cfg, seed=5).eval(), build_model(cfg, seed=5).eval()
    with torch.inference_mode():
        sa = a.sample(a.encode(batch), generator=torch.Generator().manual_seed(1))
        sb = b.sample(b.encode(batch), generator=torch.Generator().manual_seed(1))
        sc = b.sample(b.encode(batch), generator=torch.Generator().manual_seed(2))
    assert torch.equal(sa, sb)
    assert not torch.equal(sa, sc)


def test_several_noise_draws_average_their_score_maps(cfg):
    """``draws=K`` denoises K noise draws as one batch and returns their mean map: the mean of K runs one after
    another on the same noise stream, and for K = 1 the plain sample to the bit."""
    batch = make_batch(cfg, seeds=(1, 2))
    model = build_model(cfg, seed=5).eval()
    with torch.inference_mode():
        features = model.encode(batch)
        single = model.sample(features, generator=torch.Generator().manual_seed(3))
        assert torch.equal(model.sample(features, generator=torch.Generator().manual_seed(3), draws=1), single)
        g = torch.Generator().manual_seed(3)
        one_by_one = torch.stack([model.sample(features, generator=g) for _ in range(3)])
        mean, trajectory = model.sample(features, generator=torch.Generator().manual_seed(3), draws=3,
                                        return_trajectory=True)
    assert torch.allclose(mean, one_by_one.mean(0), atol=1e-5), float((mean - one_by_one.mean(0)).abs().max())
    assert not torch.allclose(mean, single, atol=1e-3)  # the mean of three is not the first draw
    assert mean.shape == single.shape and trajectory.shape == (cfg.inference_steps + 1, *single.shape)
    for bad in (0, 1.5, -2):
        with pytest.raises(ValueError, match="draws"):
            model.sample(features, draws=bad)
    with pytest.raises(ValueError, match="draws"):
        DiffusionSuctionPolicy(model=model, draws=0)
    candidates = DiffusionSuctionPolicy(model=model, draws=2, record_trajectory=False).predict(obs_from(5), top_k=3)
    assert len(candidates) > 0


@pytest.mark.parametrize("objective", [{}, {"prediction": "x0", "map_loss_weight": 0.0},
                                       {"prediction": "x0", "map_loss_weight": 0.0, "segment_levers": True}],
                         ids=["eps+map", "x0", "x0+levers"])
def test_training_learns_to_rank_good_suction_points(objective):
    """Overfit one synthetic scene: the top-k precision of the sampled map must clearly beat the untrained model.

    Both objectives: the public code's (eps plus the sampled-map loss) and the CPU preset's (x0 alone).
    """
    cfg = DiffusionConfig.tiny(inference_steps=5, **objective)
    batch = make_batch(cfg)
    quality = batch["labels"].prod(-1)
    model = build_model(cfg, seed=0)

    def ap() -> float:
        model.eval()
        with torch.inference_mode():
            s = model.sample(model.encode(batch), generator=torch.Generator().manual_seed(1))
        model.train()
        return topk_precision(s.prod(-1), quality, k=20)

    before = ap()
    opt = torch.optim.Adam(model.parameters(), lr=2e-3)
    for i in range(100):
        loss = model.forward_train(batch, torch.Generator().manual_seed(i))["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = ap()
    assert before < 0.3
    assert after > max(0.45, before + 0.25), (before, after)


def test_positive_weight_weights_the_loss_by_the_label(cfg):
    """1 + w * label per point and channel: unlabelled scenes are unaffected, labelled points count more."""
    plain, weighted = (build_model(DiffusionConfig.tiny(inference_steps=5, prediction="x0", map_loss_weight=0.0,
                                                        positive_weight=w), seed=0) for w in (0.0, 4.0))
    batch = make_batch(cfg)
    empty = {**batch, "labels": torch.zeros_like(batch["labels"])}
    loss = {name: [float(m.forward_train(b, torch.Generator().manual_seed(1))["loss"].detach())
                   for m in (plain, weighted)] for name, b in (("labelled", batch), ("empty", empty))}
    assert loss["empty"][0] == pytest.approx(loss["empty"][1], rel=1e-6)
    assert loss["labelled"][1] > loss["labelled"][0] * 1.1


def test_topk_precision_known_values():
    labels = torch.tensor([[1.0, 0.5, 0.0, 0.9]])
    perfect = topk_precision(labels.clone(), labels, k=2, thresholds=(0.4,))
    worst = topk_precision(-labels, labels, k=1, thresholds=(0.4,))
    assert perfect == 1.0 and worst == 0.0


# -- checkpoints --------------------------------------------------------------------------------------------------
def test_checkpoint_roundtrip_and_errors(cfg, tmp_path):
    model = build_model(cfg, seed=3)
    path = save_checkpoint(tmp_path / "m.pt", model, step=7)
    loaded, payload = load_model(path)
    assert payload["step"] == 7 and payload["config"] == cfg
    for k, v in model.state_dict().items():
        assert torch.equal(v, loaded.state_dict()[k])
    with pytest.raises(FileNotFoundError, match="nope.pt"):
        load_checkpoint(tmp_path / "nope.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="junk.pt"):
        load_checkpoint(tmp_path / "junk.pt")
    with pytest.raises(ValueError, match="config mismatch"):
        load_model(path, expected=DiffusionConfig.tiny(inference_steps=7))
    bad = torch.load(path, weights_only=True)
    bad["config"]["decoder_dim"] = 64  # weights no longer fit the config
    torch.save(bad, tmp_path / "mismatch.pt")
    with pytest.raises(ValueError, match="mismatch.pt.*do not match"):
        load_model(tmp_path / "mismatch.pt")
    bad["version"] = 99
    torch.save(bad, tmp_path / "future.pt")
    with pytest.raises(ValueError, match="version"):
        load_checkpoint(tmp_path / "future.pt")


# -- policy -------------------------------------------------------------------------------------------------------
def test_policy_predicts_sorted_nms_candidates(cfg, tmp_path):
    path = save_checkpoint(tmp_path / "m.pt", build_model(cfg))
    policy = DiffusionSuctionPolicy(checkpoint=path, seed=0)
    obs = obs_from(3, 2 * N)  # more points than num_points: subsampled
    obs["points"][:5] = np.nan  # dropouts are skipped
    cands = policy.predict(obs, top_k=10)
    assert isinstance(cands, Candidates) and 0 < len(cands) <= 10
    assert np.all(np.diff(cands.scores) <= 0) and cands.scores.min() >= 0 and cands.scores.max() <= 1
    assert np.allclose(np.linalg.norm(cands.normals, axis=1), 1, atol=1e-5)
    d = np.linalg.norm(cands.points[:, None] - cands.points[None], axis=-1) + np.eye(len(cands))
    assert d.min() > 0.02 - 1e-6
    traj = policy.last_trajectory
    assert traj is not None and traj.maps.shape == (cfg.inference_steps + 1, N, 4) and len(traj.points) == N
    assert policy.act(obs).shape == (6,)
    again = DiffusionSuctionPolicy(checkpoint=path, seed=0).predict(obs, top_k=10)
    assert np.array_equal(again.points, cands.points) and np.array_equal(again.scores, cands.scores)


def test_policy_decode_subset_and_bad_inputs(cfg, tmp_path):
    policy = DiffusionSuctionPolicy(model=build_model(cfg), decode_points=128)
    obs = obs_from(4)
    assert len(policy.predict(obs, top_k=5)) <= 5
    assert policy.last_trajectory.maps.shape[1] == 128
    empty = policy.predict({"points": np.zeros((0, 3)), "normals": np.zeros((0, 3))})
    assert len(empty) == 0 and policy.last_trajectory is None
    assert len(policy.predict({k: v[:3] for k, v in obs.items()})) == 0
    assert 0 < len(policy.predict({k: v[:20] for k, v in obs.items()}, top_k=4)) <= 4  # tiny but usable
    with pytest.raises(ValueError, match="no candidates"):
        policy.act({"points": np.zeros((0, 3)), "normals": np.zeros((0, 3))})
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        policy.predict({"points": np.zeros((10, 2)), "normals": np.zeros((10, 2))})
    with pytest.raises(ValueError, match="normals"):
        policy.predict({"points": np.zeros((10, 3))})
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        DiffusionSuctionPolicy(checkpoint=tmp_path / "missing.pt")


# -- post-processing ----------------------------------------------------------------------------------------------
def test_nms_matches_brute_force_greedy():
    rng = np.random.default_rng(0)
    pts, scores = rng.uniform(0, 0.2, (400, 3)), rng.random(400)
    keep = nms_indices(pts, scores, 0.02)
    ref, alive = [], np.ones(400, bool)
    for i in np.argsort(-scores):
        if alive[i]:
            ref.append(i)
            alive &= np.linalg.norm(pts - pts[i], axis=1) > 0.02
    assert keep.tolist() == ref
    assert nms_indices(pts, scores, 0.02, max_keep=5).tolist() == ref[:5]
    assert len(cKDTree(pts[keep]).query_pairs(0.02 - 1e-9)) == 0
    c = select_candidates(pts, np.tile([0, 0, 2.0], (400, 1)), scores, top_k=3)
    assert len(c) == 3 and np.allclose(c.normals, [0, 0, 1])
    with pytest.raises(ValueError):
        nms_indices(pts, scores[:10])


# -- trainer CLI --------------------------------------------------------------------------------------------------
def test_train_cli_runs_and_resumes_deterministically(tmp_path):
    from policies.diffusion.train import main

    common = ["--synthetic", "4", "--preset", "tiny", "--num-points", "256", "--inference-steps", "3",
              "--batch-size", "2", "--val-every", "2", "--val-scenes", "1", "--threads", "1", "--no-progress"]
    main(common + ["--out", str(tmp_path / "a"), "--steps", "4"])
    main(common + ["--out", str(tmp_path / "b"), "--steps", "2"])
    main(common + ["--out", str(tmp_path / "b"), "--steps", "4", "--resume"])
    a, b = load_checkpoint(tmp_path / "a" / "last.pt"), load_checkpoint(tmp_path / "b" / "last.pt")
    assert a["step"] == b["step"] == 4 and (tmp_path / "a" / "best.pt").is_file()
    for k, v in a["model"].items():
        assert torch.equal(v, b["model"][k]), k
    # the resumed run's record keeps both invocations, and its wall time is theirs together
    parts = b["extra"]["provenance"]["parts"]
    assert "parts" not in a["extra"]["provenance"] and len(parts) == 2 and "--resume" in parts[1]["command"]
    assert "--resume" not in parts[0]["command"]
    assert b["extra"]["provenance"]["wall_time_s"] == pytest.approx(sum(p["wall_time_s"] for p in parts))
    policy = DiffusionSuctionPolicy(checkpoint=tmp_path / "a" / "best.pt")
    assert len(policy.predict(obs_from(5, 256), top_k=3)) > 0


def test_train_cli_sets_the_ddim_sampler():
    from policies.diffusion.train import make_config, parse_args

    cfg = make_config(parse_args(["--synthetic", "4", "--timestep-spacing", "trailing", "--eta", "0.2"]))
    assert (cfg.timestep_spacing, cfg.eta) == ("trailing", 0.2)
    assert make_config(parse_args(["--synthetic", "4"])).timestep_spacing == DiffusionConfig().timestep_spacing


def test_train_cli_turns_the_segment_levers_on_or_off_whatever_the_preset():
    from policies.diffusion.train import make_config, parse_args

    assert not make_config(parse_args(["--synthetic", "4", "--preset", "paper"])).segment_levers
    assert make_config(parse_args(["--synthetic", "4", "--preset", "paper", "--segment-levers"])).segment_levers
    assert make_config(parse_args(["--synthetic", "4"])).segment_levers  # the cpu preset's default
    assert not make_config(parse_args(["--synthetic", "4", "--no-segment-levers"])).segment_levers
    with pytest.raises(SystemExit):  # both at once say two different things
        parse_args(["--synthetic", "4", "--segment-levers", "--no-segment-levers"])


def test_train_cli_warm_starts_from_a_checkpoint_and_keeps_its_record(tmp_path, capsys):
    import hashlib
    import json

    from policies.diffusion.train import main

    common = ["--synthetic", "4", "--preset", "tiny", "--num-points", "256", "--inference-steps", "3",
              "--batch-size", "2", "--val-every", "2", "--val-scenes", "1", "--threads", "1", "--no-progress"]
    main(common + ["--out", str(tmp_path / "a"), "--steps", "4"])
    start = tmp_path / "a" / "last.pt"
    a = load_checkpoint(start)
    main(common + ["--out", str(tmp_path / "b"), "--steps", "2", "--init", str(start)])
    b = load_checkpoint(tmp_path / "b" / "last.pt")
    # the warm start's first validation is the start model's own (same weights, scenes and noise)
    base = json.loads((tmp_path / "b" / "log.jsonl").read_text().splitlines()[0])
    assert base["step"] == 0 and base["val_loss"] == pytest.approx(a["extra"]["metrics"]["val_loss"], rel=1e-6)
    record = b["extra"]["init"]
    assert record["step"] == 4 and record["checkpoint"] == str(start)
    assert record["sha256"] == hashlib.sha256(start.read_bytes()).hexdigest()
    assert record["provenance"]["command"] == a["extra"]["provenance"]["command"]
    assert b["step"] == 2 and "--init" in b["extra"]["provenance"]["command"]
    # best.pt only where validation beat the start model's
    if (tmp_path / "b" / "best.pt").is_file():
        assert load_checkpoint(tmp_path / "b" / "best.pt")["extra"]["best_ap_proxy"] > base["val_ap_proxy"]
    else:
        assert "was not written" in capsys.readouterr().err
    # a start model of another config is refused, naming the field
    with pytest.raises(SystemExit, match="--init .*num_points"):
        main(common[:4] + ["--num-points", "128"] + common[6:] + ["--out", str(tmp_path / "c"), "--steps", "2",
                                                                 "--init", str(start)])
    with pytest.raises(SystemExit):  # --init and --resume say two different things
        main(common + ["--out", str(tmp_path / "b"), "--steps", "4", "--resume", "--init", str(start)])


def test_train_cli_stops_at_max_minutes_validated_and_saved(tmp_path):
    import json

    from parcelpick_env.cli import UsageError
    from policies.diffusion.train import main

    common = ["--synthetic", "4", "--preset", "tiny", "--num-points", "256", "--inference-steps", "3",
              "--batch-size", "2", "--val-every", "100", "--val-scenes", "1", "--threads", "1", "--no-progress"]
    main(common + ["--out", str(tmp_path / "a"), "--steps", "50", "--max-minutes", "1e-6"])  # past at once
    lines = [json.loads(line) for line in (tmp_path / "a" / "log.jsonl").read_text().splitlines()]
    assert lines[-1] == {"stopped_at_step": 1, "of_steps": 50, "max_minutes": 1e-6}
    assert lines[-2]["step"] == 1 and "val_ap_proxy" in lines[-2]  # validated where it stopped
    assert load_checkpoint(tmp_path / "a" / "last.pt")["step"] == 1
    main(common + ["--out", str(tmp_path / "b"), "--steps", "2", "--max-minutes", "60"])  # a budget not reached
    assert load_checkpoint(tmp_path / "b" / "last.pt")["step"] == 2
    assert "stopped_at_step" not in (tmp_path / "b" / "log.jsonl").read_text()
    for bad in ("0", "-1", "nan"):
        with pytest.raises(UsageError, match="--max-minutes"):
            main(common + ["--out", str(tmp_path / "c"), "--steps", "2", "--max-minutes", bad])
