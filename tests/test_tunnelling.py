"""Thin parcels do not fall through the floor: the lift's physics step and the slab floor (docs/cell.md, 'Tunnelling'),
nor wedge under a wall: the walls' collision boxes reach down through the slab (results/ORACLE.md, seventeenth session).

Known answers: a 6 mm mailer thrown down onto the bin floor (or the ground outside it) at the lift's step, at up
to 3 m/s (a 45 cm fall), comes to rest lying on it. At the carry's 60 Hz step it does not: it sinks through the
2 cm floor within a step or two, which is how a mailer sliding off a lifted parcel used to leave the scene.
"""

from __future__ import annotations

import numpy as np
import pybullet as pb
import pytest

from parcelpick_env.envs.config import GraspConfig
from parcelpick_env.envs.custom_scene import BoxScene, PlacedBox
from parcelpick_env.scene.scene import BinSpec
from parcelpick_env.sim.config import SimConfig
from parcelpick_env.sim.simulator import Simulator

GRASP = GraspConfig()
MAILER = (0.15, 0.11, 0.006)  # m, 50 g: the thinnest parcels of the library are 4-11 mm


def _thrown(speed: float, dt: float, xy=(0.0, 0.0), floor_z: float = 0.0) -> float:
    """Where a mailer released 10 cm above ``floor_z`` at ``speed`` downward ends after 0.5 s at step ``dt``:
    its centre's height above that surface."""
    with Simulator(SimConfig(egl_rendering=False)) as sim:
        scene = BoxScene([PlacedBox(MAILER, 0.05, center=(*xy, floor_z + 0.1))], settle_steps=1)(sim, 0)
        body = scene.parcels[0].body_id
        pb.resetBaseVelocity(body, [0.0, 0.0, -speed], [0.0, 0.0, 0.0], physicsClientId=sim.client)
        with sim.physics_overrides(timestep=dt, solver_iterations=GRASP.carry_solver_iterations):
            sim.step(int(round(0.5 / dt)))
        return float(sim.body_pose(body)[0][2]) - floor_z


@pytest.mark.parametrize("speed", [0.0, 1.0, 2.0, 3.0])
def test_a_mailer_thrown_onto_the_floor_at_the_lift_step_rests_on_it(speed):
    assert _thrown(speed, GRASP.lift_dt) == pytest.approx(MAILER[2] / 2, abs=2e-3)


def test_outside_the_bin_it_rests_on_the_ground():
    spec = BinSpec()
    outside = (spec.inner_size[0] / 2 + 0.2, 0.0)
    ground = spec.floor_z - spec.wall_thickness  # what BinSpec.contains counts as out
    assert _thrown(2.0, GRASP.lift_dt, outside, ground) == pytest.approx(MAILER[2] / 2, abs=2e-3)


def test_at_the_carry_step_it_would_fall_through():
    """Why the lift has its own step: the same throw at 60 Hz ends below the floor."""
    assert GRASP.carry_dt > GRASP.lift_dt
    assert _thrown(1.0, GRASP.carry_dt) < -0.005


def _envelope_under_the_wall(past: float) -> tuple[float, float, float]:
    """An 80 g envelope, 8 mm thick, laid on the floor with its -y edge ``past`` beyond the -y wall's inner face,
    after 1 s at the lift's step: its edge's y past the face (m, positive: under the wall), its centre's height
    above the floor, and the downward push (N) of the bin on it."""
    spec = BinSpec()
    size, face = (0.2, 0.112, 0.008), -spec.inner_size[1] / 2
    centre = (0.0, face + size[1] / 2 - past, spec.floor_z + size[2] / 2)
    with Simulator(SimConfig(egl_rendering=False)) as sim:
        scene = BoxScene([PlacedBox(size, 0.08, center=centre, friction=0.5)], settle_steps=1)(sim, 0)
        body = scene.parcels[0].body_id
        with sim.physics_overrides(timestep=GRASP.lift_dt, solver_iterations=GRASP.carry_solver_iterations):
            sim.step(int(round(1.0 / GRASP.lift_dt)))
        pos = np.asarray(sim.body_pose(body)[0])
        contacts = pb.getContactPoints(bodyA=body, physicsClientId=sim.client)  # the bin's only: it is alone
        down = sum(c[9] for c in contacts if c[7][2] < -0.5)  # normals on the bin, pointing at the envelope
        return face - (pos[1] - size[1] / 2), float(pos[2] - spec.floor_z), float(down)


@pytest.mark.parametrize("past", [0.002, 0.005, 0.010])
def test_an_envelope_under_a_wall_is_pushed_back_out_onto_the_floor(past):
    """Known answer: nothing presses it down, so it ends lying on the floor with its edge at the wall's face. With
    the walls standing on the floor's top (the seam), the 10 mm case ended 4 mm into the floor under 47 N."""
    under, height, down = _envelope_under_the_wall(past)
    assert under < 1e-3
    assert height == pytest.approx(0.004, abs=1e-3)
    assert down == 0.0
