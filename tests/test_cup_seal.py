"""Bellows cup seal (docs/cup_seal.md): known answers computed by hand from the cup's figures.

The cup is the env's 40 mm bellows cup (r = 20 mm) with the default ``BellowsCup`` figures:
stroke 10 mm, bend 25 deg, lip compliance 4 mm, leak gap 3 mm; each margin scores 1 - u^2.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh

from meshes import box, horizontal_cylinder, tilted_plane
from parcelpick_env.assets.generator import generate_parcel
from parcelpick_env.suction import scorer as scorer_module
from parcelpick_env.suction.config import CELL_CUP_RADIUS, BellowsCup, SuctionConfig
from parcelpick_env.suction.cup_seal import SEAL_REASONS, ContactSeal
from parcelpick_env.suction.scorer import SuctionScorer

R = CELL_CUP_RADIUS  # 20 mm
CUP = BellowsCup()
BELLOWS = SuctionConfig(seal_model="bellows", cup_radius=R)
DOWN = np.array([0.0, 0.0, -1.0])


def taper(u: float) -> float:
    return max(0.0, 1.0 - u * u)



def scorer_for(mesh: trimesh.Trimesh, config: SuctionConfig = BELLOWS) -> SuctionScorer:
    return SuctionScorer([mesh], np.asarray(mesh.centroid)[None], config=config)


def contact(scorer: SuctionScorer, tip, axis=DOWN) -> ContactSeal:
    return scorer.contact_seal(np.array([tip], dtype=float), np.array([axis], dtype=float), np.array([0]))


def surface_seal(scorer: SuctionScorer, point, normal=-DOWN) -> float:
    return float(scorer.seal(np.array([point], dtype=float), np.array([normal], dtype=float), np.array([0]))[0])


def reason(seal: ContactSeal) -> str:
    return str(seal.reason_names()[0])




def top_z(mesh: trimesh.Trimesh, xy: np.ndarray) -> np.ndarray:
    """Highest surface z under each (x, y), by trimesh's ray caster (independent of Open3D)."""
    xy = np.atleast_2d(xy)
    origins = np.c_[xy, np.full(len(xy), mesh.bounds[1][2] + 1.0)]
    locations, index, _ = mesh.ray.intersects_location(origins, np.tile(DOWN, (len(xy), 1)))
    z = np.full(len(xy), -np.inf)
    np.maximum.at(z, index, locations[:, 2])
    assert np.all(np.isfinite(z)), "a probe missed the parcel"
    return z


def rim_xy(centre, count: int = BELLOWS.rim_vertices) -> np.ndarray:
    phi = 2 * np.pi * np.arange(count) / count
    return np.asarray(centre)[:2] + R * np.c_[np.cos(phi), np.sin(phi)]


@pytest.fixture(scope="module")
def carton():
    """A 30x20x10 cm carton, top face at z = 0."""
    return scorer_for(box((0.30, 0.20, 0.10), (0, 0, -0.05)))


@pytest.fixture(scope="module")
def mailer():
    """A generated planar parcel (wrinkled, pillowed top), body frame at its centre."""
    return generate_parcel("planar", np.random.default_rng(3), "mailer", "train").mesh


# ----------------------------------------------------------------------------- flat face and gap
def test_flat_face_seals(carton):
    seal = contact(carton, (0, 0, 0))
    assert seal.quality[0] == pytest.approx(1.0, abs=1e-5)
    assert reason(seal) == "sealed"
    assert seal.gap[0] == pytest.approx(0.0, abs=1e-6) and seal.tilt[0] == pytest.approx(0.0, abs=1e-6)
    assert surface_seal(carton, (0, 0, 0)) == pytest.approx(1.0, abs=1e-5)


@pytest.mark.parametrize("hover", [0.001, 0.0015, 0.0025])
def test_lip_just_above_a_flat_face_leaks_by_the_gap(carton, hover):
    seal = contact(carton, (0, 0, hover))
    assert seal.gap[0] == pytest.approx(hover, abs=1e-6)
    assert seal.quality[0] == pytest.approx(taper(hover / CUP.leak_gap), abs=1e-4)  # 1.5 mm: 0.75


def test_candidate_5cm_above_a_carton_top_fails_on_gap(carton):
    seal = contact(carton, (0, 0, 0.05))
    assert (seal.quality[0], reason(seal)) == (0.0, "gap")
    assert seal.gap[0] == pytest.approx(0.05, abs=1e-6)


def test_lip_pressed_into_the_face_uses_the_stroke(carton):
    seal = contact(carton, (0, 0, -0.005))  # 5 mm of the 10 mm stroke
    assert seal.quality[0] == pytest.approx(taper(0.5), abs=1e-4)
    assert reason(contact(carton, (0, 0, -0.011))) == "obstruction"


# ----------------------------------------------------------------------------- edges
def test_cup_bisecting_a_90_degree_edge_fails_on_edge():
    """Edge along y at the origin, faces z = 0 (x < 0) and x = 0 (z < 0), axis along the bisector.

    Rim ray at angle phi lands R |cos phi| below the lip: residual half-band R / 2 = 12.5 mm, three
    times the 4 mm lip compliance; the spring model passed this cup at 0.586.
    """
    edge = scorer_for(box((0.2, 0.3, 0.2), (-0.1, 0, -0.1)))
    bisector = np.array([1.0, 0.0, 1.0]) / np.sqrt(2)
    seal = contact(edge, (0, 0, 0), -bisector)
    assert (seal.quality[0], reason(seal)) == (0.0, "edge")
    assert seal.residual[0] == pytest.approx(R / 2, abs=1e-5)
    assert surface_seal(edge, (0, 0, 0), bisector) == 0.0
    spring = scorer_for(edge.meshes[0], SuctionConfig(cup_radius=R))
    assert surface_seal(spring, (0, 0, 0), bisector) == pytest.approx(0.586, abs=2e-3)


def test_vertical_cup_over_a_top_edge_misses(carton):
    assert reason(contact(carton, (0.15, 0, 0))) == "miss"


# ----------------------------------------------------------------------------- tilt
@pytest.mark.parametrize("degrees", [10.0, 20.0, 22.0, 24.0])
def test_plane_tilted_within_the_bend_limit_seals_partly(degrees):
    plane = scorer_for(tilted_plane(degrees))
    expected = taper(degrees / CUP.max_bend)  # 20 deg: 0.36, 22 deg: 0.2256
    assert surface_seal(plane, (0, 0, 0)) == pytest.approx(expected, abs=1e-4)
    # The same cup resting on the plane's first touch point, the rim's uphill end (x = -r).
    seal = contact(plane, (0, 0, R * np.tan(np.radians(degrees))))
    assert seal.gap[0] == pytest.approx(0.0, abs=1e-6)
    assert np.degrees(seal.tilt[0]) == pytest.approx(degrees, abs=1e-3)
    assert seal.quality[0] == pytest.approx(expected, abs=1e-4) and reason(seal) == "sealed"


def test_plane_tilted_beyond_the_bend_limit_fails_on_tilt():
    seal = contact(scorer_for(tilted_plane(27.0)), (0, 0, R * np.tan(np.radians(27.0))))
    assert (seal.quality[0], reason(seal)) == (0.0, "tilt")


def test_quality_falls_smoothly_with_tilt_no_cliff():
    degrees = np.arange(0.0, 26.0, 1.0)
    meshes = [tilted_plane(d) for d in degrees]
    scorer = SuctionScorer(meshes, np.array([m.centroid for m in meshes]), config=BELLOWS)
    tips = np.c_[np.zeros((len(degrees), 2)), R * np.tan(np.radians(degrees))]
    quality = scorer.contact_seal(tips, np.tile(DOWN, (len(degrees), 1)), np.arange(len(degrees))).quality
    assert np.all(np.diff(quality) < 0)
    assert quality[20] - quality[22] == pytest.approx(0.36 - 0.2256, abs=1e-3)  # the spring model: 0.94 -> 0
    assert np.max(-np.diff(quality)) < 0.09  # never more than 0.09 per degree


# ----------------------------------------------------------------------------- curvature
def test_cylinder_of_50mm_seals_with_the_hand_computed_quality():
    """Rim at x = r cos(phi) lies d = Rc - sqrt(Rc^2 - x^2) below the crown: 0 .. 4.17 mm.

    The fitted plane is level at mean(d) = 2.06 mm, so the half-band is 2.09 mm (u = 0.522) and the
    crown rises 2.06 mm into the cup (u = 0.206): quality (1 - 0.272) (1 - 0.043) = 0.697.
    """
    radius = 0.05
    x = rim_xy((0, 0))[:, 0]
    depth = radius - np.sqrt(radius**2 - x**2)
    expected = taper(np.ptp(depth) / 2 / CUP.lip_compliance) * taper(depth.mean() / CUP.stroke)
    seal = contact(scorer_for(horizontal_cylinder(radius)), (0, 0, radius))
    assert expected == pytest.approx(0.697, abs=1e-3)
    assert seal.quality[0] == pytest.approx(expected, abs=3e-3) and reason(seal) == "sealed"
    assert seal.residual[0] == pytest.approx(np.ptp(depth) / 2, abs=2e-5)


@pytest.mark.parametrize("radius, expected", [(0.028, "edge"), (0.012, "miss")])
def test_tight_cylinders_do_not_seal(radius, expected):
    """Below Rc = (r^2 + 4c^2) / 4c = 29 mm the saddle exceeds the lip; below r the rim misses."""
    seal = contact(scorer_for(horizontal_cylinder(radius)), (0, 0, radius))
    assert (seal.quality[0], reason(seal)) == (0.0, expected)


def test_seal_rises_with_cylinder_radius():
    qualities = [surface_seal(scorer_for(horizontal_cylinder(rc)), (0, 0, rc)) for rc in (0.030, 0.05, 0.1)]
    assert 0 < qualities[0] < qualities[1] < qualities[2] < 1


def test_bump_inside_the_cup_uses_the_stroke(carton):
    """A 1 cm square post on the carton's centre stands into the cup (disk rays at 0, 8.3, 16.7 mm)."""
    for height, quality, why in ((0.005, taper(0.5), "sealed"), (0.012, 0.0, "obstruction")):
        mesh = trimesh.util.concatenate([box((0.30, 0.20, 0.10), (0, 0, -0.05)),
                                         box((0.01, 0.01, height), (0, 0, height / 2))])
        assert surface_seal(scorer_for(mesh), (0, 0, 0)) == pytest.approx(quality, abs=1e-4)
        assert reason(contact(scorer_for(mesh), (0, 0, 0))) == why


# ----------------------------------------------------------------------------- mailers and hulls
def test_cup_hovering_1cm_above_a_wrinkled_mailer_fails_on_gap(mailer):
    scorer = scorer_for(mailer)
    tip = np.array([0.0, 0.0, top_z(mailer, np.zeros(2))[0] + 0.01])
    seal = contact(scorer, tip)
    true_gap = tip[2] - top_z(mailer, rim_xy(tip)).max()  # highest rim point touches first
    assert (seal.quality[0], reason(seal)) == (0.0, "gap")
    assert seal.gap[0] == pytest.approx(true_gap, abs=5e-5) and true_gap > CUP.leak_gap
    lowered = contact(scorer, tip + seal.gap[0] * DOWN)  # the same cup brought down to first touch seals
    assert lowered.quality[0] > 0 and reason(lowered) == "sealed"


def test_tip_on_a_tray_hull_scores_by_the_true_gap():
    """A tray: 2 cm border bars at z = 0 around a 16 cm floor h below. Its convex hull's top is z = 0,
    so a cup resting on the hull at the centre hovers exactly h above the true floor."""
    for depth, quality, why in ((0.0015, taper(0.5), "sealed"), (0.004, 0.0, "gap")):
        parts = [box((0.20, 0.20, 0.02), (0, 0, -depth - 0.01))]
        parts += [box(e, c) for e, c in [((0.20, 0.02, depth), (0, 0.09, -depth / 2)),
                                         ((0.20, 0.02, depth), (0, -0.09, -depth / 2)),
                                         ((0.02, 0.16, depth), (0.09, 0, -depth / 2)),
                                         ((0.02, 0.16, depth), (-0.09, 0, -depth / 2))]]
        tray = trimesh.util.concatenate(parts)
        tip = np.array([0.0, 0.0, top_z(tray.convex_hull, np.zeros(2))[0]])
        seal = contact(scorer_for(tray), tip)
        assert tip[2] == pytest.approx(0.0, abs=1e-9)
        assert seal.gap[0] == pytest.approx(depth, abs=1e-6)
        assert seal.quality[0] == pytest.approx(quality, abs=1e-4) and reason(seal) == why


def bent_mailer(curvature: float) -> trimesh.Trimesh:
    """A 20x15x1 cm mailer bent along x, z += k x^2: its top is concave, so its hull bridges the dip."""
    slab = box((0.20, 0.15, 0.01), (0, 0, 0))
    slab = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(slab.vertices, slab.faces, max_edge=0.004))
    slab.vertices[:, 2] += curvature * slab.vertices[:, 0] ** 2
    return slab


@pytest.mark.parametrize("curvature", [0.2, 0.4])
def test_tip_on_a_bent_mailer_hull_scores_by_the_true_gap(curvature):
    """The hull's top runs flat between the end edges at k (L/2)^2 above the true centre; the rim
    (|x| <= r) touches first at x = +-r, k r^2 higher: gap = k ((L/2)^2 - r^2) = 1.92 / 3.84 mm.
    The rim's saddle is k r^2 / 2 = 0.06 / 0.13 mm against the 4 mm lip compliance."""
    mailer = bent_mailer(curvature)
    tip = np.array([0.0, 0.0, top_z(mailer.convex_hull, np.zeros(2))[0]])
    gap = curvature * (0.1**2 - R**2)
    seal = contact(scorer_for(mailer), tip)
    assert seal.gap[0] == pytest.approx(gap, abs=2e-5)
    expected = taper(gap / CUP.leak_gap) * taper(curvature * R**2 / 2 / CUP.lip_compliance)
    assert seal.quality[0] == pytest.approx(expected, abs=2e-3)  # 0.590 at k = 0.2 /m, 0 at 0.4 /m
    assert reason(seal) == ("sealed" if gap < CUP.leak_gap else "gap")


def hull_rest(mailer: trimesh.Trimesh) -> tuple[np.ndarray, float]:
    """Tip of a flat-bottomed cup resting on the hull's highest point under its disk, at the centre,
    and the true gap below it: the tip's height over the highest true rim point (trimesh rays)."""
    disk = np.concatenate([rim_xy((0, 0)), rim_xy((0, 0))[::4] * 0.5, np.zeros((1, 2))])
    tip = np.array([0.0, 0.0, top_z(mailer.convex_hull, disk).max()])
    return tip, float(tip[2] - top_z(mailer, rim_xy((0, 0))).max())


@pytest.fixture(scope="module")
def hull_mailers():
    """The two generated planar parcels (of seeds 0..39) whose true top lies furthest below their hull
    at the centre (2.1 and 3.3 mm when written: seeds 11 and 35)."""
    mailers = [generate_parcel("planar", np.random.default_rng(seed), "mailer", "train").mesh for seed in range(40)]
    gaps = [hull_rest(m)[1] for m in mailers]
    return [mailers[i] for i in np.argsort(gaps)[-2:]]


@pytest.mark.parametrize("rank", [0, 1])
def test_tip_resting_on_a_generated_mailer_hull_scores_by_the_true_gap(hull_mailers, rank):
    """The wrinkled true top lies a few mm below the hull the cup rests on; the seal's gap is that
    true distance at the rim's first touch, and it alone can fail the seal."""
    mailer = hull_mailers[rank]
    tip, true_gap = hull_rest(mailer)
    seal = contact(scorer_for(mailer), tip)
    assert true_gap > 0.0015  # the hull stands well off the true top here
    assert seal.gap[0] == pytest.approx(true_gap, abs=5e-5)
    assert seal.quality[0] <= taper(true_gap / CUP.leak_gap) + 1e-4
    assert reason(seal) == ("gap" if true_gap >= CUP.leak_gap else "sealed")


# ----------------------------------------------------------------------------- API
def test_contact_seal_is_vectorised_and_batched(carton, monkeypatch):
    tips = np.array([[0, 0, 0], [0, 0, 0.0015], [0.15, 0, 0], [0, 0, 0.05], [0.05, 0.02, 0.001]], dtype=float)
    axes = np.tile(DOWN, (len(tips), 1))
    ids = np.array([0, 0, 0, 0, -1])
    whole = carton.contact_seal(tips, axes, ids)
    singles = [carton.contact_seal(t[None], a[None], i[None]) for t, a, i in zip(tips, axes, ids)]
    monkeypatch.setattr(scorer_module, "MAX_BATCH", 2)
    batched = carton.contact_seal(tips, axes, ids)
    for field in dataclasses.fields(ContactSeal):
        stacked = np.concatenate([getattr(s, field.name) for s in singles])
        np.testing.assert_allclose(getattr(whole, field.name), stacked, atol=1e-7)
        np.testing.assert_allclose(getattr(whole, field.name), getattr(batched, field.name), rtol=1e-12, atol=1e-15)
    assert list(whole.reason_names()) == ["sealed", "sealed", "miss", "gap", "miss"]
    assert whole.reason.dtype == np.int8 and whole.quality.dtype == np.float32
    assert np.all((whole.quality > 0) == (whole.reason == SEAL_REASONS.index("sealed")))


def test_contact_seal_refuses_bad_input(carton):
    with pytest.raises(ValueError, match="axes must be unit"):
        carton.contact_seal(np.zeros((1, 3)), np.array([[0, 0, -2.0]]), np.array([0]))
    with pytest.raises(ValueError, match="tips"):
        carton.contact_seal(np.zeros((1, 2)), np.array([DOWN]), np.array([0]))
    with pytest.raises(ValueError, match="seal_model='bellows'"):
        scorer_for(box((0.1, 0.1, 0.1), (0, 0, 0)), SuctionConfig()).contact_seal(
            np.zeros((1, 3)), np.array([DOWN]), np.array([0]))


def test_bellows_config_round_trips_and_validates():
    config = SuctionConfig(seal_model="bellows", cup_radius=R, bellows=BellowsCup(max_bend=30.0))
    assert SuctionConfig(**dataclasses.asdict(config)) == config
    with pytest.raises(ValueError, match="stroke"):
        BellowsCup(stroke=0.0)
    with pytest.raises(ValueError, match="max_bend"):
        BellowsCup(max_bend=95.0)
    with pytest.raises(ValueError, match="bellows"):
        SuctionConfig(bellows=3)
