"""Procedural parcels and the asset library: sizes, masses, closed meshes, split and determinism."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from parcelpick_env.assets.generator import (CARTON_SIDE_RANGE, CUP_MASS_LIMIT, GEN3_PAYLOAD, MAX_MASS, MIN_MASS,
                                             PLANAR_LENGTH, PLANAR_WIDTH, ROLL_LENGTH, TOOL_ALLOWANCE, TUBE_LENGTH,
                                             TUBE_RADIUS, generate_parcel)
from parcelpick_env.assets.library import AssetLibrary
from parcelpick_env.assets.parcel import CATEGORIES

N_PER_CATEGORY = 12


def _parcels(category: str) -> list:
    return [generate_parcel(category, np.random.default_rng([1, i]), f"{category}-{i}", "train")
            for i in range(N_PER_CATEGORY)]


def _centre_thickness(mesh: trimesh.Trimesh) -> float:
    """Thickness along z through the body origin, by ray casting down through the mesh."""
    locations, _, _ = mesh.ray.intersects_location([[0.0, 0.0, 1.0]], [[0.0, 0.0, -1.0]])
    return float(np.ptp(locations[:, 2]))


@pytest.mark.parametrize("category", CATEGORIES)
def test_parcels_are_closed_centred_and_light_enough(category):
    for asset in _parcels(category):
        mesh = asset.mesh
        assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
        assert len(mesh.faces) <= 4000
        np.testing.assert_allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-9)  # origin at geometric centre
        np.testing.assert_allclose(asset.extents, mesh.extents)
        assert MIN_MASS <= asset.mass <= MAX_MASS
        assert mesh.contains([asset.com])[0], "centre of mass must lie inside the parcel"
        assert len(mesh.visual.face_colors) == len(mesh.faces)
        assert asset.category == category and all(0 <= c <= 1 for c in asset.rgba)


def test_category_sizes():
    lo, hi = CARTON_SIDE_RANGE
    for asset in _parcels("rectangular"):  # dents and bulges move a face by up to 12 % of the half side
        assert np.all(asset.extents >= lo * 0.88 - 1e-6) and np.all(asset.extents <= hi * 1.12 + 1e-6)
    for asset in _parcels("planar"):
        assert 0.005 - 1e-6 <= _centre_thickness(asset.mesh) <= 0.05 + 1e-6
        assert PLANAR_WIDTH[0] - 1e-6 <= asset.extents[:2].min() and asset.extents[:2].max() <= PLANAR_LENGTH[1] + 1e-6
    for asset in _parcels("cylindrical"):
        radius = asset.extents[1:].max() / 2  # axis along body x
        # the 48-gon's flats sit a little inside the radius
        assert TUBE_RADIUS[0] - 1e-3 <= radius <= TUBE_RADIUS[2] + 1e-6
        assert ROLL_LENGTH[0] - 1e-6 <= asset.extents[0] <= TUBE_LENGTH[1] + 1e-6


def test_masses_respect_the_arm(library):
    """The Gen3 carries 4 kg mid-range continuous without an end effector; the tool takes its share; the
    cup's rated pull at the carry's load share bounds it too (the lower wins)."""
    assert MAX_MASS == pytest.approx(min(GEN3_PAYLOAD - TOOL_ALLOWANCE, CUP_MASS_LIMIT)) and MAX_MASS <= 3.5
    masses = np.array([a.mass for a in library.train + library.test])
    assert masses.max() <= MAX_MASS and masses.min() >= MIN_MASS
    assert masses.max() > 1.5  # heavy parcels exist: the holding physics is exercised


def test_cartons_are_dented_not_perfect_boxes():
    volumes = [a.mesh.volume / np.prod(a.extents) for a in _parcels("rectangular")]
    assert min(volumes) < 0.999  # displaced faces, not the bounding box


def test_generate_parcel_rejects_bad_input():
    with pytest.raises(ValueError):
        generate_parcel("sphere", np.random.default_rng(0), "x", "train")
    with pytest.raises(ValueError):
        generate_parcel("planar", np.random.default_rng(0), "x", "validation")


def test_library_split_is_100_13_disjoint_and_balanced(library):
    assert len(library.train) == 100 and len(library.test) == 13
    train_ids = {a.asset_id for a in library.train}
    test_ids = {a.asset_id for a in library.test}
    assert not train_ids & test_ids
    for split in ("train", "test"):
        counts = [len(library.assets(split, c)) for c in CATEGORIES]
        assert min(counts) >= 4 and max(counts) - min(counts) <= 1
        assert len(library.assets(split, "mixed")) == sum(counts)
        assert all(a.split == split for a in library.assets(split, "mixed"))
    asset = library.test[0]
    assert library.get(asset.asset_id) is asset
    with pytest.raises(KeyError):
        library.get("no-such-asset")
    with pytest.raises(ValueError):
        library.assets("train", "spheres")


def test_library_is_deterministic_per_index(library):
    again = AssetLibrary.generate(seed=0, num_train=6, num_test=0)
    for a, b in zip(library.train[:6], again.train):
        assert a.asset_id == b.asset_id
        assert np.array_equal(a.mesh.vertices, b.mesh.vertices) and a.mass == b.mass
        assert np.array_equal(a.com, b.com)
    other = AssetLibrary.generate(seed=1, num_train=1, num_test=0)
    assert not np.array_equal(other.train[0].mesh.vertices, library.train[0].mesh.vertices)
    assert AssetLibrary.default(0) is library  # cached


def test_library_generates_an_asset_only_when_it_is_asked_for(monkeypatch):
    import parcelpick_env.assets.library as library_module

    made: list[str] = []
    real = library_module.generate_parcel
    monkeypatch.setattr(library_module, "generate_parcel", lambda *a, **k: made.append(a[2]) or real(*a, **k))
    lazy = AssetLibrary.generate(seed=0, num_train=9, num_test=3)
    pool = lazy.assets("train", "planar")
    assert len(lazy) == 12 and len(pool) == 3 and (lazy.train + lazy.test).ids[-1] == "test-cylindrical-002"
    assert made == []  # choosing and indexing need only the keys
    asset = pool[1]
    assert made == [asset.asset_id] == ["train-planar-004"]
    assert lazy.get("train-planar-004") is asset and pool[1] is asset and made == ["train-planar-004"]
    eager = AssetLibrary.generate(seed=0, num_train=9, num_test=0).train[4]  # the same index, generated alone
    assert np.array_equal(asset.mesh.vertices, eager.mesh.vertices) and asset.mass == eager.mass
    with pytest.raises(IndexError, match="not in a library of 12 assets"):
        lazy[12]


def test_a_library_pickles_as_its_recipe_or_its_assets():
    import pickle

    lazy = AssetLibrary.generate(seed=3, num_train=4, num_test=1)
    copy = pickle.loads(pickle.dumps(lazy))
    assert copy.keys == lazy.keys and copy.seed == 3
    assert np.array_equal(copy.test[0].mesh.vertices, lazy.test[0].mesh.vertices)
    eager = AssetLibrary([lazy.train[0], lazy.test[0]], seed=None)
    back = pickle.loads(pickle.dumps(eager))
    assert [a.asset_id for a in back.train + back.test] == [lazy.train[0].asset_id, lazy.test[0].asset_id]
