"""The one farthest-point sampler (parcelpick_env/farthest_points.py) and its three callers."""

from __future__ import annotations

import numpy as np
import pytest

from parcelpick_env.farthest_points import farthest_point_indices, fixed_size_sample


def _greedy_reference(points: np.ndarray, k: int, start: int) -> np.ndarray:
    """Textbook FPS, written out for the test: next = the point farthest from all chosen (first on ties)."""
    chosen = [start]
    dist = ((points - points[start]) ** 2).sum(1)
    for _ in range(k - 1):
        chosen.append(int(np.argmax(dist)))
        dist = np.minimum(dist, ((points - points[chosen[-1]]) ** 2).sum(1))
    return np.sort(chosen)


def test_known_answer_on_a_line():
    line = np.c_[np.arange(10.0), np.zeros(10), np.zeros(10)]
    # from 0: the far end 9, then 4 and 5 are both 4 away from {0, 9}: the lower index wins
    assert farthest_point_indices(line, 3).tolist() == [0, 4, 9]
    assert farthest_point_indices(line, 2, start=5).tolist() == [0, 5]
    assert farthest_point_indices(line, 10).tolist() == list(range(10))
    assert farthest_point_indices(line, 50).tolist() == list(range(10))  # k >= N: every point


@pytest.mark.parametrize("start", [0, 17, 299])
def test_matches_the_greedy_definition(start):
    cloud = np.random.default_rng(start).normal(size=(300, 3))
    assert np.array_equal(farthest_point_indices(cloud, 40, start), _greedy_reference(cloud, 40, start))


def test_bad_input_is_refused():
    cloud = np.zeros((5, 3))
    for bad in (dict(points=np.zeros((0, 3)), k=1), dict(points=np.zeros((4, 2)), k=1), dict(points=cloud, k=0),
                dict(points=cloud, k=2, start=5), dict(points=np.full((3, 3), np.nan), k=1)):
        with pytest.raises(ValueError):
            farthest_point_indices(**bad)
    with pytest.raises(ValueError, match="presample"):
        fixed_size_sample(cloud, 2, np.random.default_rng(0), presample=0.5)


def test_fixed_size_sample_covers_the_cloud_and_is_seeded():
    rng = np.random.default_rng(0)
    cloud = np.concatenate([rng.normal(0, 0.01, (5000, 3)), rng.normal(1, 0.01, (50, 3))])
    idx = fixed_size_sample(cloud, 20, np.random.default_rng(1))
    assert len(np.unique(idx)) == 20 and (idx >= 5000).sum() >= 5  # the small far cluster is not ignored
    assert np.array_equal(idx, fixed_size_sample(cloud, 20, np.random.default_rng(1)))
    pre = fixed_size_sample(cloud, 20, np.random.default_rng(1), presample=4.0)
    assert len(np.unique(pre)) == 20 and np.array_equal(pre, fixed_size_sample(cloud, 20, np.random.default_rng(1), 4.0))
    assert not np.array_equal(pre, fixed_size_sample(cloud, 20, np.random.default_rng(2), 4.0))
    padded = fixed_size_sample(cloud[:10], 16, rng)
    assert len(padded) == 16 and set(padded.tolist()) == set(range(10))  # every point, then repeats
    with pytest.raises(ValueError):
        fixed_size_sample(np.zeros((0, 3)), 4, rng)


def test_hull_reduction_keeps_the_farthest_vertices():
    """The simulator's collision hull: FPS from the vertex farthest from the centroid, by definition."""
    import trimesh

    from parcelpick_env.sim import simulator

    class _Asset:  # the two fields _asset_geometry reads; weak-referenceable for its cache
        mesh = trimesh.creation.cylinder(radius=0.04, height=0.2, sections=48)  # 96 hull vertices

    hull = _Asset.mesh.convex_hull.vertices
    start = int(np.argmax(((hull - hull.mean(0)) ** 2).sum(1)))
    geometry = simulator._asset_geometry(_Asset(), 24)  # type: ignore[arg-type]
    assert np.array_equal(geometry["hull"], hull[_greedy_reference(hull, 24, start)])


def test_diffusion_fps_centres_use_the_same_sampler():
    from policies.diffusion.neighbourhood import sample_indices

    cloud = np.random.default_rng(3).random((500, 3))
    assert np.array_equal(sample_indices(cloud, 64, "fps"), farthest_point_indices(cloud, 64))
