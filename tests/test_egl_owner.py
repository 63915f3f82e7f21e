"""One EGL owner per process: no simulator or env closing, opening or resetting blanks another's camera.

pybullet's EGL plugin terminates the process-wide EGL display when any EGL client disconnects; before
``sim/egl.py`` the other live env then rendered 99.7 % of its depth pixels at the near plane.
"""

from __future__ import annotations

import numpy as np
import pytest

from parcelpick_env.camera.camera import Camera
from parcelpick_env.camera.config import CameraConfig
from parcelpick_env.envs.custom_scene import BoxScene, PlacedBox
from parcelpick_env.envs.parcel_pick import ParcelPickEnv
from parcelpick_env.sim.egl import EGL_OWNER
from parcelpick_env.sim.simulator import Simulator

ENV = dict(num_parcels=3, layout="scattered", object_set="rectangular", num_points=256,
           camera=CameraConfig(width=160, height=120))
CAMERA = CameraConfig(width=160, height=120, depth_noise_std=0.0)
SEED = 5


def _depth(env: ParcelPickEnv) -> np.ndarray:
    return env.reset(seed=SEED)[0]["depth"][..., 0]


def _assert_sane(depth: np.ndarray) -> None:
    """Not the blank render: most pixels see the bin, none sits at the near plane."""
    valid = depth > 0
    assert valid.mean() > 0.9
    assert depth[valid].min() > 2 * ENV["camera"].near


def test_closing_one_env_leaves_the_other_rendering_as_a_fresh_env():
    first, second = ParcelPickEnv(**ENV), ParcelPickEnv(**ENV)
    try:
        before = _depth(second)
        _depth(first)
        first.close()
        after = _depth(second)  # the case: rendered after the other env closed
    finally:
        first.close()
        second.close()
    fresh = ParcelPickEnv(**ENV)
    try:
        reference = _depth(fresh)
    finally:
        fresh.close()
    _assert_sane(after)
    np.testing.assert_array_equal(after, reference)
    np.testing.assert_array_equal(before, reference)


def _box_world(sim: Simulator, k: int):
    """A different known box per ``k``, so every simulator's image is its own."""
    return BoxScene([PlacedBox((0.10 + 0.05 * k, 0.20, 0.08), 0.5, (0.05 * k - 0.1, 0.0))])(sim, k)


def test_any_order_of_creating_resetting_and_closing_simulators_keeps_every_camera():
    """Each simulator's image is rendered once, then re-rendered, without rebuilding its world, after the
    others were built, rendered, reset, closed and replaced: it must not change (it did before, as every
    client's GL calls landed in the newest EGL context)."""
    camera = Camera(CAMERA)
    sims = {k: Simulator() for k in range(3)}
    scenes, expected = {}, {}
    try:
        for k, sim in sims.items():
            scenes[k] = _box_world(sim, k)
            expected[k] = camera.capture(sim, scenes[k])
        sims.pop(1).close()
        sims[3] = Simulator()  # reuses the closed one's client
        scenes[3] = _box_world(sims[3], 3)
        expected[3] = camera.capture(sims[3], scenes[3])
        _box_world(sims[0], 1)  # reset and rebuilt with another box, then closed
        sims.pop(0).close()
        assert len({s.client for s in sims.values()}) == len(sims)
        for k in (2, 3, 2):
            got = camera.capture(sims[k], scenes[k])
            np.testing.assert_array_equal(got.depth, expected[k].depth, err_msg=f"simulator {k}")
            np.testing.assert_array_equal(got.rgb, expected[k].rgb, err_msg=f"simulator {k}")
        assert not np.array_equal(expected[2].depth, expected[3].depth)
        with Simulator() as fresh:  # and a fresh simulator sees what the long-lived one does
            np.testing.assert_array_equal(camera.capture(fresh, _box_world(fresh, 2)).depth, expected[2].depth)
    finally:
        for sim in sims.values():
            sim.close()


def test_closed_or_stale_simulators_fail_clearly():
    camera = Camera(CAMERA)
    sim = Simulator()
    scene = _box_world(sim, 0)
    if sim.egl_enabled:
        EGL_OWNER.release(sim.client)  # a client taken away behind the simulator's back
        assert not sim.egl_current
        with pytest.raises(RuntimeError, match="EGL renderer is no longer valid"):
            camera.capture(sim, scene)
        sim._client = None  # already handed back: nothing left to release
    sim.close()
    with pytest.raises(RuntimeError, match="closed Simulator"):
        camera.capture(sim, scene)
    with pytest.raises(RuntimeError, match="Simulator is closed"):
        _ = sim.client


def test_constructing_an_env_starts_no_renderer():
    """gymnasium's AsyncVectorEnv builds and closes one env in the parent before forking its workers."""
    env = ParcelPickEnv(**ENV)
    live, idle = EGL_OWNER.num_clients
    env.close()
    assert env.sim._client is None
    assert EGL_OWNER.num_clients == (live, idle)
