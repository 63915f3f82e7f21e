"""Normal-STD and random baselines on an analytically ray-cast box-on-a-floor depth image."""

import numpy as np
import open3d as o3d
import pytest

from parcelpick_env.scene.scene import BinSpec
from policies.normal_std import NormalStdConfig, NormalStdPolicy
from policies.random_policy import RandomPolicy
from rendered_depth import depth_image, straight_down

BOX_MIN = np.array([-0.05, -0.05, 0.0])
BOX_MAX = np.array([0.25, 0.15, 0.10])  # a 30 x 20 x 10 cm box on the floor z = 0


def _render_box_scene(width: int = 320, height: int = 240, focal: float = 280.0):
    """Depth image of the box and floor from a camera 1 m up, off to the side so two box sides show."""
    floor = o3d.geometry.TriangleMesh.create_box(2.0, 2.0, 0.01).translate((-1.0, -1.0, -0.01))
    box = o3d.geometry.TriangleMesh.create_box(*(BOX_MAX - BOX_MIN)).translate(BOX_MIN)
    scene = o3d.t.geometry.RaycastingScene()
    for mesh in (floor, box):
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    K, cam_to_world = straight_down(focal, width, height, (-0.3, -0.2, 1.0))
    depth = depth_image(scene, K, cam_to_world, width, height)
    # The cloud the env would observe: every valid pixel, normals pointing up (enough for the random policy).
    u, v = np.meshgrid(np.arange(width), np.arange(height))
    cam = np.stack([(u - K[0, 2]) * depth / focal, (v - K[1, 2]) * depth / focal, depth], -1)[depth > 0]
    points = (cam @ cam_to_world[:3, :3].T + cam_to_world[:3, 3]).astype(np.float32)
    normals = np.tile(np.float32([0, 0, 1]), (len(points), 1))
    obs = {"depth": depth[..., None], "points": points, "normals": normals,
           "rgb": np.zeros((height, width, 3), np.uint8)}
    return obs, {"intrinsics": K, "extrinsics": cam_to_world}


@pytest.fixture(scope="module")
def box_scene():
    return _render_box_scene()


def _heat_near(fmap, xyz):
    dist = np.linalg.norm(fmap.points - np.asarray(xyz), axis=-1)
    dist[~fmap.valid] = np.inf
    pixel = np.unravel_index(np.argmin(dist), dist.shape)
    assert dist[pixel] < 0.01, "test point not observed"
    return fmap.heat[pixel]


def test_flat_box_centre_beats_box_edge(box_scene):
    obs, info = box_scene
    fmap = NormalStdPolicy().flatness(obs, info)
    centre = _heat_near(fmap, [0.10, 0.05, 0.10])
    # Edges next to the two sides the camera sees (x = -0.05 and y = -0.05).
    edges = [_heat_near(fmap, [-0.045, 0.05, 0.10]), _heat_near(fmap, [0.10, -0.045, 0.10])]
    assert centre > 0.95
    assert max(edges) < 0.5 * centre


def _assert_valid_candidates(cands, obs, top_k):
    assert 0 < len(cands) <= top_k
    assert cands.points.shape == (len(cands), 3) and cands.normals.shape == (len(cands), 3)
    assert np.all(np.diff(cands.scores) <= 0)
    np.testing.assert_allclose(np.linalg.norm(cands.normals, axis=1), 1.0, atol=1e-5)
    lo, hi = obs["points"].min(0) - 1e-4, obs["points"].max(0) + 1e-4
    assert np.all((cands.points >= lo) & (cands.points <= hi))
    action = cands.best_action()
    assert action.shape == (6,) and action.dtype == np.float32 and np.all(np.isfinite(action))


def test_normal_std_candidates_are_valid_and_avoid_visible_edges(box_scene):
    obs, info = box_scene
    policy = NormalStdPolicy()
    cands = policy.predict(obs, info, top_k=30)
    _assert_valid_candidates(cands, obs, 30)
    assert np.all(cands.normals[:, 2] > 0.9)  # every flat region here faces up
    # No top candidate sits within 1 cm of the two box edges that have a visible side below them.
    on_top = cands.points[:, 2] > 0.09
    near_edge = on_top & ((cands.points[:, 0] < BOX_MIN[0] + 0.01) | (cands.points[:, 1] < BOX_MIN[1] + 0.01))
    assert not near_edge.any()
    # Candidates survive NMS at 2 cm.
    d = np.linalg.norm(cands.points[:, None] - cands.points[None], axis=-1) + np.eye(len(cands))
    assert d.min() >= 0.02 - 1e-6
    assert policy.act(obs, info).shape == (6,)


def test_random_policy_valid_and_seeded(box_scene):
    obs, info = box_scene
    policy = RandomPolicy(seed=3)
    first = policy.predict(obs, info, top_k=40)
    _assert_valid_candidates(first, obs, 40)
    policy.reset(seed=3)
    again = policy.predict(obs, info, top_k=40)
    np.testing.assert_array_equal(first.points, again.points)
    other = RandomPolicy(seed=4).predict(obs, info, top_k=40)
    assert not np.array_equal(first.points, other.points)
    assert len(RandomPolicy().predict({"points": obs["points"][:5], "normals": obs["normals"][:5]}, top_k=50)) == 5


@pytest.mark.parametrize("breakage", ["nan_depth", "empty_depth", "no_info", "bad_shape"])
def test_normal_std_rejects_bad_observations(box_scene, breakage):
    obs, info = dict(box_scene[0]), box_scene[1]
    if breakage == "nan_depth":
        obs["depth"] = obs["depth"].copy()
        obs["depth"][5, 5] = np.nan
    elif breakage == "empty_depth":
        obs["depth"] = np.zeros_like(obs["depth"])
    elif breakage == "no_info":
        info = None
    else:
        obs["depth"] = obs["depth"][..., 0][None]
    with pytest.raises(ValueError):
        NormalStdPolicy().predict(obs, info)


def test_random_policy_rejects_bad_observations():
    with pytest.raises(ValueError):
        RandomPolicy().predict({"points": np.full((4, 3), np.nan), "normals": np.ones((4, 3))})
    with pytest.raises(ValueError):
        RandomPolicy().predict({"points": np.zeros((4, 2)), "normals": np.ones((4, 2))})


def test_config_validation():
    with pytest.raises(ValueError):
        NormalStdConfig(cell=0)
    with pytest.raises(ValueError):
        NormalStdConfig(nms_radius=-1.0)
    with pytest.raises(ValueError):
        NormalStdConfig(workspace=((0, 0, 0), (1, -1, 1)))
    assert NormalStdConfig(downsample=2).effective_knn == 56  # KNN 224 over the same surface patch
    # the bin's inner floor up to 1 m (piles may top the rim): the env's info['workspace']
    spec = BinSpec(inner_size=(0.70, 0.50))
    np.testing.assert_allclose(NormalStdConfig.for_bin(spec).workspace, ((-0.35, -0.25, 0.0), (0.35, 0.25, 1.0)))
    with pytest.raises(ValueError):
        NormalStdConfig(floor_clearance=-0.001)


def test_normal_std_stays_inside_the_observed_workspace(box_scene):
    """The env crops the cloud to the bin; the flat floor outside it must not attract candidates."""
    obs, info = box_scene
    cropped = dict(obs)
    inside = np.all(np.abs(obs["points"][:, :2] - [0.1, 0.05]) < [0.25, 0.2], axis=1)
    cropped["points"], cropped["normals"] = obs["points"][inside], obs["normals"][inside]
    cands = NormalStdPolicy().predict(cropped, info, top_k=50)
    lo, hi = cropped["points"].min(0) - 1e-6, cropped["points"].max(0) + 1e-6
    assert len(cands) > 5 and np.all((cands.points >= lo) & (cands.points <= hi))
    box = ((-0.1, -0.1, 0.05), (0.3, 0.2, 0.2))  # the upper half of the box: its top and two visible sides
    on_box = NormalStdPolicy(NormalStdConfig(workspace=box)).predict(obs, info, top_k=50)
    assert len(on_box) > 3 and np.all((on_box.points >= np.array(box[0])) & (on_box.points <= np.array(box[1])))


BIN = BinSpec(inner_size=(0.40, 0.30), wall_height=0.20)
BALL_CENTRE, BALL_RADIUS = np.array([0.05, 0.0, 0.05]), 0.05


def _render_bin_scene(width: int = 320, height: int = 240, focal: float = 200.0):
    """Depth image of ``BIN`` (floor and walls, ``BinSpec.meshes``) holding one ball, from a camera 0.7 m above
    its centre looking straight down, with the env's ``info['workspace']``. Nothing on the ball is flat, so the
    bin's inner walls are the flattest surfaces in view once the floor is masked, as in the env's cell."""
    import trimesh

    ball = trimesh.creation.icosphere(subdivisions=4, radius=BALL_RADIUS)
    ball.apply_translation(BALL_CENTRE)
    scene = o3d.t.geometry.RaycastingScene()
    for mesh in BIN.meshes() + [ball]:
        scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                            o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    K, cam_to_world = straight_down(focal, width, height, (0.0, 0.0, 0.7))
    depth = depth_image(scene, K, cam_to_world, width, height)
    return {"depth": depth}, {"intrinsics": K, "extrinsics": cam_to_world, "workspace": BIN.workspace()}


def _wall_gap(points: np.ndarray) -> np.ndarray:
    """Horizontal distance from each point to the nearest inner wall of ``BIN``."""
    half = np.asarray(BIN.inner_size) / 2
    return np.min(half - np.abs(points[:, :2] - np.asarray(BIN.center_xy)), axis=1)


def test_normal_std_never_picks_the_bin_walls():
    """The bin's inner walls are flat and in view; a cup sent along their horizontal normal strikes them
    (closed loop: every pick went there). ``wall_clearance`` masks them as ``floor_clearance`` masks the floor."""
    obs, info = _render_bin_scene()
    unmasked = NormalStdPolicy(NormalStdConfig(wall_clearance=0.0)).predict(obs, info, top_k=20)
    assert _wall_gap(unmasked.points[:1])[0] < 0.005  # the scene tests something: unmasked, the best pick is a wall
    cfg = NormalStdConfig()
    cands = NormalStdPolicy(cfg).predict(obs, info, top_k=20)
    assert len(cands) > 0 and np.all(_wall_gap(cands.points) >= cfg.wall_clearance - 1e-9)
    assert np.linalg.norm(cands.best_action()[:3] - BALL_CENTRE) < BALL_RADIUS + 0.005  # the ball, all that is left
    with pytest.raises(ValueError, match="wall_clearance"):
        NormalStdConfig(wall_clearance=-0.001)
    with pytest.raises(ValueError, match="wall_clearance"):  # wider than half the bin: nothing left to pick
        NormalStdPolicy(NormalStdConfig(wall_clearance=0.2)).predict(obs, info)
