"""The named suction-quality definitions (parcelpick_env/suction/quality.py) on hand-computed answers.

`suctionnet` is SuctionNet-1Billion's evaluator; each expected value below is computed here, independently of the
scorer's ray casting, from the analytic surface (the limit SuctionNet's dense 0.2 mm sample approaches).
`physical` is the env's cup hanging the real mass; its answers come from F = dP A / S and the Dex-Net ring
conditions by hand.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import trimesh
from meshes import box, horizontal_cylinder, tilted_plane

from parcelpick_env.assets.parcel import ParcelAsset
from parcelpick_env.scene.scene import BinSpec, ParcelState, Scene
from parcelpick_env.suction.config import SuctionConfig
from parcelpick_env.suction.geometry import build_scene
from parcelpick_env.suction.physical import hull_seats, lip_face
from parcelpick_env.suction.quality import (
    PAPER_LABELS,
    SUCTIONNET_EVALUATOR,
    SUCTIONNET_LABEL_TIME,
    PhysicalCell,
    check_definition,
    definition_scorer,
    score_definition,
)
from parcelpick_env.suction.scorer import SuctionScorer

UP = np.array([0.0, 0.0, 1.0])
G, K, R10 = 9.8, 15.6, 0.010
TAU_THR = R10 * K * math.pi  # 0.490 N m


def one(scorer: SuctionScorer, method: str, point, normal=UP) -> float:
    return float(getattr(scorer, method)(np.array([point], float), np.array([normal], float), np.array([0]))[0])


def continuous_suctionnet_seal(height, r: float = R10, band: float = 0.001, bins: int = 72,
                               samples: int = 121) -> float:
    """SuctionNet's seal with each bin's vertex at the highest point of its annular sector, the sector sampled
    on a fine grid: ``height(rho, theta)`` is the surface above the cup plane in the cup frame."""
    width = 2 * np.pi / bins
    centres = width * np.arange(bins)
    rho = np.linspace(r - band, r + band, samples)
    offsets = np.linspace(-width / 2, width / 2, samples)
    h = np.array([height(rho[None, :], (c + offsets)[:, None]).max() for c in centres])
    chord = 2 * r * np.sin(np.pi / bins)
    stretched = np.sqrt(chord**2 + (np.roll(h, -1) - h) ** 2)
    return float(np.exp(-1e5 * h.var()) * (chord / stretched).min())


# ------------------------------------------------------------------------------------------- suctionnet seal
@pytest.mark.parametrize("radius, dense_sample", [(0.012, 0.73), (0.020, 0.91), (0.050, 0.99)])
def test_suctionnet_seal_on_cylinders(radius, dense_sample):
    """Horizontal cylinders (axis x): the rim's bins rise and fall with |y|. The scorer's heading in the cup frame
    is measured from world +y (tangent_frames of a vertical normal), so y = rho cos(theta)."""
    scorer = SuctionScorer([horizontal_cylinder(radius, sections=2048)], np.zeros((1, 3)), config=SUCTIONNET_EVALUATOR)
    ours = one(scorer, "seal", (0, 0, radius))
    expected = continuous_suctionnet_seal(lambda rho, th: np.sqrt(radius**2 - (rho * np.cos(th)) ** 2) - radius)
    assert ours == pytest.approx(expected, abs=4e-3)
    # SuctionNet's own figure on a dense point sample is a little lower (its bin maxima jitter, which the
    # deform term reads as stretch; docs/labels.md): the continuous limit stays within 0.03 of it.
    assert abs(ours - dense_sample) < 0.03


def test_suctionnet_seal_is_stricter_than_the_spring_on_curves():
    spring = SuctionScorer([horizontal_cylinder(0.012)], np.zeros((1, 3)), config=PAPER_LABELS)
    suctionnet = SuctionScorer([horizontal_cylinder(0.012)], np.zeros((1, 3)), config=SUCTIONNET_EVALUATOR)
    assert one(suctionnet, "seal", (0, 0, 0.012)) < one(spring, "seal", (0, 0, 0.012)) - 0.05


@pytest.mark.parametrize("degrees", [10.0, 20.0])
def test_suctionnet_seal_on_a_tilted_plane_approached_vertically(degrees):
    """Plane z = -x tan(a) under a vertical cup: in the cup frame x = -rho sin(theta), so h = rho sin(theta) tan(a)."""
    scorer = SuctionScorer([tilted_plane(degrees)], np.zeros((1, 3)), config=SUCTIONNET_EVALUATOR)
    slope = math.tan(math.radians(degrees))
    expected = continuous_suctionnet_seal(lambda rho, th: rho * np.sin(th) * slope)
    assert one(scorer, "seal", (0, 0, 0)) == pytest.approx(expected, abs=0.01)
    assert 0.05 < expected < 0.95  # a graded answer, not a pass/fail


def test_suctionnet_seal_fails_where_the_face_rises_5mm_inside_the_cup():
    """At 35 deg the plane stands r tan(a) = 7 mm above p inside the disk: SuctionNet's collision rule (> 5 mm)."""
    scorer = SuctionScorer([tilted_plane(35.0)], np.zeros((1, 3)), config=SUCTIONNET_EVALUATOR)
    assert one(scorer, "seal", (0, 0, 0)) == 0.0
    assert one(scorer, "seal", (0, 0, 0), normal=(math.sin(math.radians(35)), 0, math.cos(math.radians(35)))) \
        == pytest.approx(1.0, abs=1e-3)  # along the face normal it is a flat face


def test_suctionnet_seal_flat_top_and_edge():
    scorer = SuctionScorer([box((0.3, 0.2, 0.1), (0, 0, 0.05))], np.zeros((1, 3)), config=SUCTIONNET_EVALUATOR)
    assert one(scorer, "seal", (0, 0, 0.1)) == pytest.approx(1.0, abs=1e-6)
    # 9.5 mm from the edge the band's outer part overhangs, but every bin still holds top-face points: 1, as the
    # highest point of each bin is on the top; 7.5 mm from it the +x bins hold nothing (not even side-face points,
    # which lie 7.5 mm out): empty bins fail
    assert one(scorer, "seal", (0.1405, 0, 0.1)) == pytest.approx(1.0, abs=1e-6)
    assert one(scorer, "seal", (0.1425, 0, 0.1)) == 0.0


# ------------------------------------------------------------------------------------------- wrenches
@pytest.fixture(scope="module")
def carton():
    """30 x 20 x 10 cm on z = 0; its COM is put 3 cm off the surface centroid to tell the two apart."""
    mesh = box((0.3, 0.2, 0.1), (0, 0, 0.05))
    return mesh, np.array([[0.03, 0.0, 0.05]])


def test_suctionnet_wrench_uses_the_larger_bending_axis_about_the_surface_centroid(carton):
    mesh, com = carton
    scorer = SuctionScorer([mesh], com, config=SUCTIONNET_EVALUATOR)
    assert one(scorer, "wrench", (0, 0, 0.1)) == pytest.approx(1.0, abs=1e-6)  # over the centroid, not the COM
    # 3 cm off in x and 2 cm in y: max(g 0.03, g 0.02) / 0.49 = 0.6
    assert one(scorer, "wrench", (-0.03, -0.02, 0.1)) == pytest.approx(1 - G * 0.03 / TAU_THR, abs=1e-5)
    paper = SuctionScorer([mesh], np.array([[0.0, 0.0, 0.05]]), config=PAPER_LABELS)
    assert one(paper, "wrench", (-0.03, -0.02, 0.1)) == pytest.approx(1 - G * math.hypot(0.03, 0.02) / TAU_THR,
                                                                      abs=1e-5)


def test_suctionnet_wrench_has_no_gravity_angle_factor():
    """A side pick on a 4 mm board standing on edge: the centroid (and COM) 2 mm behind the face bends the lip by
    g 0.002 either way, and the paper's label alone halves it for the 90 degree approach."""
    mesh = box((0.004, 0.2, 0.2), (0, 0, 0.1))
    side = ((0.002, 0.0, 0.1), (1.0, 0.0, 0.0))
    lever = 1 - G * 0.002 / TAU_THR
    centre = np.array([[0.0, 0.0, 0.1]])
    assert one(SuctionScorer([mesh], centre, config=SUCTIONNET_EVALUATOR), "wrench", *side) == pytest.approx(lever, abs=1e-5)
    assert one(SuctionScorer([mesh], centre, config=PAPER_LABELS), "wrench", *side) == pytest.approx(0.5 * lever, abs=1e-5)


def test_suctionnet_label_time_wrench_is_lenient(carton):
    """Top-down, SuctionNet's frame has y = world y: the label-time norm counts the twist (0) and tau_y = g dx only,
    at sqrt(2) the threshold, so an offset along y costs nothing at all."""
    mesh, _ = carton
    scorer = SuctionScorer([mesh], np.zeros((1, 3)), config=SUCTIONNET_LABEL_TIME)
    assert one(scorer, "wrench", (-0.03, 0, 0.1)) == pytest.approx(1 - G * 0.03 / (math.sqrt(2) * TAU_THR), abs=1e-5)
    assert one(scorer, "wrench", (0, -0.09, 0.1)) == pytest.approx(1.0, abs=1e-6)
    assert one(SuctionScorer([mesh], np.zeros((1, 3)), config=SUCTIONNET_EVALUATOR), "wrench", (0, -0.09, 0.1)) == 0.0


# ------------------------------------------------------------------------------------------- physical
def scene_of(mesh, mass: float, com_local=(0.0, 0.0, 0.0), centre=(0.0, 0.0, 0.05)) -> Scene:
    asset = ParcelAsset(asset_id="c", category="rectangular", split="test", mesh=mesh, mass=mass,
                        com=np.asarray(com_local, float), rgba=(1, 1, 1, 1), extents=np.asarray(mesh.extents))
    state = ParcelState(object_id=0, body_id=-1, asset=asset, position=np.asarray(centre, float),
                        orientation=np.array([0.0, 0.0, 0.0, 1.0]), friction=0.5)
    return Scene(parcels=[state], bin=BinSpec(), seed=0, layout="scattered", object_set="rectangular", split="test")


def physical(scene: Scene, point, normal=UP):
    scorer = definition_scorer("physical", scene)
    return score_definition("physical", scorer, np.array([point], float), np.array([normal], float), np.array([0]))


def rated_pull(seal: float, cell: PhysicalCell) -> float:
    """F = dP(s) pi r^2 / S with dP(s) = dP0 / (1 + beta (1 - s)) (suction/cup.py)."""
    cup, r = cell.cup, cell.suction.cup_radius
    return cup.vacuum_kpa * 1e3 / (1 + cup.leak_ratio * (1 - seal)) * math.pi * r**2 / cup.safety_factor


def test_physical_centre_pick_margin_is_the_vacuum_share():
    cell = PhysicalCell()
    scores = physical(scene_of(box((0.3, 0.2, 0.1), (0, 0, 0)), 1.0), (0, 0, 0.1))
    seal = float(scores.seal[0])
    assert seal > 0.95
    assert float(scores.wrench[0]) == pytest.approx(1 - 1.0 * G / rated_pull(seal, cell), abs=1e-4)  # ~0.8
    assert float(scores.collision[0]) == 1.0


def test_physical_lever_arm_bends_the_lip_and_the_heavy_parcel_falls():
    """5 cm from the COM: material ratio sqrt(2) m g d / (pi r k), 0.707 at 1 kg (holds), 1.41 at 2 kg (falls)."""
    cell = PhysicalCell()
    cap = math.pi * cell.suction.cup_radius * cell.suction.material_k
    light = physical(scene_of(box((0.3, 0.2, 0.1), (0, 0, 0)), 1.0), (0.05, 0, 0.1))
    assert float(light.wrench[0]) == pytest.approx(1 - math.sqrt(2) * 1.0 * G * 0.05 / cap, abs=1e-3)
    heavy = physical(scene_of(box((0.3, 0.2, 0.1), (0, 0, 0)), 2.0), (0.05, 0, 0.1))
    assert float(heavy.wrench[0]) == 0.0 and float(heavy.quality[0]) == 0.0


def test_physical_seal_below_the_env_threshold_holds_nothing():
    """On a 12 mm tube the 20 mm lip cannot close: the physical seal channel is 0 (the spring label still seals)."""
    tube = horizontal_cylinder(0.012)
    scores = physical(scene_of(tube, 0.3, centre=(0, 0, 0.012)), (0, 0, 0.024))
    assert float(scores.seal[0]) == 0.0 and float(scores.quality[0]) == 0.0


def physical_seal(scene: Scene, point, object_id: int = 0) -> float:
    scorer = definition_scorer("physical", scene)
    return float(scorer.physical(np.array([point], float), UP[None], np.array([object_id])).seal[0])


def test_a_cup_coming_down_on_a_tilted_face_seats_where_its_uphill_rim_touches():
    """A vertical cup over a face tilted 15 deg stops when its uphill rim meets the hull, r tan 15 deg = 5.4 mm
    above where the axis meets it, and seals by the tilt alone: 1 - (15/25)^2 = 0.64. Seated on the axis, the rim
    would be pressed 5.4 mm in and the stroke would cost 1 - 0.536^2 more (0.46)."""
    tilt = math.radians(15.0)
    mesh = box((0.3, 0.2, 0.1), (0, 0, 0)).apply_transform(trimesh.transformations.rotation_matrix(tilt, [1, 0, 0]))
    centre = np.array([0.0, 0.0, 0.08])
    scene = scene_of(mesh, 0.5, centre=centre)
    top = centre + 0.05 * np.array([0.0, -math.sin(tilt), math.cos(tilt)])  # where the vertical axis meets the face
    face = lip_face(definition_scorer("physical", scene).config)
    tips, own = hull_seats(build_scene([scene.parcels[0].world_mesh().convex_hull]), top[None], UP[None],
                           np.array([0]), face)
    assert own[0] and tips[0, 2] - top[2] == pytest.approx(0.020 * math.tan(tilt), abs=3e-4)
    assert physical_seal(scene, top) == pytest.approx(1 - (15 / 25) ** 2, abs=0.02)


def test_a_cup_whose_face_meets_an_overhanging_neighbour_first_lands_there():
    """A plank 3 cm above a box's top overhangs its edge by 2.5 cm. With the axis 1.5 cm clear of the plank's
    edge, the rim of the 20 mm lip still meets the plank first: the cup lands there and the box gets no seal
    (seated on the axis, it sealed the box at 1.0). 4.5 cm clear, the lip seats on the box."""
    low = scene_of(box((0.2, 0.2, 0.1), (0, 0, 0)), 0.5, centre=(0, 0, 0.05))
    plank = scene_of(box((0.2, 0.2, 0.02), (0, 0, 0)), 0.5, centre=(0.175, 0, 0.14)).parcels[0]
    plank.object_id = 1
    scene = dataclasses.replace(low, parcels=low.parcels + [plank])
    assert physical_seal(scene, (0.03, 0, 0.1)) > 0.95  # the lip's face clears the plank (x <= 0.05 < 0.075)
    assert physical_seal(scene, (0.06, 0, 0.1)) == 0.0  # its rim reaches x = 0.08, under the plank


def test_collision_on_bin_walls_counts_except_for_suctionnet():
    """A tall parcel against the +y wall: the tool on its edge clips the wall. SuctionNet's evaluator knows only
    objects and the table."""
    spec = BinSpec()
    wall_y = spec.center_xy[1] + spec.inner_size[1] / 2
    mesh = box((0.1, 0.1, 0.2), (0, 0, 0))
    scene = scene_of(mesh, 0.5, centre=(spec.center_xy[0], wall_y - 0.055, spec.floor_z + 0.1))
    point = np.array([[spec.center_xy[0], wall_y - 0.008, spec.floor_z + 0.2]])  # the tool reaches 2 mm into the wall
    assert definition_scorer("paper", scene).collision(point, UP[None])[0] == 0.0
    assert definition_scorer("suctionnet", scene).collision(point, UP[None])[0] == 1.0


def test_unknown_definition_is_one_clear_error():
    with pytest.raises(ValueError, match="unknown quality definition 'suctionet'"):
        check_definition("suctionet")
    assert SuctionConfig().wrench_model == "paper"
