"""Suction scorer: the known answers of docs/labels.md, collision, visibility and input validation."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from meshes import box, horizontal_cylinder
from parcelpick_env.assets.parcel import ParcelAsset
from parcelpick_env.scene.scene import BinSpec, ParcelState, Scene
from parcelpick_env.suction.config import SuctionConfig
from parcelpick_env.suction.scorer import SuctionScorer, SuctionScores
from parcelpick_env.suction.visibility import object_visibility

UP = np.array([[0.0, 0.0, 1.0]])
TORQUE_THR = SuctionConfig().torque_threshold




@pytest.fixture(scope="module")
def parcel_box():
    """The 30x20x10 cm box of the known-answer table, resting on z = 0, COM at its centre."""
    mesh = box((0.30, 0.20, 0.10), (0, 0, 0.05))
    return SuctionScorer([mesh], np.array([[0.0, 0.0, 0.05]]))


def one(scorer, method, point, normal=UP[0], object_id=0):
    args = (np.array([point], dtype=float), np.array([normal], dtype=float))
    if method != "collision":
        args += (np.array([object_id]),)
    return float(getattr(scorer, method)(*args)[0])


# ----------------------------------------------------------------------------- seal
def test_box_top_centre_seals_and_resists_gravity(parcel_box):
    assert one(parcel_box, "seal", (0, 0, 0.10)) == pytest.approx(1.0, abs=1e-3)
    assert one(parcel_box, "wrench", (0, 0, 0.10)) == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("point", [(0.148, 0.0, 0.10), (0.0, 0.098, 0.10), (0.15, 0.10, 0.10)],
                         ids=["2mm-from-x-edge", "2mm-from-y-edge", "corner"])
def test_rim_falling_off_the_box_breaks_the_seal(parcel_box, point):
    assert one(parcel_box, "seal", point) == 0.0


def test_rim_fully_on_the_box_near_an_edge_still_seals(parcel_box):
    assert one(parcel_box, "seal", (0.138, 0.0, 0.10)) == pytest.approx(1.0, abs=1e-3)


@pytest.mark.parametrize("radius, expected, tol", [(0.008, 0.0, 0.0), (0.012, 0.87, 0.015),
                                                   (0.020, 0.97, 0.01), (0.050, 0.995, 0.003)])
def test_horizontal_cylinder_known_answers(radius, expected, tol):
    scorer = SuctionScorer([horizontal_cylinder(radius)], np.zeros((1, 3)))
    assert one(scorer, "seal", (0, 0, radius)) == pytest.approx(expected, abs=tol)


def test_seal_on_cylinder_decreases_with_curvature():
    seals = [one(SuctionScorer([horizontal_cylinder(R)], np.zeros((1, 3))), "seal", (0, 0, R))
             for R in (0.012, 0.02, 0.05)]
    assert seals[0] < seals[1] < seals[2]


@pytest.mark.parametrize("radius, expected", [(0.02, 1.0), (0.05, 1.0), (0.008, 0.0)])
def test_sphere_seals_only_when_larger_than_the_cup(radius, expected):
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    scorer = SuctionScorer([sphere], np.zeros((1, 3)))
    assert one(scorer, "seal", (0, 0, radius)) == pytest.approx(expected, abs=2e-3)


@pytest.mark.parametrize("bump_height, expected", [(0.008, 0.0), (0.003, 1.0)])
def test_obstruction_inside_the_cup_disk(bump_height, expected):
    """A post at the cup's centre, inside the rim: taller than 5 mm blocks the seal."""
    top = box((0.30, 0.20, 0.10), (0, 0, 0.05))
    post = box((0.004, 0.004, bump_height), (0, 0, 0.10 + bump_height / 2))
    scorer = SuctionScorer([trimesh.util.concatenate([top, post])], np.array([[0, 0, 0.05]]))
    assert one(scorer, "seal", (0, 0, 0.10)) == pytest.approx(expected, abs=1e-3)


def test_flipped_normal_does_not_seal(parcel_box):
    """Approaching a box top from inside the box: the rim rays meet the top from behind."""
    assert one(parcel_box, "seal", (0, 0, 0.10), normal=(0, 0, -1)) == 0.0


def test_seal_uses_only_the_candidate_object():
    """A parcel hovering above the rim plane must not be mistaken for the surface under the cup."""
    lower = box((0.30, 0.20, 0.10), (0, 0, 0.05))
    upper = box((0.10, 0.10, 0.02), (0, 0, 0.12))  # 1 cm above the lower top, over the candidate
    scorer = SuctionScorer([lower, upper], np.array([[0, 0, 0.05], [0, 0, 0.12]]))
    assert one(scorer, "seal", (0, 0, 0.10), object_id=0) == pytest.approx(1.0, abs=1e-3)
    # The same point claimed for the upper parcel: no rim lands on it within the cup disk.
    assert one(scorer, "seal", (0, 0, 0.10), object_id=1) == 0.0


def reference_spring_seal(mesh, p, n, r=0.010, vertices=72, offset=0.05):
    """The spring model written out directly, one candidate at a time, with trimesh's ray caster."""
    helper = np.eye(3)[np.argmin(np.abs(n))]
    u = np.cross(n, helper)
    u /= np.linalg.norm(u)
    w = np.cross(n, u)
    theta = 2 * np.pi * np.arange(vertices) / vertices
    rim = p + r * (np.cos(theta)[:, None] * u + np.sin(theta)[:, None] * w)
    origins = rim + offset * n
    locations, ray_index, _ = mesh.ray.intersects_location(origins, np.tile(-n, (vertices, 1)))
    projected = np.empty_like(rim)
    for k in range(vertices):
        depth = (origins[k] - locations[ray_index == k]) @ n
        if not np.any(depth >= 0):
            return 0.0
        projected[k] = origins[k] - depth[depth >= 0].min() * n
    before = np.linalg.norm(np.roll(rim, -1, axis=0) - rim, axis=1)
    after = np.linalg.norm(np.roll(projected, -1, axis=0) - projected, axis=1)
    return max(0.0, 1 - min(1.0, ((after - before) / before).max()))


def test_seal_matches_a_direct_reference_on_a_bumpy_surface():
    rng = np.random.default_rng(1)
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.06)
    mesh.vertices += rng.normal(0, 0.0004, mesh.vertices.shape)
    mesh.apply_translation((0.3, -0.2, 0.1))
    points, faces = trimesh.sample.sample_surface(mesh, 8, seed=2)
    normals = mesh.face_normals[faces]
    ours = SuctionScorer([mesh], mesh.centroid[None]).seal(points, normals, np.zeros(8, dtype=int))
    expected = [reference_spring_seal(mesh, p, n) for p, n in zip(points, normals)]
    assert np.ptp(expected) > 0.05  # the bumps make the candidates differ
    np.testing.assert_allclose(ours, expected, atol=5e-5)


# ----------------------------------------------------------------------------- wrench
def test_side_face_centre_seals_but_cannot_hold(parcel_box):
    side = ((0.15, 0.0, 0.05), (1.0, 0.0, 0.0))
    assert one(parcel_box, "seal", *side) == pytest.approx(1.0, abs=1e-3)
    assert one(parcel_box, "wrench", *side) == 0.0  # 0.15 m * 9.8 N = 1.47 N m > 0.49


def test_top_twelve_cm_off_centre_cannot_hold(parcel_box):
    assert one(parcel_box, "seal", (0.12, 0.0, 0.10)) == pytest.approx(1.0, abs=1e-3)
    assert one(parcel_box, "wrench", (0.12, 0.0, 0.10)) == 0.0


def test_side_pick_gravity_angle_halves_the_score():
    mesh = box((0.1, 0.1, 0.1), (0, 0, 0.05))
    contact, normal = np.array([0.05, 0.0, 0.05]), np.array([1.0, 0.0, 0.0])
    # COM at the contact: no lever, only the angle factor 1 - (pi/2)/pi.
    at_contact = SuctionScorer([mesh], contact[None])
    assert one(at_contact, "wrench", contact, normal) == pytest.approx(0.5, abs=1e-6)
    # COM 2 cm inside on the axis: the lever is orthogonal to the axis, so torque adds.
    inside = SuctionScorer([mesh], np.array([[0.03, 0.0, 0.05]]))
    expected = (1 - 0.02 * 9.8 / TORQUE_THR) * 0.5
    assert one(inside, "wrench", contact, normal) == pytest.approx(expected, abs=1e-5)
    # The same lever along the axis of a top pick produces no torque.
    top = SuctionScorer([mesh], np.array([[0.0, 0.0, 0.08]]))
    assert one(top, "wrench", (0, 0, 0.10)) == pytest.approx(1.0, abs=1e-6)


def test_off_centre_pick_on_long_box_scores_lower_wrench():
    mesh = box((0.60, 0.10, 0.10), (0, 0, 0.05))
    scorer = SuctionScorer([mesh], np.array([[0.0, 0.0, 0.05]]))
    centre, off = one(scorer, "wrench", (0, 0, 0.1)), one(scorer, "wrench", (0.03, 0, 0.1))
    assert centre == pytest.approx(1.0)
    assert off == pytest.approx(1 - 0.03 * 9.8 / TORQUE_THR, abs=1e-5)
    assert off < centre


def test_tilted_approach_angle_and_lever(parcel_box):
    tilt = np.deg2rad(30)
    normal = np.array([np.sin(tilt), 0.0, np.cos(tilt)])
    contact = np.array([0.0, 0.0, 0.10])
    at_contact = SuctionScorer(parcel_box.meshes, contact[None])
    assert one(at_contact, "wrench", contact, normal) == pytest.approx(1 - 30 / 180, abs=1e-5)
    # COM 5 cm down the tilted axis: gravity's lever arm is 5 cm * sin(30 deg), across the axis.
    on_axis = SuctionScorer(parcel_box.meshes, (contact - 0.05 * normal)[None])
    expected = (1 - 0.05 * np.sin(tilt) * 9.8 / TORQUE_THR) * (1 - 30 / 180)
    assert one(on_axis, "wrench", contact, normal) == pytest.approx(expected, abs=1e-5)


# ----------------------------------------------------------------------------- collision
def test_isolated_box_top_is_collision_free(parcel_box):
    assert one(parcel_box, "collision", (0, 0, 0.10)) == 1.0


def test_parcel_lying_above_the_candidate_collides():
    lower = box((0.30, 0.20, 0.10), (0, 0, 0.05))
    upper = box((0.10, 0.10, 0.02), (0.0, 0.0, 0.15))  # 4-6 cm above the candidate
    scorer = SuctionScorer([lower, upper], np.zeros((2, 3)))
    assert one(scorer, "collision", (0, 0, 0.10)) == 0.0
    assert one(scorer, "collision", (0.10, 0.0, 0.10)) == 1.0  # beside the upper box


def test_tool_clipping_a_bin_wall_collides():
    bin_spec = BinSpec(inner_size=(0.70, 0.50), wall_height=0.25)
    wall_x = 0.35  # inner face of the +x wall
    parcel = box((0.10, 0.10, 0.10), (wall_x - 0.05, 0.0, 0.05))
    scorer = SuctionScorer([parcel], np.array([[wall_x - 0.05, 0.0, 0.05]]), bin_spec.meshes())
    assert one(scorer, "collision", (wall_x - 0.005, 0.0, 0.10)) == 0.0  # tool 5 mm into the wall
    assert one(scorer, "collision", (wall_x - 0.03, 0.0, 0.10)) == 1.0  # 2 cm of clearance


@pytest.mark.parametrize("intruder, expected", [
    (((0.05, 0.20, 0.40), (0.148 + 0.007 + 0.025, 0.0, 0.20)), 0.0),  # tall side 7 mm from the axis
    (((0.02, 0.02, 0.02), (0.148 + 0.007 + 0.010, 0.0, 0.15)), 0.0),  # cube poking 3 mm in, mid-tool
    (((0.02, 0.02, 0.02), (0.148 + 0.012 + 0.010, 0.0, 0.15)), 1.0),  # cube 2 mm outside the tool
], ids=["tall-side", "small-cube-in", "small-cube-out"])
def test_parcel_beside_the_tool(intruder, expected):
    lower = box((0.30, 0.20, 0.10), (0, 0, 0.05))
    scorer = SuctionScorer([lower, box(*intruder)], np.zeros((2, 3)))
    assert one(scorer, "collision", (0.148, 0.0, 0.10)) == expected


def test_wider_tool_body_collides_where_the_thin_tool_does_not():
    lower = box((0.30, 0.20, 0.10), (0, 0, 0.05))
    upper = box((0.05, 0.05, 0.02), (0.05, 0.0, 0.25))  # 15 cm above, 5 cm off the axis
    coms = np.zeros((2, 3))
    thin = SuctionScorer([lower, upper], coms)
    wide = SuctionScorer([lower, upper], coms, config=SuctionConfig(body_radius=0.05))
    assert one(thin, "collision", (0, 0, 0.10)) == 1.0
    assert one(wide, "collision", (0, 0, 0.10)) == 0.0


# ----------------------------------------------------------------------------- score, batch
def test_score_is_the_product_and_matches_single_scores():
    lower = box((0.30, 0.20, 0.10), (0, 0, 0.05))
    upper = box((0.10, 0.10, 0.02), (0.0, 0.0, 0.15))
    scorer = SuctionScorer([lower, upper], np.array([[0, 0, 0.05], [0, 0, 0.15]]))
    points = np.array([[0, 0, 0.10], [0.08, 0.05, 0.10], [0.148, 0, 0.10], [0, 0, 0.16], [0, 0, 0]])
    normals = np.tile(UP, (5, 1))
    ids = np.array([0, 0, 0, 1, -1])
    visibility = np.array([0.8, 0.5])
    scores = scorer.score(points, normals, ids, visibility)
    assert isinstance(scores, SuctionScores) and len(scores) == 5
    for name in ("seal", "wrench", "collision", "visibility", "total"):
        assert getattr(scores, name).dtype == np.float32 and getattr(scores, name).shape == (5,)
    np.testing.assert_allclose(scores.as_array(), np.stack(
        [scores.seal, scores.wrench, scores.collision, scores.visibility], axis=1))
    np.testing.assert_allclose(scores.total, scores.as_array().prod(axis=1), rtol=1e-6)
    np.testing.assert_allclose(scores.visibility, [0.8, 0.8, 0.8, 0.5, 0.0])
    assert scores.collision[0] == 0 and scores.collision[1] == 1 and scores.collision[3] == 1
    assert scores.seal[2] == 0 and scores.seal[3] > 0.99 and scores.seal[4] == 0
    assert scores.wrench[4] == 0 and scores.total[4] == 0
    # Batching changes nothing: the same candidates one by one.
    for i in range(5):
        single = scorer.score(points[i:i + 1], normals[i:i + 1], ids[i:i + 1], visibility)
        np.testing.assert_allclose(single.as_array()[0], scores.as_array()[i], atol=1e-6)


def test_large_batches_are_split_without_changing_results(monkeypatch):
    import parcelpick_env.suction.scorer as scorer_module

    lower = box((0.30, 0.20, 0.10), (0, 0, 0.05))
    upper = box((0.10, 0.10, 0.02), (0.0, 0.0, 0.15))
    scorer = SuctionScorer([lower, upper], np.array([[0, 0, 0.05], [0, 0, 0.15]]))
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-0.16, 0.16, 50), rng.uniform(-0.11, 0.11, 50),
                              np.full(50, 0.10)])
    normals, ids = np.tile(UP, (50, 1)), np.zeros(50, dtype=int)
    whole = scorer.score(points, normals, ids).as_array()
    assert 0 < whole[:, 0].mean() < 1 and 0 < whole[:, 2].mean() < 1  # a mix of outcomes
    monkeypatch.setattr(scorer_module, "MAX_BATCH", 7)
    np.testing.assert_array_equal(scorer.score(points, normals, ids).as_array(), whole)


def test_scorer_survives_pickling(parcel_box):
    import pickle

    clone = pickle.loads(pickle.dumps(parcel_box))
    points, normals, ids = np.array([[0, 0, 0.1], [0.148, 0, 0.1]]), np.tile(UP, (2, 1)), np.zeros(2, int)
    np.testing.assert_array_equal(clone.score(points, normals, ids).as_array(),
                                  parcel_box.score(points, normals, ids).as_array())


def test_empty_candidate_batch():
    scorer = SuctionScorer([box((0.1, 0.1, 0.1), (0, 0, 0.05))], np.zeros((1, 3)))
    scores = scorer.score(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=int))
    assert scores.as_array().shape == (0, 4)


def test_scene_without_parcels_still_checks_the_bin():
    scene = Scene(parcels=[], bin=BinSpec(), seed=0, layout="stacked", object_set="mixed", split="train")
    scorer = SuctionScorer.from_scene(scene)
    scores = scorer.score(np.array([[0, 0, 0.001], [0, 0.245, 0.001]]), np.tile(UP, (2, 1)),
                          np.array([-1, -1]))
    np.testing.assert_array_equal(scores.collision, [1.0, 0.0])  # the second clips the +y wall
    np.testing.assert_array_equal(scores.total, [0.0, 0.0])
    ids, dist = scorer.nearest_object(np.zeros((1, 3)))
    assert ids[0] == -1 and np.isinf(dist[0])


def test_nearest_object_assigns_points():
    a, b = box((0.1, 0.1, 0.1), (0, 0, 0.05)), box((0.1, 0.1, 0.1), (0.3, 0, 0.05))
    scorer = SuctionScorer([a, b], np.zeros((2, 3)))
    ids, dist = scorer.nearest_object(np.array([[0, 0, 0.102], [0.3, 0.02, 0.1], [0.2, 0, 0.05]]))
    np.testing.assert_array_equal(ids, [0, 1, 1])
    np.testing.assert_allclose(dist, [0.002, 0.0, 0.05], atol=1e-5)


def test_from_scene_uses_parcels_coms_and_bin():
    mesh = box((0.3, 0.2, 0.1), (0, 0, 0))
    asset = ParcelAsset(asset_id="b", category="rectangular", split="train", mesh=mesh, mass=1.0,
                        com=np.array([0.1, 0.0, 0.0]), rgba=(1, 1, 1, 1),
                        extents=np.array([0.3, 0.2, 0.1]))
    state = ParcelState(object_id=0, body_id=1, asset=asset, position=np.array([0.0, 0.0, 0.05]),
                        orientation=np.array([0.0, 0.0, 0.0, 1.0]), friction=0.5)
    scene = Scene(parcels=[state], bin=BinSpec(), seed=0, layout="scattered",
                  object_set="rectangular", split="train")
    scorer = SuctionScorer.from_scene(scene)
    assert scorer.num_objects == 1
    np.testing.assert_allclose(scorer.coms, [[0.1, 0.0, 0.05]])
    assert one(scorer, "seal", (0, 0, 0.10)) == pytest.approx(1.0, abs=1e-3)
    assert one(scorer, "wrench", (0.1, 0, 0.10)) == pytest.approx(1.0, abs=1e-6)  # over the COM
    assert one(scorer, "collision", (0.0, 0.0, 0.10)) == 1.0
    assert one(scorer, "collision", (0.0, 0.25, 0.001)) == 0.0  # on the floor against a wall


# ----------------------------------------------------------------------------- visibility
def overhead_camera(width=64, height=48, z=1.0):
    K = np.array([[60.0, 0, (width - 1) / 2], [0, 60.0, (height - 1) / 2], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # OpenCV camera looking straight down
    T[:3, 3] = (0, 0, z)
    return K, T, width, height


def test_visibility_alone_partly_buried_and_hidden():
    K, T, w, h = overhead_camera()
    target = box((0.2, 0.2, 0.05), (0, 0, 0.025))
    cover_half = box((0.2, 0.4, 0.05), (0.1, 0, 0.10))  # covers the +x half of the target
    lid = box((0.5, 0.5, 0.02), (0, 0, 0.30))
    assert object_visibility([target], K, T, w, h)[0] == pytest.approx(1.0)
    partly = object_visibility([target, cover_half], K, T, w, h)
    assert 0.3 < partly[0] < 0.7 and partly[1] == pytest.approx(1.0)
    hidden = object_visibility([target], K, T, w, h, occluders=[lid])
    assert hidden[0] == pytest.approx(0.0, abs=1e-6)
    outside = box((0.1, 0.1, 0.1), (5.0, 0, 0))  # never in view, even alone
    assert object_visibility([target, outside], K, T, w, h)[1] == 0.0


def test_visibility_matches_counting_every_ray_crossing():
    """Reference: alone-pixels from Open3D's list_intersections (every object each ray crosses)."""
    import open3d as o3d

    from parcelpick_env.suction.geometry import build_scene
    from parcelpick_env.suction.visibility import camera_rays

    K, T, w, h = overhead_camera(48, 40, z=0.8)
    T[:3, :3] = trimesh.transformations.rotation_matrix(0.3, (1, 0, 0))[:3, :3] @ T[:3, :3]
    rng = np.random.default_rng(3)
    meshes = [box((*rng.uniform(0.08, 0.2, 2), 0.04), (*rng.uniform(-0.1, 0.1, 2), 0.05 * i + 0.02))
              for i in range(6)]  # stacked layers, overlapping in the image
    wall = box((0.02, 0.6, 0.3), (0.2, 0, 0.15))
    ours = object_visibility(meshes, K, T, w, h, occluders=[wall])

    rays = o3d.core.Tensor(camera_rays(K, T, w, h))
    first = build_scene(meshes + [wall]).cast_rays(rays)["geometry_ids"].numpy().astype(np.int64)
    visible = np.array([(first == k).sum() for k in range(len(meshes))])
    crossings = build_scene(meshes).list_intersections(rays)
    pairs = set(zip(crossings["ray_ids"].numpy().tolist(), crossings["geometry_ids"].numpy().tolist()))
    alone = np.bincount([g for _, g in pairs], minlength=len(meshes))
    expected = np.where(alone > 0, visible / np.maximum(alone, 1), 0.0)
    assert np.sum((expected > 0.05) & (expected < 0.95)) >= 2  # the boxes really overlap in the image
    np.testing.assert_allclose(ours, expected, atol=0.02)


# ----------------------------------------------------------------------------- validation
@pytest.mark.parametrize("kwargs", [dict(cup_radius=-0.01), dict(rim_vertices=4),
                                    dict(seal_model="foam"), dict(tool_near=0.2),
                                    dict(body_radius=-1.0), dict(max_ray_depth=0.0),
                                    dict(num_threads=-1)])
def test_bad_config_raises(kwargs):
    with pytest.raises(ValueError):
        SuctionConfig(**kwargs)


def test_bad_inputs_raise(parcel_box):
    p, n, ids = np.array([[0, 0, 0.1]]), UP.copy(), np.array([0])
    bad_calls = [
        lambda: parcel_box.seal(np.array([[np.nan, 0, 0.1]]), n, ids),
        lambda: parcel_box.seal(p[:, :2], n, ids),
        lambda: parcel_box.seal(p, n * 2, ids),
        lambda: parcel_box.seal(p, np.zeros((1, 3)), ids),
        lambda: parcel_box.seal(p, np.tile(UP, (2, 1)), ids),
        lambda: parcel_box.seal(p, n, np.array([1])),
        lambda: parcel_box.seal(p, n, np.array([0.0])),
        lambda: parcel_box.wrench(p, n, np.array([0, 0])),
        lambda: parcel_box.collision(p, np.array([[0, 0, np.inf]])),
        lambda: parcel_box.score(p, n, ids, visibility=np.array([0.5, 0.5])),
        lambda: parcel_box.score(p, n, ids, visibility=np.array([1.5])),
        lambda: parcel_box.nearest_object(np.zeros((2, 2))),
        lambda: SuctionScorer([box((0.1, 0.1, 0.1), (0, 0, 0))], np.zeros((2, 3))),
        lambda: SuctionScorer(["not a mesh"], np.zeros((1, 3))),
        lambda: SuctionScorer([box((0.1, 0.1, 0.1), (0, 0, 0))], np.zeros((1, 3)), config={}),
        lambda: object_visibility([box((0.1, 0.1, 0.1), (0, 0, 0))], np.eye(2), np.eye(4), 8, 8),
        lambda: object_visibility([box((0.1, 0.1, 0.1), (0, 0, 0))], np.eye(3), np.eye(4), 0, 8),
    ]
    for call in bad_calls:
        with pytest.raises(ValueError):
            call()
