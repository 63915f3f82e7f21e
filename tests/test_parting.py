"""The oracle's parting pushes (policies/parting.py, CellTwin.rehearse_push, OraclePolicy(parting_pushes=True)):
where the pushes start, the twin's push against the env's, and a push taken only where no pick holds."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from parcelpick_env.assets.library import AssetLibrary
from parcelpick_env.camera.config import CameraConfig
from parcelpick_env.envs.custom_scene import BoxScene, PlacedBox
from parcelpick_env.envs.parcel_pick import ParcelPickEnv
from policies.cell_twin import CellTwin
from policies.oracle import GroundTruth, OraclePolicy, ground_truth, pinned_parcels
from policies.parting import ABOVE_BOTTOM, BELOW_TOP, SIDE_GAP, column_clear, push_candidates, push_frame

SMALL = dict(camera=CameraConfig(width=160, height=120), num_points=256, obs_mode="state_dict")
# a flat carton on the floor with a smaller one lying on it, and a tall one beside them
PILE = BoxScene([PlacedBox((0.24, 0.18, 0.06), 0.6, (-0.05, 0.0)),
                 PlacedBox((0.12, 0.10, 0.05), 0.3, (-0.05, 0.0), z=0.06),
                 PlacedBox((0.10, 0.10, 0.16), 0.4, (0.20, 0.05))])
CUP_RADIUS = 0.02


@pytest.fixture(scope="module")
def cell():
    env = ParcelPickEnv(scene_factory=PILE, action_mode="pose_push", **SMALL)
    obs, info = env.reset(seed=0)
    library = AssetLibrary.default(int(info["asset_seed"]))
    twin = CellTwin()
    twin.sync(obs, library)
    yield env, obs, library, twin
    twin.close()
    env.close()


def test_pushes_start_beside_the_free_parcels_first_the_highest_first(cell):
    _, obs, library, _ = cell
    truth = ground_truth(obs, library)
    pinned = pinned_parcels(truth)
    assert pinned.tolist() == [True, False, False]  # the small carton lies on the flat one
    pushes = push_candidates(truth, pinned, CUP_RADIUS, limit=12)
    # by the centre of mass: the small carton's (8.5 cm up) above the tall one's (8 cm); the pinned one last
    assert len(pushes) == 12 and [p.parcel for p in pushes] == [1] * 4 + [2] * 4 + [0] * 4
    for p, axis in zip(pushes, [[1, 0], [-1, 0], [0, 1], [0, -1]] * 3):  # level cartons: along x, then y
        lo, hi = truth.meshes[p.parcel].bounds
        d = p.direction
        assert abs(np.linalg.norm(d) - 1) < 1e-12 and d[2] == 0 and d[:2] @ axis > 0.999
        # the cup's side stands SIDE_GAP off the box's face it pushes, at its height band
        face = np.where(d > 0, lo, hi)  # the face the push meets first
        assert float((face - p.start)[:2] @ d[:2]) == pytest.approx(CUP_RADIUS + SIDE_GAP, abs=1e-4)
        centre = (lo + hi) / 2  # and the push goes through the box's centre line
        v = (centre - p.start)[:2]
        assert float(d[0] * v[1] - d[1] * v[0]) == pytest.approx(0.0, abs=1e-4)
        assert p.start[2] == pytest.approx(max(lo[2] + ABOVE_BOTTOM, hi[2] - BELOW_TOP))
    assert len(push_candidates(truth, pinned, CUP_RADIUS, limit=5)) == 5
    # with the env's action box, a start beyond it is left out: the tall carton's push from its +x side starts
    # the tall carton pushed from its +x side starts at x = 0.28, past a box cut at x = 0.26
    lo, hi = np.array([-0.4, -0.3, -0.05]), np.array([0.26, 0.3, 1.0])
    boxed = push_candidates(truth, pinned, CUP_RADIUS, limit=12, bounds=(lo, hi))
    assert len(boxed) == 11 and all(np.all(p.start >= lo) and np.all(p.start <= hi) for p in boxed)


def _truth(meshes: list[trimesh.Trimesh]) -> GroundTruth:
    return GroundTruth(meshes=meshes, coms=np.array([m.center_mass for m in meshes]), masses=np.ones(len(meshes)),
                       obstacles=[], bin_centre=np.zeros(2))


def test_a_tilted_parcel_is_pushed_along_its_own_axes_from_beside_its_body():
    """A 30 x 8 x 8 cm tube-like carton, its long axis 30 deg off x and tipped 40 deg up: its world bounding box
    stands up to 5 cm off its body at the push height, so a push from beside the box would come down on air. The
    push runs along the carton's own horizontal axis, and the cup's side stands SIDE_GAP off its outline there."""
    carton = trimesh.creation.box(extents=(0.30, 0.08, 0.08))
    carton.apply_transform(trimesh.transformations.rotation_matrix(np.radians(-40), [0, 1, 0]))
    carton.apply_transform(trimesh.transformations.rotation_matrix(np.radians(30), [0, 0, 1]))
    carton.apply_translation([0.0, 0.0, 0.2])
    long_axis = np.array([np.cos(np.radians(30)), np.sin(np.radians(30))])
    pushes = push_candidates(_truth([carton]), np.array([False]), CUP_RADIUS, limit=4)
    assert len(pushes) == 4
    assert abs(pushes[0].direction[:2] @ long_axis) > 0.999 and abs(pushes[2].direction[:2] @ long_axis) < 0.02
    for p in pushes:
        outline = carton.section(plane_origin=p.start, plane_normal=[0, 0, 1]).vertices
        assert float(((outline - p.start)[:, :2] @ p.direction[:2]).min()) == pytest.approx(CUP_RADIUS + SIDE_GAP)
    lo, _ = carton.bounds
    assert pushes[0].start[0] > lo[0] + 0.04  # along +x it starts well inside the world box's -x face
    # and ``push_frame`` gives that outline's rectangle, its first axis the one nearer x, signed to +x
    centre, axes, half, z = push_frame(carton)
    assert axes[0] @ long_axis > 0.999 and z == pytest.approx(carton.bounds[1, 2] - BELOW_TOP)
    outline = (carton.section(plane_origin=[0, 0, z], plane_normal=[0, 0, 1]).vertices[:, :2] - centre) @ axes.T
    np.testing.assert_allclose(outline.max(axis=0), half, atol=1e-9)
    np.testing.assert_allclose(outline.min(axis=0), -half, atol=1e-9)


def test_a_push_whose_cup_would_come_down_on_another_parcel_is_left_out():
    """A flat carton with a wide one bridging over its -x side: the push along +x would start under the bridge,
    so it is not offered; the other three are, and ``column_clear`` says why."""
    flat = trimesh.creation.box(extents=(0.20, 0.20, 0.05))
    flat.apply_translation([0.0, 0.0, 0.025])
    bridge = trimesh.creation.box(extents=(0.10, 0.30, 0.02))
    bridge.apply_translation([-0.14, 0.0, 0.12])  # over the cup's way down beside the flat carton's -x face
    truth = _truth([flat, bridge])
    pushes = [p for p in push_candidates(truth, np.array([False, True]), CUP_RADIUS, limit=8) if p.parcel == 0]
    assert [tuple(np.round(p.direction[:2])) for p in pushes] == [(-1, 0), (0, 1), (0, -1)]
    start = np.array([[-0.10 - CUP_RADIUS - SIDE_GAP, 0.0, 0.02], [0.10 + CUP_RADIUS + SIDE_GAP, 0.0, 0.02]])
    assert column_clear(truth, start, CUP_RADIUS).tolist() == [False, True]


def test_the_twins_push_leaves_the_pile_the_envs_push_leaves(cell):
    """The tall carton pushed 10 cm along +x on the twin and in the env ends in the same place (to a millimetre),
    the twin's state after it says so, and the twin is posed again as synced."""
    env, obs, library, twin = cell
    truth = ground_truth(obs, library)
    push = next(p for p in push_candidates(truth, pinned_parcels(truth), CUP_RADIUS, 12)
                if p.parcel == 2 and p.direction[0] > 0)
    result, after = twin.rehearse_push(push.start, push.direction)
    assert result.outcome == "pushed" and after is not None
    before = obs["parcel_position"][2].astype(np.float64)
    moved_twin = after["parcel_position"][2] - before
    assert 0.07 < moved_twin[0] < 0.11 and abs(moved_twin[1]) < 0.01
    np.testing.assert_allclose(after["parcel_position"][:2], obs["parcel_position"][:2], atol=2e-3)  # the others stay
    body = twin.scene.parcels[2].body_id
    np.testing.assert_allclose(twin._executor.sim.body_pose(body)[0], before, atol=1e-5)  # posed again as synced
    _, _, _, _, info = env.step(np.concatenate([push.start, push.direction, [-1.0]]).astype(np.float32))
    assert info["outcome"] == "pushed"
    np.testing.assert_allclose(env.sim.body_pose(env.scene.parcels[2].body_id)[0], after["parcel_position"][2],
                               atol=1e-3)


def test_the_oracle_pushes_only_where_no_pick_holds():
    """On a pile where a pick holds the oracle picks (the seventh number >= 0) and rehearses no push; with its
    rehearsals all failed (as at a dead end), or its pick fragile (held as synced, not on every jittered twin), it
    rehearses pushes on the twin and acts on one only if a pick holds after it."""
    env = ParcelPickEnv(scene_factory=PILE, action_mode="pose_push", **SMALL)
    oracle = OraclePolicy(parting_pushes=True)
    try:
        obs, info = env.reset(seed=0)
        action = oracle.act(obs, info)
        assert action.shape == (7,) and action[6] >= 0 and oracle.last_push_rehearsals == []
        assert "success" in oracle.last_rehearsals
        oracle.last_rehearsals = ["dropped"]  # as if every rehearsal of this decision had failed
        pushed = oracle._parting_push(obs, info)
        assert oracle.last_push_rehearsals  # pushes were rehearsed
        assert pushed is not None and pushed.shape == (7,) and pushed[6] < 0
        assert "success" in oracle.last_rehearsals  # a pick held on the pile the push left
        oracle.last_rehearsals, oracle.last_fragile = ["success"], True  # held as synced, not on jittered twins
        assert oracle._parting_push(obs, info) is not None and oracle.last_push_rehearsals  # as at a dead end
        oracle.last_rehearsals, oracle.last_fragile = ["success"], False
        assert oracle._parting_push(obs, info) is None and oracle.last_push_rehearsals == []
        oracle.last_rehearsals = ["dropped"]
        assert oracle._parting_push(obs, {**info, "pushes_left": 0}) is None  # none left: the pick stands
        assert oracle.last_push_rehearsals == []
        assert oracle.action_mode == OraclePolicy().action_mode == "pose_push"  # pushes are the default
        assert OraclePolicy(parting_pushes=False).action_mode == "pose"
    finally:
        oracle.twin.close()
        env.close()
    with pytest.raises(ValueError, match="parting_pushes"):
        OraclePolicy(parting_pushes="yes")
