"""markers.neighbours against scipy's cKDTree, which it replaces in detect and identify (issue 40, per-job
overhead): the same distances to the last bit and the same neighbours, on seeded point sets of every
size and scale the marker stage meets (a few to thousands of points, 10 px to 1e5 px), with and
without an upper bound, and the same points within a radius, boundaries included. Where points lie
exactly as far from a query (ties), the lower index comes first; cKDTree's order is its tree's."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from dmais_pipe.markers import neighbours
from dmais_pipe.markers.neighbours import Neighbours


@pytest.fixture(params=["all pairs", "chunks and grid"])
def paths(request, monkeypatch):
    """Each test both ways: look-ups of up to CHUNK_PAIRS pairs (65,536) compare every pair at once, larger
    ones go by chunks (unbounded) or by the grid (bounds, radii); a CHUNK_PAIRS of 64 sends nearly
    every look-up the second way."""
    if request.param != "all pairs":
        monkeypatch.setattr(neighbours, "CHUNK_PAIRS", 64)
    return request.param


def _same_query(tree: cKDTree, ours: Neighbours, *args, **kwargs) -> None:
    expected, got = tree.query(*args, **kwargs), ours.query(*args, **kwargs)
    np.testing.assert_array_equal(got[0], expected[0])
    np.testing.assert_array_equal(got[1], expected[1])
    assert np.shape(got[1]) == np.shape(expected[1]) and np.asarray(got[1]).dtype.kind == "i"


@pytest.mark.parametrize("seed", range(4))
def test_the_nearest_points_are_cKDTrees(seed, paths):
    rng = np.random.default_rng(seed)
    for _ in range(40):
        scale = float(rng.choice([10.0, 4096.0, 1e5]))
        points = rng.uniform(-scale, scale, (int(rng.integers(1, 400)), 2))
        queries = rng.uniform(-1.2 * scale, 1.2 * scale, (int(rng.integers(1, 3000)), 2))
        tree, ours = cKDTree(points), Neighbours(points)
        for k in (1, 2, 9):
            _same_query(tree, ours, queries, k)
        _same_query(tree, ours, queries[0], min(9, len(points)))
        _same_query(tree, ours, queries[0])
        for bound in (rng.uniform(0.01, 0.5) * scale, rng.uniform(1.0, 3.0) * scale):
            _same_query(tree, ours, queries, distance_upper_bound=float(bound))


@pytest.mark.parametrize("seed", range(3))
def test_the_points_within_a_radius_are_cKDTrees(seed, paths):
    rng = np.random.default_rng(100 + seed)
    for _ in range(30):
        scale = float(rng.choice([10.0, 4096.0, 1e5]))
        points = rng.uniform(-scale, scale, (int(rng.integers(1, 2000)), 2))
        radius = float(rng.uniform(0.001, 0.3) * scale)
        tree, ours = cKDTree(points), Neighbours(points)
        for queries in (points, rng.uniform(-scale, scale, (50, 2))):
            got = ours.query_ball_point(queries, radius)
            assert [sorted(near) for near in tree.query_ball_point(queries, radius)] == list(got)
        assert sorted(tree.query_ball_point(points[0], radius)) == ours.query_ball_point(points[0], radius)


def test_boundaries_ties_and_missing_neighbours(paths):
    """On a grid of integers: a point exactly at the radius is within it, one exactly at the upper
    bound is not (cKDTree's <= and <); the distances of ties are cKDTree's, their indices ascending;
    fewer points than k give inf and n."""
    grid = np.array([[x, y] for x in range(12) for y in range(12)], dtype=float)
    queries = np.random.default_rng(7).integers(-2, 26, (4000, 2)) / 2.0
    tree, ours = cKDTree(grid), Neighbours(grid)
    for radius in (1.0, 2.0, np.sqrt(2.0), 2.5):
        assert [sorted(near) for near in tree.query_ball_point(queries, radius)] == list(
            ours.query_ball_point(queries, radius))
    for k in (1, 2, 9):
        distance, index = ours.query(queries, k)
        np.testing.assert_array_equal(distance, tree.query(queries, k)[0])
        d2 = ((queries[:, None, :] - grid[index.reshape(len(queries), -1)]) ** 2).sum(axis=2)
        ties = np.diff(d2, axis=1) == 0
        assert np.all(np.diff(index.reshape(len(queries), -1), axis=1)[ties] > 0)
    for bound in (1.0, 1.5, 2.0):
        np.testing.assert_array_equal(ours.query(queries, distance_upper_bound=bound)[0],
                                      tree.query(queries, distance_upper_bound=bound)[0])
    few = Neighbours(grid[:3])
    distance, index = few.query(queries[:5], 5)
    assert np.isinf(distance[:, 3:]).all() and (index[:, 3:] == 3).all()
    empty = Neighbours(np.zeros((0, 2)))
    assert empty.query([1.0, 2.0]) == cKDTree(np.zeros((0, 2))).query([1.0, 2.0])


@pytest.mark.parametrize("call", [lambda near: near.query([np.nan, 1.0]),
                                  lambda near: near.query([[np.inf, 0.0]], distance_upper_bound=3.0),
                                  lambda near: near.query_ball_point([[1.0, np.nan]], 1.0)])
def test_what_is_not_finite_is_refused_as_cKDTree_refuses_it(call):
    points = np.array([[0.0, 0.0], [1.0, 1.0]])
    for kind in (cKDTree, Neighbours):
        with pytest.raises(ValueError, match="must be finite"):
            call(kind(points))
        with pytest.raises(ValueError, match="must be finite"):
            kind(np.array([[np.nan, 1.0]]))
