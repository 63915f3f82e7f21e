"""``Simulator.asleep``: the resting pile sleeps through a transport, wakes when struck, and is plain after.

Known answers: a sleeping body does not move at all (Bullet does not integrate it); a body dropped onto a
sleeper moves it; a body moving faster than the sleep tolerance is left awake; and once the block ends a
sleeper whose support is gone falls, and never falls asleep by itself again.
"""

from __future__ import annotations

import numpy as np
import pybullet as pb
import pytest

from parcelpick_env.envs.config import GraspConfig
from parcelpick_env.envs.custom_scene import BoxScene, PlacedBox
from parcelpick_env.scene.config import PileConfig
from parcelpick_env.scene.pile import build_pile
from parcelpick_env.sim.config import SimConfig
from parcelpick_env.sim.simulator import Simulator

BASE = PlacedBox((0.20, 0.20, 0.10), 1.0, center=(0.0, 0.0, 0.05))
STACK = BoxScene([BASE, BASE.resting_on_top((0.15, 0.15, 0.10), 0.5), PlacedBox((0.1, 0.1, 0.1), 0.5, (0.2, 0.1))],
                 settle_steps=480)


@pytest.fixture()
def stack():
    with Simulator(SimConfig(egl_rendering=False)) as sim:
        scene = STACK(sim, 0)
        sim.settle([p.body_id for p in scene.parcels])
        yield sim, [p.body_id for p in scene.parcels]


def _position(sim: Simulator, body: int) -> np.ndarray:
    return np.asarray(pb.getBasePositionAndOrientation(body, physicsClientId=sim.client)[0])


def test_sleepers_do_not_move_and_a_falling_box_wakes_the_one_it_strikes(stack):
    sim, (base, top, side) = stack
    with sim.asleep([base, top, side]) as slept:
        assert sorted(slept) == sorted([base, top, side])
        sim.step(1)  # Bullet applies the deactivation at the end of a step
        before = {b: _position(sim, b) for b in (base, top, side)}
        sim.step(240)
        for b in (base, top, side):  # not integrated at all: bit for bit where they were
            assert np.array_equal(_position(sim, b), before[b])
        col = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[0.05] * 3, physicsClientId=sim.client)
        drop = pb.createMultiBody(3.0, col, basePosition=[0.2, 0.1, 0.35], physicsClientId=sim.client)
        sim.step(120)
        assert _position(sim, drop)[2] > 0.1  # it lands on the sleeper instead of passing through it
        assert np.linalg.norm(_position(sim, side) - before[side]) > 1e-4  # struck: woken, pushed
        assert np.array_equal(_position(sim, base), before[base])  # untouched island: still asleep


def test_a_moving_body_stays_awake(stack):
    sim, (base, top, side) = stack
    pb.resetBaseVelocity(side, [0.2, 0.0, 0.0], physicsClientId=sim.client)  # faster than sleep_linear_velocity
    with sim.asleep([base, top, side]) as slept:
        assert side not in slept and base in slept and top in slept


def test_after_the_block_bodies_are_plain_again(stack):
    sim, (base, top, side) = stack
    with sim.asleep([base, top, side]):
        sim.step(10)
    sim.step(1)  # Bullet applies the wake-up at the next step (as it does the deactivation)
    sim.remove(base)  # the top box loses its support: awake, it falls to the floor
    z0 = _position(sim, top)[2]
    sim.step(240)
    assert _position(sim, top)[2] < z0 - 0.08
    # and it never falls asleep by itself: a drift at 0.5 mm/s, below any sleep threshold (the block's own,
    # or Bullet's, which stopped a body moving at 1 cm/s after 2 s), keeps going; weightless, so that only
    # sleep could stop it
    pb.setGravity(0, 0, 0, physicsClientId=sim.client)
    position, orientation = sim.body_pose(side)
    sim.set_body_pose(side, position + [0.0, 0.0, 0.05], orientation)  # off the floor: nothing touches it
    pb.resetBaseVelocity(side, [0.0, 0.0, 5e-4], physicsClientId=sim.client)
    z0 = _position(sim, side)[2]
    sim.step(4 * 240)
    assert _position(sim, side)[2] - z0 > 1.5e-3  # 4 s at 0.5 mm/s; asleep after 2 s it would be 1 mm


def test_a_stacked_pile_sleeps_through_the_carry_step(library):
    """At the carry's 60 Hz step a resting pile jitters; asleep it stays exactly put (with Bullet's
    wake-up on motion left on, the jitter woke it and it moved 2 mm in 2 s, measured)."""
    with Simulator(SimConfig(egl_rendering=False)) as sim:
        scene = build_pile(sim, PileConfig(num_parcels=6, layout="stacked", object_set="mixed"), 0, library)
        ids = [p.body_id for p in scene.parcels]
        carry = GraspConfig()
        with sim.physics_overrides(timestep=carry.carry_dt, solver_iterations=carry.carry_solver_iterations):
            sim.step(30)
            with sim.asleep(ids) as slept:
                assert sorted(slept) == sorted(ids)
                sim.step(1)
                before = np.array([_position(sim, b) for b in ids])
                sim.step(120)
                assert np.array_equal(np.array([_position(sim, b) for b in ids]), before)


def test_a_sleep_scope_dozes_at_each_call_what_is_still_then_and_wakes_them_all(stack):
    """``sleep_scope``: a body moving at the first doze is left awake, and sleeps at a later doze once it
    is still; on leaving the block both are awake (the base's support removed, the top one falls)."""
    sim, (base, top, side) = stack
    pb.resetBaseVelocity(top, [0.2, 0.0, 0.0], physicsClientId=sim.client)
    with sim.sleep_scope() as doze:
        assert doze([base, top]) == [base]
        pb.resetBaseVelocity(top, [0.0, 0.0, 0.0], physicsClientId=sim.client)
        assert doze([top, side]) == [top, side]
        sim.step(1)
        before = _position(sim, top)
        sim.step(60)
        assert np.array_equal(_position(sim, top), before)
    sim.step(1)
    sim.remove(base)
    z0 = _position(sim, top)[2]
    sim.step(240)
    assert _position(sim, top)[2] < z0 - 0.08
