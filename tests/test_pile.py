"""Simulator and pile building: mesh-frame poses, determinism, split hygiene, validation, rest, layouts,
what a request keeps, the one definition of inside the bin, and the arm's reach over the tote."""

from __future__ import annotations

import logging

import numpy as np
import pybullet as pb
import pytest
import shapely
from scipy.spatial.transform import Rotation

from parcelpick_env.assets.library import OBJECT_SETS
from parcelpick_env.robot.arm import ArmConfig, Gen3Arm, reachability
from parcelpick_env.scene.config import PileConfig
from parcelpick_env.scene import pile
from parcelpick_env.scene.pile import SCATTER_CAPACITY, STACKED_FILL_CAPACITY, build_pile, refresh_scene_poses
from parcelpick_env.scene.scene import BinSpec
from parcelpick_env.sim.config import SimConfig
from parcelpick_env.sim.simulator import Simulator

TINY = dict(num_parcels=4, object_set="mixed")


@pytest.fixture(scope="module")
def sim():
    with Simulator() as s:
        yield s


def _poses(scene):
    return (np.array([p.position for p in scene.parcels]), np.array([p.orientation for p in scene.parcels]))


def test_body_pose_is_the_mesh_frame_not_the_com_frame(sim, library):
    sim.reset()
    asset = max(library.train, key=lambda a: np.linalg.norm(a.com))  # the most off-centre COM
    assert np.linalg.norm(asset.com) > 1e-3
    q = Rotation.from_euler("xyz", [0.3, -0.2, 1.0]).as_quat()
    body = sim.add_parcel(asset, [0.1, -0.05, 0.5], q, friction=0.5)
    pos, orn = sim.body_pose(body)
    np.testing.assert_allclose(pos, [0.1, -0.05, 0.5], atol=1e-9)
    np.testing.assert_allclose(np.abs(orn @ q), 1.0, atol=1e-9)
    com_pos, _ = pb.getBasePositionAndOrientation(body, physicsClientId=sim.client)
    np.testing.assert_allclose(com_pos, Rotation.from_quat(q).apply(asset.com) + [0.1, -0.05, 0.5], atol=1e-9)
    sim.set_body_pose(body, [0.0, 0.0, 1.0], [0, 0, 0, 1])
    np.testing.assert_allclose(sim.body_pose(body)[0], [0.0, 0.0, 1.0], atol=1e-9)
    mass = pb.getDynamicsInfo(body, -1, physicsClientId=sim.client)[0]
    assert mass == pytest.approx(asset.mass)


def test_settle_stops_when_motion_stops(sim, library):
    sim.reset()
    sim.add_bin(BinSpec())
    asset = library.assets("train", "rectangular")[0]
    body = sim.add_parcel(asset, [0, 0, asset.extents[2] / 2 + 0.05], [0, 0, 0, 1], friction=0.6)
    window = sim.rest_steps()
    steps = sim.settle([body])
    assert window < steps < sim.config.max_settle_steps  # it fell 5 cm first: more than one window
    before = sim.com_poses([body])
    sim.step(window)
    assert sim.still(before, sim.com_poses([body]), window * sim.config.timestep).all()
    assert sim.settle([body]) == window  # already at rest: one window shows it
    lowest = (Rotation.from_quat(sim.body_pose(body)[1]).apply(asset.mesh.vertices) + sim.body_pose(body)[0])[:, 2].min()
    assert abs(lowest) < 0.004  # resting on the floor (z = 0) with its true mesh, within the collision margin


def test_still_is_net_motion_over_the_window_not_speed(sim):
    """The one rest test: a body that moved 1 mm over a 1/6 s window is still (the tolerance is 0.01 m/s
    times the window, 1.67 mm), whatever its speed in between; 2 mm is not; a turn of 0.5 degree is still,
    2 degrees is not (0.1 rad/s times the window is 0.017 rad, 0.95 degree)."""
    seconds = sim.config.rest_window
    assert seconds == pytest.approx(1 / 6)
    at = (np.zeros((4, 3)), np.tile([0.0, 0.0, 0.0, 1.0], (4, 1)))
    moved = np.array([[0.001, 0, 0], [0.002, 0, 0], [0, 0, 0], [0, 0, 0]])
    turns = Rotation.from_euler("z", [[0.0], [0.0], [0.5], [2.0]], degrees=True).as_quat()
    np.testing.assert_array_equal(sim.still(at, (moved, turns), seconds), [True, False, True, False])
    assert sim.timestep == pytest.approx(sim.config.timestep)
    assert sim.rest_steps() == 40 and sim.rest_steps(1 / 120) == 20


def test_simulator_rejects_bad_input_and_cleans_up(library):
    with pytest.raises(ValueError):
        SimConfig(timestep=0)
    with pytest.raises(ValueError):
        SimConfig(max_settle_steps=0)
    s = Simulator(SimConfig(egl_rendering=False))
    tmpdir = s._tmpdir
    with pytest.raises(ValueError):
        s.add_parcel(library.train[0], [0, 0, np.nan], [0, 0, 0, 1], 0.5)
    with pytest.raises(ValueError):
        s.add_parcel(library.train[0], [0, 0, 0], [0, 0, 0, 0], 0.5)
    with pytest.raises(ValueError):
        s.add_parcel(library.train[0], [0, 0, 0], [0, 0, 0, 1], -1.0)
    body = s.add_parcel(library.train[0], [0, 0, 1], [0, 0, 0, 1], 0.5)
    s.remove(body)
    assert not s.has_body(body)
    s.close()
    assert not tmpdir.exists()
    with pytest.raises(RuntimeError):
        s.step()


@pytest.mark.parametrize("kwargs", [
    dict(num_parcels=0), dict(num_parcels=51), dict(object_set="spheres"), dict(layout="heap"),
    dict(split="validation"), dict(friction_range=(0.8, 0.2)), dict(friction_range=(-0.1, 0.5)),
    dict(drop_height=-1.0), dict(chute_height=0.2), dict(stack_tilt_deg=-5.0), dict(scatter_yaw_jitter_deg=90.0),
    dict(heavy_first_mass=-0.5), dict(heavy_first_mass=float("nan")), dict(heavy_first_mass=float("inf")),
])
def test_pile_config_validation(kwargs):
    with pytest.raises(ValueError):
        PileConfig(**kwargs)


def test_negative_bin_size_is_rejected():
    with pytest.raises(ValueError):
        PileConfig(bin=BinSpec(inner_size=(-0.5, 0.5)))


def test_same_seed_gives_identical_poses(sim, library):
    config = PileConfig(**TINY)
    a = build_pile(sim, config, seed=3, library=library)
    b = build_pile(sim, config, seed=3, library=library)
    with Simulator(SimConfig(egl_rendering=False)) as fresh:
        c = build_pile(fresh, config, seed=3, library=library)
    for other in (b, c):
        assert [p.asset.asset_id for p in a.parcels] == [p.asset.asset_id for p in other.parcels]
        for x, y in zip(_poses(a), _poses(other)):
            assert np.array_equal(x, y)
    d = build_pile(sim, config, seed=4, library=library)
    assert not np.array_equal(_poses(a)[0][:1], _poses(d)[0][:1])


@pytest.mark.parametrize("split", ["train", "test"])
def test_split_scenes_use_only_their_split(sim, library, split):
    allowed = {a.asset_id for a in library.assets(split, "mixed")}
    for seed in range(2):
        scene = build_pile(sim, PileConfig(num_parcels=5, split=split), seed=seed, library=library)
        assert scene.parcels and scene.split == split
        assert all(p.asset.split == split and p.asset.asset_id in allowed for p in scene.parcels)


def test_stacked_pile_is_inside_the_bin_and_at_rest(sim, library):
    config = PileConfig(**TINY)
    scene = build_pile(sim, config, seed=1, library=library)
    meta = scene.meta
    assert meta["at_rest"]
    assert [p.object_id for p in scene.parcels] == list(range(len(scene.parcels)))
    assert meta["placed"] == len(scene.parcels)
    assert meta["requested"] == meta["placed"] + meta["skipped"] + meta["lost"] == config.num_parcels
    assert config.bin.contains(scene.world_coms()).all()
    for p in scene.parcels:  # scene poses are the simulator's mesh-frame poses
        pos, orn = sim.body_pose(p.body_id)
        assert np.array_equal(pos, p.position) and np.array_equal(orn, p.orientation)
        assert config.friction_range[0] <= p.friction <= config.friction_range[1]
    sim.step(40)  # at rest: another sixth of a second under nominal physics moves nothing visibly
    moved = [np.linalg.norm(sim.body_pose(p.body_id)[0] - p.position) for p in scene.parcels]
    assert max(moved) < 0.002


def test_heavy_parcels_first_go_down_the_chute_first_and_land_low(sim, library):
    """The same draws in another order: the parcels over the mass go first (a stable partition), so they rest
    on the floor rather than on the others; a mass no parcel exceeds changes nothing, bit for bit."""
    base = dict(num_parcels=20, layout="stacked", object_set="mixed")

    def build(**kwargs):  # the scene, and how high each parcel's hull starts above the floor (while it exists)
        scene = build_pile(sim, PileConfig(**base, **kwargs), seed=0, library=library)
        return scene, [pb.getAABB(p.body_id, physicsClientId=sim.client)[0][2] - scene.bin.floor_z
                       for p in scene.parcels]

    drawn, drawn_bottoms = build()
    masses = [p.asset.mass for p in drawn.parcels]
    cut = float(np.sort(masses)[-4])  # the three heaviest are over it
    routed, routed_bottoms = build(heavy_first_mass=cut)
    assert len(drawn.parcels) == len(routed.parcels) == 20  # nothing lost either way, so scene order is drop order
    heavy = [p.asset.asset_id for p in drawn.parcels if p.asset.mass > cut]
    light = [p.asset.asset_id for p in drawn.parcels if p.asset.mass <= cut]
    assert len(heavy) == 3 and [p.asset.asset_id for p in routed.parcels] == heavy + light
    assert max(routed_bottoms[:3]) < 0.02  # all three on the floor
    assert max(b for b, m in zip(drawn_bottoms, masses) if m > cut) > 0.05  # drawn order: one lay on others
    unchanged, _ = build(heavy_first_mass=max(masses))
    for x, y in zip(_poses(drawn), _poses(unchanged)):
        assert np.array_equal(x, y)


def test_the_env_passes_its_induction_order_to_the_pile_and_reports_the_request(library):
    from parcelpick_env.camera.config import CameraConfig
    from parcelpick_env.envs.parcel_pick import ParcelPickEnv

    env = ParcelPickEnv(num_parcels=8, layout="stacked", heavy_first_mass=0.5, num_points=256,
                        camera=CameraConfig(width=64, height=48))
    try:
        _, info = env.reset(seed=2)
        masses = [p.asset.mass for p in env.scene.parcels]
        heavy = sum(m > 0.5 for m in masses)
        assert 0 < heavy < len(masses) and all(m > 0.5 for m in masses[:heavy])  # the heavy class came first
        # and the info reports what the request was
        assert info["parcels_requested"] == 8 and info["pile_hull_fill"] == env.scene.meta["hull_fill"] > 0
    finally:
        env.close()
    with pytest.raises(ValueError, match="heavy_first_mass"):
        ParcelPickEnv(heavy_first_mass=float("nan"))


@pytest.mark.parametrize("seed", range(5))
def test_a_30_parcel_stacked_request_keeps_at_least_28(sim, library, seed):
    scene = build_pile(sim, PileConfig(num_parcels=30, layout="stacked", object_set="mixed"), seed, library)
    assert scene.meta["placed"] == len(scene.parcels) >= 28
    assert scene.meta["skipped"] == 0 and scene.meta["lost"] == 30 - len(scene.parcels)
    assert scene.bin.contains(scene.world_coms()).all()


def test_fifty_train_parcels_of_any_cluster_ask_less_than_a_stacked_tote_keeps(library):
    """The parcels are sized for the tote (docs/piles.md): fifty of any cluster ask on average less of it than the
    fill a stacked tote keeps 95% of."""
    for object_set in OBJECT_SETS:
        hulls = [asset.mesh.convex_hull.volume for asset in library.assets("train", object_set)]
        assert 50 * np.mean(hulls) / BinSpec().volume < STACKED_FILL_CAPACITY, object_set


@pytest.mark.parametrize("object_set", ["rectangular", "cylindrical"])
def test_fifty_cartons_or_tubes_keep_95_percent(sim, library, object_set):
    """The clusters with the largest parcels: fifty asked, at least 95% kept on average over three piles."""
    config = PileConfig(num_parcels=50, layout="stacked", object_set=object_set)
    kept = [len(build_pile(sim, config, seed, library).parcels) for seed in range(3)]
    assert np.mean(kept) >= 0.95 * 50, kept


@pytest.mark.parametrize("object_set", OBJECT_SETS)
def test_scattered_places_every_parcel_up_to_the_capacity(sim, library, object_set):
    for seed in range(2):
        config = PileConfig(num_parcels=SCATTER_CAPACITY, layout="scattered", object_set=object_set)
        scene = build_pile(sim, config, seed, library)
        assert len(scene.parcels) == SCATTER_CAPACITY, scene.meta
        assert scene.meta["skipped"] == scene.meta["lost"] == 0


def test_scattered_beyond_capacity_reports_the_shortfall(sim, library):
    scene = build_pile(sim, PileConfig(num_parcels=20, layout="scattered", object_set="rectangular"), 0, library)
    meta = scene.meta
    assert meta["skipped"] > 0 and len(scene.parcels) >= SCATTER_CAPACITY
    assert meta["requested"] == 20 == meta["placed"] + meta["skipped"] + meta["lost"]


def test_a_request_reports_its_hull_fill(sim, library):
    """The fill is the asked parcels' hull volume (kept and lost alike) over the tote's inner volume."""
    assert BinSpec().volume == pytest.approx(0.70 * 0.45 * 0.30)
    scene = build_pile(sim, PileConfig(**TINY), 0, library)
    hulls = sum(parcel.asset.mesh.convex_hull.volume for parcel in scene.parcels)
    assert scene.meta["lost"] == 0 and scene.meta["hull_fill"] == pytest.approx(hulls / BinSpec().volume)
    assert 0 < scene.meta["hull_fill"] < STACKED_FILL_CAPACITY


def test_an_overfull_stacked_request_warns_once_and_loses_parcels(sim, library, caplog, monkeypatch):
    """Ten cartons (about 15 L of hull) asked of a 7.5 L tote: the request is built, parcels spill over the
    rim, and one warning names the fill (once a process, not once a pile)."""
    spec = BinSpec(inner_size=(0.30, 0.25), wall_height=0.10)
    config = PileConfig(num_parcels=10, object_set="rectangular", bin=spec)
    monkeypatch.setitem(pile._WARNED, "overfull", False)
    with caplog.at_level(logging.WARNING, logger=pile.__name__):
        scene = build_pile(sim, config, 0, library)
        build_pile(sim, config, 1, library)
    warnings = [r.getMessage() for r in caplog.records if "convex hulls" in r.getMessage()]
    assert len(warnings) == 1 and "10 rectangular parcels" in warnings[0], warnings
    by_id = {asset.asset_id: asset for asset in library.assets("train", "rectangular")}
    asked = [parcel.asset for parcel in scene.parcels] + [by_id[i] for i in scene.meta["lost_assets"]]
    assert len(asked) == 10
    fill = sum(asset.mesh.convex_hull.volume for asset in asked) / spec.volume
    assert scene.meta["hull_fill"] == pytest.approx(fill) and fill > 1
    assert scene.meta["lost"] > 0 and scene.meta["placed"] + scene.meta["lost"] == 10


def test_inside_the_bin_is_one_definition():
    spec = BinSpec()
    hx, hy = np.asarray(spec.inner_size) / 2
    coms = np.array([
        [0.0, 0.0, 0.05],  # on the floor
        [hx - 0.001, hy - 0.001, 0.4],  # in a corner, heaped above the rim
        [hx + spec.wall_thickness / 2, 0.0, spec.wall_height + 0.02],  # balancing on the wall top
        [0.0, -hy - 0.05, -spec.wall_thickness + 0.003],  # fell out, on the ground beside the tote
        [0.0, 0.0, -0.05],  # below the floor
    ])
    np.testing.assert_array_equal(spec.contains(coms), [True, True, False, False, False])


def _tote_grid(spec: BinSpec, counts: tuple[int, int, int], top: float, margin: float) -> np.ndarray:
    """Points over the inner floor (``margin`` from the walls) from the floor up to ``top``."""
    (x0, y0, _), (x1, y1, _) = spec.workspace(margin=-margin)
    axes = np.linspace(x0, x1, counts[0]), np.linspace(y0, y1, counts[1]), spec.floor_z + np.linspace(0, top, counts[2])
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def test_arm_reaches_the_tote_top_down():
    """The mount reaches the tote's floor and the pile's height range top-down (coarse grid; the
    full 12 x 9 x 6 grid figure is in docs/piles.md). The margin is half the smallest parcel side:
    no top face has its centre closer to a wall."""
    spec = BinSpec()
    points = _tote_grid(spec, (7, 5, 4), top=0.45, margin=0.025)
    client = pb.connect(pb.DIRECT)
    try:
        arm = Gen3Arm(client, ArmConfig())
        reached = reachability(arm, points)
    finally:
        pb.disconnect(client)
    assert reached.mean() >= 0.99, points[~reached]


def test_scattered_footprints_do_not_overlap(sim, library):
    scene = build_pile(sim, PileConfig(num_parcels=4, layout="scattered", object_set="rectangular"), 0, library)
    assert len(scene.parcels) >= 2
    footprints = [shapely.convex_hull(shapely.multipoints(m.vertices[:, :2])) for m in scene.world_meshes()]
    for i in range(len(footprints)):
        for j in range(i + 1, len(footprints)):
            inter = footprints[i].intersection(footprints[j]).area
            assert inter < 0.02 * min(footprints[i].area, footprints[j].area)
    heights = np.array([m.bounds[0, 2] for m in scene.world_meshes()])
    assert np.all(np.abs(heights) < 0.01)  # every scattered parcel rests on the floor, none on another


def test_refresh_scene_poses_follows_the_simulator(sim, library):
    scene = build_pile(sim, PileConfig(num_parcels=2), seed=0, library=library)
    parcel = scene.parcels[0]
    sim.set_body_pose(parcel.body_id, [0.05, 0.02, 0.6], [0, 0, 0, 1])
    refresh_scene_poses(sim, scene)
    np.testing.assert_allclose(parcel.position, [0.05, 0.02, 0.6], atol=1e-9)
    sim.remove(parcel.body_id)
    with pytest.raises(ValueError):
        refresh_scene_poses(sim, scene)
