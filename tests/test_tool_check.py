"""The deployment tool check on a ray-cast depth image of a 30 cm tall box on a floor (known distances)."""

import dataclasses

import numpy as np
import open3d as o3d
import pytest

from parcelpick_env.envs.config import EnvConfig
from parcelpick_env.suction.physical import physical_tool
from policies.base import Candidates, Policy
from parcelpick_env.suction.geometry import build_scene
from policies.tool_check import ToolCheckConfig, ToolCheckedPolicy, check_picks, observed_mesh, tool_clear
from rendered_depth import depth_image, straight_down

BOX_MIN = np.array([0.10, -0.05, 0.0])
BOX_MAX = np.array([0.20, 0.05, 0.30])  # a 10 x 10 x 30 cm box standing on the floor z = 0
UP = np.array([0.0, 0.0, 1.0])


@pytest.fixture(scope="module")
def tall_box():
    floor = o3d.geometry.TriangleMesh.create_box(2.0, 2.0, 0.01).translate((-1.0, -1.0, -0.01))
    box = o3d.geometry.TriangleMesh.create_box(*(BOX_MAX - BOX_MIN)).translate(BOX_MIN)
    scene = o3d.t.geometry.RaycastingScene()
    for mesh in (floor, box):
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    K, cam_to_world = straight_down(280.0, 320, 240, (0.0, 0.0, 1.0))
    depth = depth_image(scene, K, cam_to_world, 320, 240)
    return {"depth": depth[..., None]}, {"intrinsics": K, "extrinsics": cam_to_world}


def test_the_observed_surface_is_where_the_camera_saw_it(tall_box):
    obs, info = tall_box
    surface = build_scene([observed_mesh(obs["depth"][..., 0], info["intrinsics"], info["extrinsics"], stride=3)])
    rays = np.array([[0.15, 0.0, 1.0, 0, 0, -1], [-0.30, 0.10, 1.0, 0, 0, -1]], dtype=np.float32)
    heights = 1.0 - surface.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    np.testing.assert_allclose(heights, [0.30, 0.0], atol=1e-3)


def test_the_physical_tool_is_blocked_beside_a_tall_box_and_clear_away_from_it(tall_box):
    obs, info = tall_box
    tool = physical_tool(EnvConfig().suction)
    # the cup's probe is 32 mm wide (20 mm lip + the planner's clearance), the wrist's 50 mm, from 15.5 cm up
    assert tool.tool_radius == pytest.approx(0.032) and tool.body_radius == pytest.approx(0.05)
    points = np.array([
        [-0.25, 0.0, 0.0],  # the open floor
        [0.08, 0.0, 0.0],  # 2 cm from the box: inside the cup's probe
        [0.06, 0.0, 0.0],  # 4 cm: clear of the cup's probe, inside the wrist's
        [0.02, 0.0, 0.0],  # 8 cm: clear of both
        [0.15, 0.0, 0.30],  # the box's top: nothing above it
    ])
    clear = tool_clear(obs, info, points, np.tile(UP, (len(points), 1)))
    assert clear.tolist() == [True, False, False, True, True]


def test_with_the_seal_on_a_pick_whose_lip_hangs_over_the_box_edge_fails_for_the_cells_cup_only(tall_box):
    obs, info = tall_box
    points = np.array([
        [0.15, 0.0, 0.30],  # the box top's centre: 50 mm from every edge
        [0.13, 0.0, 0.30],  # 30 mm from the edge: the 20 mm lip rests on the top
        [0.115, 0.0, 0.30],  # 15 mm: the cell's 20 mm lip hangs 5 mm over the edge, a 10 mm one does not
        [-0.25, 0.0, 0.0],  # the open floor
    ])
    normals = np.tile(UP, (len(points), 1))
    cell = ToolCheckConfig(seal=True)
    assert cell.suction.cup_radius == pytest.approx(0.020)
    assert check_picks(obs, info, points, normals, cell).tolist() == [True, True, False, True]
    assert tool_clear(obs, info, points, normals, cell).tolist() == [True, True, True, True]  # the seal's verdict
    small = ToolCheckConfig(seal=True, suction=dataclasses.replace(cell.suction, cup_radius=0.010))
    assert check_picks(obs, info, points, normals, small).tolist() == [True, True, True, True]


class _Fixed(Policy):
    """Returns the same ranked candidates every time."""

    name = "fixed"

    def __init__(self, points, scores, obs_mode="pointcloud"):
        self.candidates = Candidates(points=np.float32(points), normals=np.tile(np.float32(UP), (len(points), 1)),
                                     scores=np.float32(scores))
        self.obs_mode = obs_mode

    def predict(self, obs, info=None, top_k=50):
        c = self.candidates
        return Candidates(points=c.points[:top_k], normals=c.normals[:top_k], scores=c.scores[:top_k])


def test_the_wrapped_policy_acts_on_its_best_clear_candidate_and_keeps_the_rest_in_order(tall_box):
    obs, info = tall_box
    inner = _Fixed([[0.08, 0.0, 0.0], [0.06, 0.0, 0.0], [-0.25, 0.0, 0.0], [0.15, 0.0, 0.30]], [0.9, 0.8, 0.7, 0.6])
    policy = ToolCheckedPolicy(inner)
    np.testing.assert_allclose(policy.act(obs, info)[:3], [-0.25, 0.0, 0.0])
    ranked = policy.predict(obs, info, top_k=4)
    np.testing.assert_allclose(ranked.points[:, 0], [-0.25, 0.15, 0.08, 0.06])
    np.testing.assert_allclose(ranked.scores, [0.7, 0.6, 0.0, 0.0])  # a blocked tool scores 0: descending still
    assert policy.last_passed.tolist() == [True, True, False, False]
    # only the first `candidates` are checked: the rest keep their rank and score
    first_only = ToolCheckedPolicy(inner, ToolCheckConfig(candidates=1)).predict(obs, info, top_k=4)
    np.testing.assert_allclose(first_only.scores, [0.8, 0.7, 0.6, 0.0])


def test_with_a_retry_radius_the_cell_does_not_go_back_where_a_pick_just_failed(tall_box):
    obs, info = tall_box
    # the floor at -0.25 passes, and so do the floor 5 cm from it and the box top; 0.08 is blocked by the box
    inner = _Fixed([[-0.25, 0.0, 0.0], [-0.25, 0.04, 0.0], [0.08, 0.0, 0.0], [0.15, 0.0, 0.30]], [0.9, 0.8, 0.7, 0.6])
    policy = ToolCheckedPolicy(inner, ToolCheckConfig(retry_radius=0.05))
    np.testing.assert_allclose(policy.act(obs, info)[:3], [-0.25, 0.0, 0.0])
    dropped = dict(info, attempts=1, outcome="dropped", contacted=True, contact_point=np.array([-0.25, 0.01, 0.0]))
    ranked = policy.predict(obs, dropped, top_k=4)
    np.testing.assert_allclose(ranked.points[0], [0.15, 0.0, 0.30])  # both floor picks are within 5 cm of it
    assert policy.last_retried.tolist() == [False, True, True, False] and policy.last_passed[:3].tolist() == [True] * 3
    assert np.all(np.diff(ranked.scores) <= 0)
    policy.predict(obs, dropped, top_k=4)
    assert len(policy.failed.points) == 1  # one attempt, read once however often its info is seen
    # a failure without contact (never reached) is placed where the check's own first pick was: the box top
    unreached = dict(info, attempts=2, outcome="unreachable", contacted=False, contact_point=np.zeros(3))
    again = policy.predict(obs, unreached, top_k=4)
    np.testing.assert_allclose(policy.failed.points[-1], [0.15, 0.0, 0.30])
    # every passing pick is near a failure now: the cell goes back rather than give up, in the policy's order
    np.testing.assert_allclose(again.points[0], [-0.25, 0.0, 0.0])
    assert not policy.last_retried.any()
    policy.predict(obs, dict(info, attempts=3, outcome="success"), top_k=4)
    assert len(policy.failed.points) == 0  # a success forgets the failures
    policy.predict(obs, unreached, top_k=4)  # an older attempt's info changes nothing
    assert len(policy.failed.points) == 0
    policy.predict(obs, dict(info, attempts=4, outcome="dropped", contacted=True, contact_point=np.zeros(3)))
    policy.reset(0)
    assert len(policy.failed.points) == 0
    by_default = ToolCheckedPolicy(inner)  # the cell's rule is on by default
    by_default.predict(obs, info)
    np.testing.assert_allclose(by_default.predict(obs, dropped, top_k=4).points[0], [0.15, 0.0, 0.30])
    off = ToolCheckedPolicy(inner, ToolCheckConfig(retry_radius=0.0))  # 0 turns it off: the same pick again
    off.predict(obs, info)
    np.testing.assert_allclose(off.predict(obs, dropped, top_k=4).points[0], [-0.25, 0.0, 0.0])
    for bad in (-0.01, float("nan"), True, "5 cm"):
        with pytest.raises(ValueError, match="retry_radius"):
            ToolCheckConfig(retry_radius=bad)


def test_the_tool_check_refuses_a_policy_without_a_depth_image_or_with_its_own_act():
    with pytest.raises(ValueError, match="obs_mode='state_dict'"):
        ToolCheckedPolicy(_Fixed([[0, 0, 0]], [1.0], obs_mode="state_dict"))

    class OwnAct(_Fixed):
        def act(self, obs, info=None):
            return np.zeros(2, dtype=np.float32)

    with pytest.raises(ValueError, match="acts otherwise"):
        ToolCheckedPolicy(OwnAct([[0, 0, 0]], [1.0]))
    with pytest.raises(ValueError, match="stride"):
        ToolCheckConfig(stride=0)
    with pytest.raises(ValueError, match="bellows"):
        ToolCheckConfig(seal=True, suction=dataclasses.replace(EnvConfig().suction, seal_model="spring"))
