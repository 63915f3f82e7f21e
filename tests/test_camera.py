"""Overhead camera: metric depth, back-projection, normals, segmentation, noise and the pinhole model."""

from __future__ import annotations

import dataclasses

import numpy as np
import open3d as o3d
import pytest
import trimesh

from parcelpick_env.assets.parcel import ParcelAsset
from parcelpick_env.camera.camera import Camera
from parcelpick_env.camera.config import CameraConfig
from parcelpick_env.camera.frame import BACKGROUND
from parcelpick_env.camera import normals as normals_module
from parcelpick_env.camera.normals import knn_normals_at, open3d_normals, organized_normals, smallest_eigenvectors
from parcelpick_env.scene.scene import BinSpec, ParcelState, Scene
from parcelpick_env.sim.simulator import Simulator

BOX = (0.30, 0.20, 0.10)
BOX_XY = (0.0524, -0.03)  # box edges fall between pixel centres so a half-pixel error would show
CAM_Z = 1.4


def _box_asset() -> ParcelAsset:
    mesh = trimesh.creation.box(extents=BOX)
    mesh.visual.face_colors = np.tile([200, 150, 100, 255], (len(mesh.faces), 1))
    return ParcelAsset(asset_id="test-box", category="rectangular", split="test", mesh=mesh, mass=1.0,
                       com=np.zeros(3), rgba=(0.8, 0.6, 0.4, 1.0), extents=np.asarray(BOX))


@pytest.fixture(scope="module")
def box_world():
    """One box resting exactly on the bin floor (placed, not simulated) under the camera."""
    with Simulator() as sim:
        spec = BinSpec()
        sim.add_bin(spec)
        asset = _box_asset()
        position, orientation = np.array([*BOX_XY, BOX[2] / 2]), np.array([0.0, 0.0, 0.0, 1.0])
        body = sim.add_parcel(asset, position, orientation, friction=0.5)
        parcel = ParcelState(object_id=0, body_id=body, asset=asset, position=position,
                             orientation=orientation, friction=0.5)
        scene = Scene(parcels=[parcel], bin=spec, seed=0, layout="scattered", object_set="rectangular", split="test")
        yield sim, scene


def _camera(**kwargs) -> Camera:
    return Camera(CameraConfig(width=160, height=120, position=(0.0, 0.0, CAM_Z), depth_noise_std=0.0, **kwargs))


def test_config_validation():
    for bad in (dict(width=0), dict(fov_y_deg=0.0), dict(near=2.0, far=1.0), dict(depth_noise_std=-1.0),
                dict(dropout_prob=1.0), dict(renderer="vulkan"), dict(normal_knn=1), dict(position=(0, 0))):
        with pytest.raises(ValueError):
            CameraConfig(**bad)


def test_default_view_covers_the_default_bin():
    cam = Camera(CameraConfig())
    spec = BinSpec()
    sx, sy = spec.inner_size[0] / 2 + spec.wall_thickness, spec.inner_size[1] / 2 + spec.wall_thickness
    rim = np.array([[x, y, z] for x in (-sx, sx) for y in (-sy, sy) for z in (0.0, spec.wall_height)])
    uv = cam.project(rim)
    assert np.all(uv >= 0) and np.all(uv[:, 0] <= cam.config.width - 1) and np.all(uv[:, 1] <= cam.config.height - 1)
    big = BinSpec(inner_size=(1.2, 0.9), wall_height=0.35)
    cam = Camera(CameraConfig.for_bin(big))
    assert np.all(cam.project(np.array([[0.62, 0.47, 0.35], [-0.62, -0.47, 0.0]])) >= 0)


@pytest.mark.parametrize("normal_method", ["open3d", "organized"])
def test_box_top_depth_points_and_normals(box_world, normal_method):
    sim, scene = box_world
    cam = _camera(normal_method=normal_method)
    frame = cam.capture(sim, scene)
    top_z = BOX[2]
    # The pixel seeing the box top centre reads the known distance.
    u, v = np.round(cam.project(np.array([[*BOX_XY, top_z]]))[0]).astype(int)
    assert frame.segmentation[v, u] == 0
    assert abs(frame.depth[v, u] - (CAM_Z - top_z)) < 1e-3
    on_box = frame.point_object_ids == 0
    pts, nrm = frame.points[on_box], frame.normals[on_box]
    assert on_box.sum() > 100
    np.testing.assert_allclose(pts[:, 2], top_z, atol=1e-3)  # only the top is visible from above
    assert np.all(np.abs(pts[:, 0] - BOX_XY[0]) <= BOX[0] / 2 + 2e-3)
    assert np.all(np.abs(pts[:, 1] - BOX_XY[1]) <= BOX[1] / 2 + 2e-3)
    interior = (np.abs(pts[:, 0] - BOX_XY[0]) < BOX[0] / 2 - 0.02) & (np.abs(pts[:, 1] - BOX_XY[1]) < BOX[1] / 2 - 0.02)
    assert np.all(nrm[interior, 2] > 0.99)  # up, towards the camera
    np.testing.assert_allclose(np.linalg.norm(frame.normals, axis=1), 1.0, atol=1e-4)
    # Everything that is not the box is background; the bin floor reads 1.4 m.
    assert set(np.unique(frame.segmentation)) == {BACKGROUND, 0}
    corner = frame.segmentation == BACKGROUND
    floor_pts = frame.points[frame.point_object_ids == BACKGROUND]
    assert corner.any() and np.any(np.abs(floor_pts[:, 2]) < 1e-3)


def test_closed_form_eigenvectors_match_eigh():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(500, 3, 3))
    cov = a @ a.transpose(0, 2, 1) + np.diag([0.0, 0.0, 0.0])
    cov[:5] = np.diag([4.0, 2.0, 1e-6])  # a flat patch: the normal is z
    vec = smallest_eigenvectors(*(cov[:, i, j] for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))))
    ref = np.linalg.eigh(cov)[1][:, :, 0]
    np.testing.assert_allclose(np.abs((vec * ref).sum(1)), 1.0, atol=1e-6)


def test_organized_normals_follow_a_curved_surface_and_skip_depth_jumps():
    h, w = 60, 80
    x, y = np.meshgrid(np.linspace(-0.2, 0.2, w), np.linspace(-0.15, 0.15, h))
    z = 0.05 * np.sin(5 * x)
    z[:, w // 2:] += 0.1  # a 10 cm step: normals next to it must not tilt
    pts = np.stack([x, y, z], -1)
    valid = np.ones((h, w), bool)
    normals = organized_normals(pts, valid, 25, np.array([0.0, 0.0, 1.4])).reshape(h, w, 3)
    truth = np.stack([-0.25 * np.cos(5 * x), np.zeros_like(x), np.ones_like(x)], -1)
    truth /= np.linalg.norm(truth, axis=-1, keepdims=True)
    assert np.all((normals * truth).sum(-1)[2:-2, 2:-2] > 0.999)


def test_pinhole_model_is_consistent(box_world):
    sim, scene = box_world
    cam = _camera()
    frame = cam.capture(sim, scene)
    K, T = frame.intrinsics, frame.extrinsics
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(T[:3, :3] @ [0, 0, 1], [0, 0, -1])  # optical axis looks straight down
    np.testing.assert_allclose(K[0, 0], K[1, 1])
    # Back-projected points project back to their own pixels.
    uv = cam.project(frame.points.astype(np.float64))
    np.testing.assert_allclose(uv[:, ::-1], frame.point_pixels, atol=0.02)
    # A world point left of and above (+y) the optical centre lands left of and above the image centre.
    u, v = cam.project(np.array([[-0.2, 0.1, 0.0]]))[0]
    assert u < K[0, 2] and v < K[1, 2]
    # The box top covers exactly the pixels whose centres (integers, OpenCV) fall inside its
    # projection; BOX_XY is chosen so a half-pixel convention error would shift the first column.
    rows, cols = np.nonzero(frame.segmentation == 0)
    (u0, _), (u1, _) = cam.project(np.array([[BOX_XY[0] - BOX[0] / 2, BOX_XY[1], BOX[2]],
                                              [BOX_XY[0] + BOX[0] / 2, BOX_XY[1], BOX[2]]]))
    assert cols.min() == np.ceil(u0) and cols.max() == np.floor(u1)
    v = cam.project(np.array([[*BOX_XY, BOX[2]]]))[0, 1]
    assert abs(rows.mean() - v) < (0.5 if cam.renderer == "egl" else 1.0)  # TinyRenderer: half a row lower


def test_noise_and_dropout_are_reproducible(box_world):
    sim, scene = box_world
    clean = _camera().capture(sim, scene)
    cam = Camera(CameraConfig(width=160, height=120, position=(0.0, 0.0, CAM_Z), depth_noise_std=0.002,
                              dropout_prob=0.1))
    a = cam.capture(sim, scene, np.random.default_rng(5))
    b = cam.capture(sim, scene, np.random.default_rng(5))
    c = cam.capture(sim, scene, np.random.default_rng(6))
    assert np.array_equal(a.depth, b.depth) and np.array_equal(a.points, b.points)
    assert not np.array_equal(a.depth, c.depth)
    valid = clean.depth > 0
    dropped = valid & (a.depth == 0)
    assert 0.07 < dropped.sum() / valid.sum() < 0.13
    kept = valid & (a.depth > 0)
    residual = a.depth[kept] - clean.depth[kept]
    assert 0.0015 < residual.std() < 0.0025 and abs(residual.mean()) < 5e-4
    assert len(a.points) == kept.sum()
    assert np.array_equal(a.segmentation, clean.segmentation)  # ground truth is not noised


def test_small_scene_segmentation_matches_object_surfaces(small_scene, small_sim, small_camera):
    scene, frame = small_scene
    # build_pile resets the world; EGL (when present) must still see the parcels added after it.
    assert small_camera.renderer == ("egl" if small_sim.egl_enabled else "tiny")
    assert frame.rgb.shape == (120, 160, 3) and frame.depth.shape == (120, 160)
    ids = set(np.unique(frame.segmentation)) - {BACKGROUND}
    assert ids and ids <= {p.object_id for p in scene.parcels}
    for p in scene.parcels:
        mask = frame.point_object_ids == p.object_id
        if not mask.any():
            continue
        raycast = o3d.t.geometry.RaycastingScene()
        mesh = p.world_mesh()
        raycast.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                              o3d.core.Tensor(mesh.faces.astype(np.uint32)))
        dist = raycast.compute_distance(o3d.core.Tensor(frame.points[mask])).numpy()
        assert np.quantile(dist, 0.95) < 3e-3  # pixels labelled k lie on parcel k's true surface
    assert np.array_equal(frame.segmentation[frame.point_pixels[:, 0], frame.point_pixels[:, 1]],
                          frame.point_object_ids)


def test_tiny_renderer_matches_egl(box_world):
    sim, scene = box_world
    if not sim.egl_enabled:
        pytest.skip("EGL is not available on this machine")
    egl = _camera(renderer="egl")
    tiny = _camera(renderer="tiny")
    a, b = egl.capture(sim, scene), tiny.capture(sim, scene)
    assert egl.renderer == "egl" and tiny.renderer == "tiny"
    agree = (a.segmentation == b.segmentation).mean()
    assert agree > 0.98
    both = (a.depth > 0) & (b.depth > 0) & (a.segmentation == b.segmentation)
    assert np.median(np.abs(a.depth[both] - b.depth[both])) < 1e-3



@pytest.mark.parametrize("normal_method", ["open3d", "organized"])
def test_normals_at_a_few_points_match_the_full_estimate(box_world, normal_method):
    """``capture(normals=False)`` + ``normals_at`` (what the dataset does) gives ``capture``'s own normals."""
    sim, scene = box_world
    cam = Camera(CameraConfig(width=160, height=120, position=(0.0, 0.0, CAM_Z), depth_noise_std=0.002,
                              normal_method=normal_method))
    full = cam.capture(sim, scene, np.random.default_rng(0))
    bare = cam.capture(sim, scene, np.random.default_rng(0), normals=False)
    assert bare.normals.shape == (0, 3) and np.array_equal(bare.points, full.points)
    idx = np.random.default_rng(1).choice(len(full.points), 300, replace=False)
    tilt = np.degrees(np.arccos(np.clip(full.normals[idx, 2], -1, 1)))
    assert tilt.max() > 5  # depth noise tilts the normals: the comparison below is not of constants
    np.testing.assert_allclose(cam.normals_at(bare, idx), full.normals[idx], atol=1e-5)
    # without the kept float64 cloud the frame's depth is back-projected again, to the same cloud
    assert bare.points64 is not None and bare.points64.dtype == np.float64
    np.testing.assert_array_equal(cam.normals_at(dataclasses.replace(bare, points64=None), idx),
                                  cam.normals_at(bare, idx))
    with pytest.raises(ValueError, match="captures"):
        _camera().normals_at(Camera(CameraConfig(width=80, height=60)).capture(sim, scene, normals=False), idx)


def test_normals_at_one_point_scan_the_cloud_and_agree_with_the_tree_and_open3d(monkeypatch):
    """A few query points scan every distance instead of building a k-d tree: the same neighbours, nearest
    first, so the same normals bit for bit; both agree with Open3D's estimate over the whole cloud."""
    rng = np.random.default_rng(0)
    x, y = np.meshgrid(np.linspace(-0.2, 0.2, 120), np.linspace(-0.15, 0.15, 90))
    points = np.stack([x.ravel(), y.ravel(), 0.1 * np.sin(8 * x.ravel()) + rng.normal(0, 0.002, x.size)], axis=1)
    viewpoint = np.array([0.0, 0.0, 1.5])
    at = rng.choice(len(points), 2, replace=False)
    assert 2 * len(points) <= normals_module.SCAN_PAIRS  # this call scans
    scanned = knn_normals_at(points, at, 30, viewpoint)
    monkeypatch.setattr(normals_module, "SCAN_PAIRS", 0)  # this one builds the tree
    np.testing.assert_array_equal(scanned, knn_normals_at(points, at, 30, viewpoint))
    np.testing.assert_allclose(scanned, open3d_normals(points, 30, viewpoint)[at], atol=1e-6)
    assert np.degrees(np.arccos(np.clip(scanned[:, 2], -1, 1))).max() > 3  # a curved, noisy surface, not a plane
