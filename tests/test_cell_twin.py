"""The oracle's twin of the pick cell (policies/cell_twin.py): the simulator's geometry, and the cell's own verdict."""

from __future__ import annotations

import numpy as np
import pytest

from parcelpick_env.assets.generator import CARTON_SIDE_RANGE, MAX_MASS
from parcelpick_env.assets.library import AssetLibrary
from parcelpick_env.camera.config import CameraConfig
from parcelpick_env.envs.custom_scene import BoxScene, PlacedBox
from parcelpick_env.envs.parcel_pick import ParcelPickEnv
from policies.cell_twin import CellTwin

SMALL = dict(camera=CameraConfig(width=160, height=120), num_points=256, obs_mode="state_dict")
# a carton at the tote's centre, one turned beside it, and a flat one 2.5 cm from the -x wall
PILE = BoxScene([PlacedBox((0.20, 0.15, 0.10), 0.5, (0.0, 0.0)),
                 PlacedBox((0.15, 0.10, 0.06), 0.3, (0.20, 0.0), yaw=0.5),
                 PlacedBox((0.25, 0.20, 0.05), 0.8, (-0.20, 0.10))])


@pytest.fixture(scope="module")
def cell():
    env = ParcelPickEnv(scene_factory=PILE, **SMALL)
    obs, info = env.reset(seed=0)
    twin = CellTwin()
    twin.sync(obs, AssetLibrary.default(int(info["asset_seed"])))
    yield env, obs, twin
    twin.close()
    env.close()


def test_the_twin_collides_the_pile_as_the_simulator_does(cell):
    """Every parcel of the twin has the simulator's collision box to float32 rounding of the observed pose, its
    plan starts from the env's own ready pose, and syncing the same observation again changes nothing."""
    env, obs, twin = cell
    assert twin.scene is not None and len(twin.scene.parcels) == len(env.scene.parcels) == 3
    bodies = [ps.body_id for ps in twin.scene.parcels]
    for ps, body in zip(env.scene.parcels, bodies):
        for theirs, ours in zip(env.sim.aabb(ps.body_id), twin._executor.sim.aabb(body)):
            np.testing.assert_allclose(ours, theirs, atol=1e-5)
    np.testing.assert_allclose(twin._executor.ready_q, env.executor.ready_q, atol=1e-9)
    twin.sync(obs, AssetLibrary.default(0))
    assert [ps.body_id for ps in twin.scene.parcels] == bodies


def test_the_twin_gives_the_cells_own_verdict_before_it_moves(cell):
    """A pick at the top centre of the middle carton is planned, and lifts; a pick on the flat carton's face towards the
    wall, approached from the wall's side, is refused before the arm moves, as the cell itself refuses it (the
    same move, link and condition in the env's info)."""
    env, _, twin = cell
    top = np.array([0.0, 0.0, 0.10])
    arm = twin._executor.arm
    q = arm.q.copy()
    assert twin.refusal(top, np.array([0.0, 0.0, 1.0])) is None
    np.testing.assert_array_equal(arm.q, q)  # planning moves nothing
    assert twin.lifts(top, np.array([0.0, 0.0, 1.0]), 0.5)  # and straight up to 50 cm by the cell's line rule
    assert not twin.lifts(np.array([1.5, 0.0, 0.3]), np.array([0.0, 0.0, 1.0]), 0.5)  # 1.5 m off: no IK at all
    point = np.array([env.scene.parcels[2].world_mesh().bounds[0, 0], 0.10, 0.025])  # its face towards the wall
    normal = np.array([-1.0, 0.0, 0.0])
    refused = twin.refusal(point, normal)
    assert refused is not None and refused.move in ("hover", "descend", "approach")
    _, _, _, _, info = env.step(np.concatenate([point, normal]).astype(np.float32))
    assert info["outcome"] == "unreachable"
    failure = info["failure"]
    assert (failure["move"], failure["link"], failure["condition"]) == (refused.move, refused.link, refused.condition)


def test_a_rehearsal_on_the_twin_ends_as_the_cells_attempt_and_leaves_the_twin_as_synced():
    """The heaviest carton the cell allows, 40 x 30 cm on top: picked 15 cm off its centre, the twin's rehearsal
    drops it on the material condition in the lift, as the env's attempt does; picked at its centre, both carry it
    off. After each rehearsal the twin stands as the observation has it (the carried parcel back in place)."""
    heavy = BoxScene([PlacedBox((0.40, 0.30, CARTON_SIDE_RANGE[1]), MAX_MASS, (0.05, 0.0), friction=0.8)])
    env = ParcelPickEnv(scene_factory=heavy, **SMALL)
    twin = CellTwin()
    try:
        obs, info = env.reset(seed=0)
        twin.sync(obs, AssetLibrary.default(int(info["asset_seed"])))
        sim = twin._executor.sim
        box = sim.aabb(twin.scene.parcels[0].body_id)
        top = np.array([0.05, 0.0, CARTON_SIDE_RANGE[1]])
        up = np.array([0.0, 0.0, 1.0])
        off = twin.rehearse(top + [0.15, 0.0, 0.0], up)
        assert (off.outcome, off.failure.move) == ("dropped", "lift") and off.failure.condition.startswith("material")
        centre = twin.rehearse(top, up)
        assert centre.outcome == "success"
        assert len(twin.scene.parcels) == 1
        for ours, before in zip(sim.aabb(twin.scene.parcels[0].body_id), box):
            np.testing.assert_allclose(ours, before, atol=1e-9)
        np.testing.assert_allclose(twin._executor.arm.q, twin._executor.home_q, atol=1e-9)
        _, _, _, _, info = env.step(np.concatenate([top + [0.15, 0.0, 0.0], up]).astype(np.float32))
        assert (info["outcome"], info["failure"]["move"], info["failure"]["condition"][:8]) == (
            "dropped", "lift", "material")
    finally:
        twin.close()
        env.close()


def test_a_jittered_rehearsal_moves_every_parcel_by_about_the_asked_error_and_the_twin_is_synced_again_after(cell):
    """``PoseJitter`` moves each parcel by a fresh draw (positions off by about ``position`` per axis, turned by about
    ``angle_deg``), reproducibly from its generator; after a jittered rehearsal the twin stands as synced."""
    from scipy.spatial.transform import Rotation

    from policies.cell_twin import PoseJitter

    _, _, twin = cell
    sim = twin._executor.sim
    before = [sim.body_pose(ps.body_id) for ps in twin.scene.parcels]
    moved = []
    for _ in range(2):
        PoseJitter(np.random.default_rng(3), 0.002, 1.0).apply(sim, twin.scene)
        moved.append([sim.body_pose(ps.body_id) for ps in twin.scene.parcels])
        for ps, (pos, orn) in zip(twin.scene.parcels, before):  # back as synced
            ps.position, ps.orientation = pos, orn
            sim.set_body_pose(ps.body_id, pos, orn)
    for (p0, q0), (p1, q1), (p2, q2) in zip(before, *moved):
        np.testing.assert_allclose(p1, p2, atol=1e-12)  # the same generator state, the same draw
        shift = np.linalg.norm(p1 - p0)
        turn = np.degrees((Rotation.from_quat(q1) * Rotation.from_quat(q0).inv()).magnitude())
        assert 1e-4 < shift < 0.012 and 0.02 < turn < 6.0
    twin.rehearse(np.array([0.0, 0.0, 0.10]), np.array([0.0, 0.0, 1.0]),
                  PoseJitter(np.random.default_rng(4), 0.002, 1.0))
    for ps, (pos, orn) in zip(twin.scene.parcels, before):
        now = sim.body_pose(ps.body_id)
        np.testing.assert_allclose(now[0], pos, atol=1e-9)
        np.testing.assert_allclose(np.abs(now[1] @ orn), 1.0, atol=1e-9)


def test_the_twin_refuses_to_answer_before_it_is_synced():
    for ask in (lambda twin: twin.refusal(np.zeros(3), np.array([0.0, 0.0, 1.0])),
                lambda twin: twin.lifts(np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.5),
                lambda twin: twin.rehearse(np.zeros(3), np.array([0.0, 0.0, 1.0]))):
        with pytest.raises(RuntimeError, match="before sync"):
            ask(CellTwin())
