"""The exposure check on ray-cast depth images of boxes with known answers: one box lying across another's top, a
lone box, and a box beside a wall that the workspace leaves out."""

import numpy as np
import open3d as o3d
import pytest

from policies.base import Candidates, Policy
from policies.exposure import ExposureConfig, bordered_segments, exposed_picks
from policies.heatmap import pixels_to_world
from policies.tool_check import ToolCheckConfig, ToolCheckedPolicy
from rendered_depth import depth_image, straight_down

UP = np.array([0.0, 0.0, 1.0])
BOXES = {  # (min corner, max corner), m; the floor is z = 0
    "under": ((0.00, -0.10, 0.00), (0.20, 0.10, 0.10)),  # 20 x 20 x 10 cm on the floor
    "over": ((0.14, -0.05, 0.10), (0.26, 0.05, 0.15)),  # lies across the under box's right edge, 5 cm thick
    "lone": ((-0.30, -0.05, 0.00), (-0.20, 0.05, 0.08)),
    "by_wall": ((-0.05, 0.20, 0.00), (0.05, 0.28, 0.06)),  # its far side 1 cm from the wall
    "wall": ((-0.40, 0.29, 0.00), (0.40, 0.31, 0.30)),
}
WORKSPACE = np.array([[-0.40, -0.29, 0.0], [0.40, 0.29, 1.0]])  # the bin's inside: the wall is beyond it


@pytest.fixture(scope="module")
def pile():
    scene = o3d.t.geometry.RaycastingScene()
    floor = o3d.geometry.TriangleMesh.create_box(2.0, 2.0, 0.01).translate((-1.0, -1.0, -0.01))
    meshes = [floor] + [o3d.geometry.TriangleMesh.create_box(*np.subtract(hi, lo)).translate(lo)
                        for lo, hi in BOXES.values()]
    for mesh in meshes:
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    K, cam_to_world = straight_down(400.0, 480, 400, (0.0, 0.0, 1.2))
    depth = depth_image(scene, K, cam_to_world, 480, 400)
    rows, cols = np.mgrid[0:400:4, 0:480:4]
    points = pixels_to_world(rows.ravel(), cols.ravel(), depth, K, cam_to_world)
    inside = np.all((points >= WORKSPACE[0]) & (points <= WORKSPACE[1]), axis=1)
    points = points[inside]
    # straight down the camera sees only level faces: every observed normal is up
    obs = {"depth": depth[..., None], "points": points.astype(np.float32),
           "normals": np.tile(UP, (len(points), 1)).astype(np.float32)}
    return obs, {"intrinsics": K, "extrinsics": cam_to_world, "workspace": WORKSPACE}


def _top(name, dx=0.0):
    (x0, y0, _), (x1, y1, z1) = BOXES[name]
    return [(x0 + x1) / 2 + dx, (y0 + y1) / 2, z1]


def test_a_box_under_another_is_bordered_and_the_one_on_top_and_a_lone_box_are_not(pile):
    obs, info = pile
    picks = np.array([_top("under", -0.05), _top("over"), _top("lone"), [0.30, -0.20, 0.0]])
    # the floor's segment has every box rising above it: it is bordered too
    assert exposed_picks(obs, info, picks).tolist() == [False, True, True, False]


def test_the_wall_beyond_the_workspace_does_not_border_the_box_beside_it(pile):
    obs, info = pile
    pick = np.array([_top("by_wall")])
    assert exposed_picks(obs, info, pick).tolist() == [True]
    without_workspace = {k: v for k, v in info.items() if k != "workspace"}
    assert exposed_picks(obs, without_workspace, pick).tolist() == [False]  # the wall rises 24 cm above it


def test_a_rise_within_the_threshold_or_beyond_the_reach_does_not_count(pile):
    obs, info = pile
    pick = np.array([_top("under", -0.05)])
    assert exposed_picks(obs, info, pick, ExposureConfig(rise=0.06)).tolist() == [True]  # the box over it is 5 cm
    assert exposed_picks(obs, info, pick, ExposureConfig(rise=0.04)).tolist() == [False]


def test_a_convex_face_does_not_border_itself_and_single_samples_do_not_count():
    # a ridge: two faces sloping down from x = 0; the tangent plane of each lies above the other
    x = np.linspace(-0.05, 0.05, 41)
    points = np.stack([x, np.zeros_like(x), 0.1 - 0.5 * np.abs(x)], axis=1)
    normals = np.where(x[:, None] < 0, [-0.447, 0.0, 0.894], [0.447, 0.0, 0.894])
    labels = np.zeros(len(x), dtype=np.int64)
    assert bordered_segments(points, normals, labels, points).tolist() == [False]
    spike = np.array([[0.0, 0.0, 0.2]] * 3)  # three samples well above it, fewer than min_samples
    assert bordered_segments(points, normals, labels, np.vstack([points, spike])).tolist() == [False]
    one = spike[:1]  # one sample within reach of 9 of the ridge's points: it counts once, not 9 times
    assert bordered_segments(points, normals, labels, np.vstack([points, one]),
                             ExposureConfig(min_samples=2)).tolist() == [False]
    assert bordered_segments(points, normals, labels, np.vstack([points, one]),
                             ExposureConfig(min_samples=1)).tolist() == [True]
    above = np.array([[0.0, 0.003 * k, 0.2] for k in range(6)])  # six distinct samples within reach
    assert bordered_segments(points, normals, labels, np.vstack([points, above])).tolist() == [True]


class _Ranked(Policy):
    name = "ranked"

    def __init__(self, points, scores):
        self.candidates = Candidates(points=np.float32(points), normals=np.tile(np.float32(UP), (len(points), 1)),
                                     scores=np.float32(scores))

    def predict(self, obs, info=None, top_k=50):
        return self.candidates


def test_the_tool_check_puts_a_covered_pick_behind_an_exposed_one_only_when_asked(pile):
    obs, info = pile
    inner = _Ranked([_top("under", -0.05), _top("lone")], [0.9, 0.6])
    plain = ToolCheckedPolicy(inner, ToolCheckConfig(seal=False)).predict(obs, info)
    np.testing.assert_allclose(plain.points[0], _top("under", -0.05), atol=1e-6)
    first = ToolCheckedPolicy(inner, ToolCheckConfig(seal=False, covered_factor=0.25)).predict(obs, info)
    np.testing.assert_allclose(first.points[0], _top("lone"), atol=1e-6)
    np.testing.assert_allclose(first.scores, [0.6, 0.225], rtol=1e-6)  # 0.9 x 0.25 behind 0.6, still sorted


@pytest.mark.parametrize("bad", [dict(covered_factor=1.5), dict(covered_factor=True), dict(exposure=None)])
def test_bad_exposure_settings_are_refused_naming_the_field(bad):
    with pytest.raises(ValueError, match="ToolCheckConfig"):
        ToolCheckConfig(**bad)
    with pytest.raises(ValueError, match="ExposureConfig: rise"):
        ExposureConfig(rise=-0.01)
    with pytest.raises(ValueError, match="ExposureConfig: wall_margin"):
        ExposureConfig(wall_margin=True)
    with pytest.raises(ValueError, match="ExposureConfig: min_samples"):
        ExposureConfig(min_samples=0)


def test_exposure_needs_the_point_cloud(pile):
    inner = _Ranked([_top("lone")], [1.0])
    inner.obs_mode = "rgbd"
    with pytest.raises(ValueError, match="obs_mode='pointcloud'"):
        ToolCheckedPolicy(inner, ToolCheckConfig(covered_factor=0.5))
