"""Diffusion-Suction decoding at the depth image's points: the strided view, the candidates, the encoder's features
at query points, and the policy's choice of where to decode."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import torch

from policies.diffusion.candidates import depth_candidates, has_depth_view, strided_view
from policies.diffusion.config import DiffusionConfig
from policies.diffusion.model import build_model
from policies.diffusion.neighbourhood import model_inputs, model_inputs_at, segment_inputs
from policies.diffusion.policy import DiffusionSuctionPolicy
from policies.diffusion.synthetic import synthetic_scene
from policies.heatmap import pixels_to_world
from tests.rendered_depth import depth_image, straight_down

pytestmark = pytest.mark.usefixtures("one_torch_thread")

WIDTH, HEIGHT, FOCAL = 160, 120, 150.0
BOX = ((-0.1, -0.08, 0.0), (0.1, 0.08, 0.2))  # the bin: a 20 x 16 cm region around the slab


@pytest.fixture(scope="module")
def view() -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """A 12 x 10 x 5 cm slab on a floor seen straight down from 0.8 m, as the env's (obs, info)."""
    scene = o3d.t.geometry.RaycastingScene()
    floor = o3d.geometry.TriangleMesh.create_box(2.0, 2.0, 0.01).translate((-1.0, -1.0, -0.01))
    slab = o3d.geometry.TriangleMesh.create_box(0.12, 0.10, 0.05).translate((-0.06, -0.05, 0.0))
    for mesh in (floor, slab):
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    K, T = straight_down(FOCAL, WIDTH, HEIGHT, (0.0, 0.0, 0.8))
    depth = depth_image(scene, K, T, WIDTH, HEIGHT)
    rows, cols = np.nonzero(depth > 0)
    points = pixels_to_world(rows, cols, depth, K, T)
    pick = np.random.default_rng(0).choice(len(points), 512, replace=False)
    normals = np.tile([0.0, 0.0, 1.0], (512, 1))
    obs = {"points": points[pick].astype(np.float32), "normals": normals.astype(np.float32), "depth": depth[..., None]}
    info = {"intrinsics": K, "extrinsics": T, "workspace": np.array(BOX)}
    return obs, info


def test_a_strided_pixel_projects_where_its_full_resolution_pixel_does(view):
    obs, info = view
    depth = np.ascontiguousarray(np.tile(obs["depth"][..., 0], (1, 3)))  # 480 wide: stride 2 to 240 columns
    K = np.array(info["intrinsics"], dtype=np.float64)
    small, K_small = strided_view(depth, K)
    assert small.shape == (HEIGHT // 2, 3 * WIDTH // 2)
    rows, cols = np.nonzero(small > 0)
    assert np.allclose(pixels_to_world(rows, cols, small, K_small, info["extrinsics"]),
                       pixels_to_world(2 * rows, 2 * cols, depth, K, info["extrinsics"]), atol=1e-12)
    narrow = obs["depth"][..., 0]  # 160 wide: kept as it is
    kept, K_kept = strided_view(narrow, K)
    assert kept is narrow and K_kept is K


def test_depth_candidates_lie_in_the_bin_with_the_surfaces_normals(view):
    obs, info = view
    points, normals = depth_candidates(obs, info, 400)
    assert points.dtype == np.float32 and len(points) == 400  # more pixels than asked lie in the bin
    lo, hi = np.array(BOX)
    assert np.all((points >= lo) & (points <= hi))
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    top = points[:, 2] > 0.049  # the slab's top face and the floor around it: both level, facing the camera
    assert top.any() and (~top).any()
    interior = (np.abs(points[:, 0]) < 0.05) & (np.abs(points[:, 1]) < 0.04) | (np.abs(points[:, 0]) > 0.075)
    assert np.all(normals[interior, 2] > 0.99)
    dense, _ = depth_candidates(obs, info, 10 ** 6)  # every pixel in the bin
    assert len(dense) > 400 and len(dense) > len(obs["points"])


def test_depth_candidates_refuse_a_bad_count_and_find_none_outside_the_view(view):
    obs, info = view
    with pytest.raises(ValueError, match="count"):
        depth_candidates(obs, info, 0)
    away = {**info, "workspace": np.array([(5.0, 5.0, 0.0), (6.0, 6.0, 1.0)])}
    points, normals = depth_candidates(obs, away, 100)
    assert points.shape == normals.shape == (0, 3)
    assert has_depth_view(obs, info) and not has_depth_view({"points": obs["points"]}, info)
    assert not has_depth_view(obs, {**info, "workspace": None}) and not has_depth_view(obs, None)


@pytest.mark.parametrize("overrides", [{}, {"segment_levers": True, "segment_size": True}])
def test_features_at_query_points_of_the_cloud_are_the_clouds_own(overrides):
    """Queried at the cloud's own points, ``model_inputs_at`` gives each the features the whole cloud's encoding
    has there: the encoder's levels read the cloud alone, and a query takes its nearest point's segment (itself)."""
    config = DiffusionConfig.tiny(inference_steps=2, **overrides)
    scene = synthetic_scene(np.random.default_rng(4), 512)
    points, normals = scene["points"], scene["normals"]
    model = build_model(config).eval()

    def encoded(batch, rows=None):
        tensors = {k: torch.from_numpy(np.ascontiguousarray(v)).unsqueeze(0) for k, v in batch.items()}
        with torch.inference_mode():
            return model.encode(tensors, rows)[0]

    whole = encoded({"points": points, "normals": normals, **model_inputs(points, normals, config)})
    at = model_inputs_at(points, normals, points, normals, config)
    assert at["points"].shape == (1024, 3) and at["fp1_index"].shape == (512, 3)
    queried = encoded(at, torch.arange(512, 1024).unsqueeze(0))
    assert torch.allclose(queried, whole, atol=1e-5), float((queried - whole).abs().max())


def test_a_query_joins_its_nearest_points_segment():
    """Two faces a gap apart: a query on either takes that face's centroid and size, whatever the query density."""
    xs, ys = np.meshgrid(np.linspace(0, 0.1, 11), np.linspace(0, 0.1, 11))
    face = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], 1)
    points = np.concatenate([face, face + (0.2, 0, 0)])
    normals = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    config = DiffusionConfig.tiny(segment_levers=True, segment_size=True)
    queries = np.array([[0.013, 0.021, 0.0], [0.29, 0.07, 0.0]])
    out = segment_inputs(points, normals, config, queries)
    levers, sizes = out["surface_levers"][-2:], out["surface_size"][-2:]
    assert np.allclose(levers[:, :3], np.array([[0.05, 0.05, 0.0], [0.25, 0.05, 0.0]]) - queries, atol=1e-6)
    assert np.allclose(levers[:, 3], np.linalg.norm(levers[:, :2], axis=1), atol=1e-6)
    assert np.allclose(sizes, out["surface_size"][0], atol=1e-7)  # the two faces are alike
    assert np.array_equal(out["surface_levers"][:-2], segment_inputs(points, normals, config)["surface_levers"])


def test_model_inputs_at_refuses_the_pointnet_encoder_and_empty_queries():
    config = DiffusionConfig.tiny(encoder="pointnet")
    scene = synthetic_scene(np.random.default_rng(0), 64)
    with pytest.raises(ValueError, match="PointNet\\+\\+"):
        model_inputs_at(scene["points"], scene["normals"], scene["points"], scene["normals"], config)
    with pytest.raises(ValueError, match="queries"):
        model_inputs_at(scene["points"], scene["normals"], np.zeros((0, 3)), np.zeros((0, 3)), DiffusionConfig.tiny())


def test_the_policy_decodes_at_the_depth_images_points_where_it_has_them(view):
    obs, info = view
    model = build_model(DiffusionConfig.tiny(inference_steps=2, candidate_points=300)).eval()
    cloud = {k: obs[k] for k in ("points", "normals")}
    dense = DiffusionSuctionPolicy(model=model, seed=0)
    got = dense.predict(obs, info, top_k=10)
    assert dense.last_trajectory is not None and len(dense.last_trajectory.points) == 300

    def from_cloud(points: np.ndarray) -> bool:
        return bool(np.all(np.min(np.linalg.norm(points[:, None] - obs["points"][None], axis=2), axis=1) < 1e-6))

    assert not from_cloud(got.points)
    assert np.all(np.isin(got.points, dense.last_trajectory.points).all(axis=1))
    for policy, args in ((DiffusionSuctionPolicy(model=model, seed=0, candidate_points=0), (obs, info)),
                         (DiffusionSuctionPolicy(model=model, seed=0), (cloud, info)),
                         (DiffusionSuctionPolicy(model=model, seed=0), (obs, None))):
        assert from_cloud(policy.predict(*args, top_k=10).points)
    pointnet = build_model(DiffusionConfig.tiny(encoder="pointnet", candidate_points=300)).eval()
    assert DiffusionSuctionPolicy(model=pointnet).candidate_points == 0
    with pytest.raises(ValueError, match="candidate_points"):
        DiffusionSuctionPolicy(model=model, candidate_points=-1)
    with pytest.raises(ValueError, match="candidate_points"):
        DiffusionConfig.tiny(candidate_points=-5)
