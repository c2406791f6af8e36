"""Exact nearest-neighbour and radius look-ups among points of the image plane, without scipy.

`Neighbours(points)` answers what scipy's `cKDTree(points)` answers for the look-ups the marker
stage makes (`query` with k >= 1 and an optional `distance_upper_bound`, `query_ball_point` with
one radius; Euclidean, eps = 0), from the same arithmetic: a distance is sqrt(dx * dx + dy * dy)
of the query minus the point, a neighbour within an upper bound u has dx * dx + dy * dy < u * u,
and a point within radius r of a query dx * dx + dy * dy <= r * r. So the distances are
cKDTree's to the last bit and so are the neighbours, but among points exactly as far from a query
(ties), where the one of the lowest index comes first (cKDTree's order there is its tree's).

Why not cKDTree: importing scipy.spatial costs a marker job ~0.1-0.2 CPU s (it loads scipy.sparse,
scipy.linalg and qhull with it) for look-ups among a few hundred points (issue 40, per-job
overhead). Look-ups of up to `CHUNK_PAIRS` pairs (queries x points: nearly all of an image's)
compare every pair at once; larger ones without a bound in chunks, and those with a bound or a
radius only the points in the 3 x 3 cells of a grid as wide as the bound about the query's cell, so
that identify's coarse counts (up to 2e6 moved predictions against the detections) stay linear.
"""

from __future__ import annotations

import numpy as np

#: Pairs (query, point) compared at once where every pair is compared: bounds the temporaries (~2 MB).
CHUNK_PAIRS = 1 << 16
#: Grids of more cells than this (points and queries absurdly far apart for the bound) compare every
#: pair instead: the cells' numbers stay exact in int64.
MAX_CELLS = 2.0 ** 60
#: A grid cell is this much wider than the bound, so that rounding in the cells' indexes never
#: leaves out a point within the bound (the comparisons themselves are exact).
_CELL_MARGIN = 1.0 + 1e-9


class Neighbours:
    """Look-ups among points (n, 2) (copied as float64), cKDTree's interface (module docstring); points
    or queries that are not finite raise cKDTree's ValueError."""

    def __init__(self, points):
        self.data = np.array(points, dtype=float).reshape(-1, 2)
        self.n = len(self.data)
        if not np.isfinite(self.data).all():
            raise ValueError("data must be finite, check for nan or inf values")

    def query(self, x, k: int = 1, distance_upper_bound: float = np.inf):
        """(distances, indices) of the k nearest points to each query of x (m, 2), nearest first:
        (m,) each for k = 1, (m, k) for k > 1; for one query x (2,) a scalar each, or (k,). A
        neighbour missing (fewer than k points, or none nearer than distance_upper_bound) has
        distance inf and index n."""
        x, queries = _queries(x)
        k, bound = int(k), float(distance_upper_bound)
        if k == 1 and len(queries) * self.n <= CHUNK_PAIRS:
            squared, index = self._nearest_of_all(queries, bound)
        else:
            squared, index = self._nearest_squared(queries, k, bound)
            if k == 1:
                squared, index = squared[:, 0], index[:, 0]
        distance = np.sqrt(squared)
        if x.ndim == 1:
            return distance[0], index[0]
        return distance, index

    def query_ball_point(self, x, r: float):
        """The indices (ascending) of the points within r of x (2,): a list; for queries x (m, 2), an
        object array (m,) of such lists."""
        x, queries = _queries(x)
        r = float(r)
        if len(queries) * self.n <= CHUNK_PAIRS:  # every pair at once, in (query, point) order
            qi, pj = np.nonzero(_squared_distances(queries, self.data) <= r * r)
        else:
            pairs = [(np.repeat(met, counts)[inside], pj[inside]) for met, counts, pj, squared in
                     self._grid_pairs(queries, r) for inside in [squared <= r * r]]
            qi = np.concatenate([q for q, _ in pairs] or [np.zeros(0, dtype=np.intp)])
            pj = np.concatenate([p for _, p in pairs] or [np.zeros(0, dtype=np.intp)])
            order = np.lexsort((pj, qi))
            qi, pj = qi[order], pj[order]
        if x.ndim == 1:
            return pj.tolist()
        points = pj.tolist()
        ends = np.cumsum(np.bincount(qi, minlength=len(queries))).tolist()
        out = np.empty(len(queries), dtype=object)
        out[:] = [points[start:end] for start, end in zip([0, *ends[:-1]], ends)]
        return out

    def _nearest_of_all(self, queries: np.ndarray, bound: float) -> tuple[np.ndarray, np.ndarray]:
        """(m,) squared distances and indices of the nearest point (the lower index of equals) nearer
        than bound to each of queries (m, 2), from every pair at once; inf and n where none is."""
        if self.n == 0:
            return np.full(len(queries), np.inf), np.full(len(queries), self.n, dtype=np.intp)
        block = _squared_distances(queries, self.data)
        index = np.argmin(block, axis=1)  # the first of equal minima: the lower index
        squared = block[np.arange(len(queries)), index]
        missing = ~(squared < bound * bound)
        if missing.any():
            squared[missing], index[missing] = np.inf, self.n
        return squared, index

    def _nearest_squared(self, queries: np.ndarray, k: int, bound: float) -> tuple[np.ndarray, np.ndarray]:
        """(m, k) squared distances and indices of the k nearest points (ties: the lower index first)
        nearer than bound to each of queries (m, 2); inf and n where missing."""
        squared = np.full((len(queries), k), np.inf)
        index = np.full((len(queries), k), self.n, dtype=np.intp)
        if self.n == 0 or len(queries) == 0:
            return squared, index
        if np.isfinite(bound):
            if k != 1:
                raise ValueError("Neighbours.query: a distance_upper_bound is only taken with k = 1")
            return self._nearest_within(queries, bound, squared, index)
        rows = max(CHUNK_PAIRS // self.n, 1)
        for start in range(0, len(queries), rows):
            block = _squared_distances(queries[start:start + rows], self.data)  # (rows, n)
            if k == 1:
                nearest = np.argmin(block, axis=1)[:, None]  # the first of equal minima: the lower index
            else:
                nearest = np.argsort(block, axis=1, kind="stable")[:, :k]
            taken = nearest.shape[1]
            index[start:start + rows, :taken] = nearest
            squared[start:start + rows, :taken] = np.take_along_axis(block, nearest, axis=1)
        return squared, index

    def _nearest_within(self, queries: np.ndarray, bound: float, squared: np.ndarray,
                        index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`_nearest_squared` for k = 1 (squared, index (m, 1), filled in) and a finite bound."""
        best, best_index = squared[:, 0], index[:, 0]
        for met, counts, pj, distance in self._grid_pairs(queries, bound):
            starts = np.cumsum(counts) - counts
            distance = np.where(distance < bound * bound, distance, np.inf)
            nearest = np.minimum.reduceat(distance, starts)
            lowest = np.minimum.reduceat(np.where(distance == np.repeat(nearest, counts), pj, self.n), starts)
            lowest = np.where(np.isfinite(nearest), lowest, self.n)
            better = (nearest < best[met]) | ((nearest == best[met]) & (lowest < best_index[met]))
            best[met[better]], best_index[met[better]] = nearest[better], lowest[better]
        return squared, index

    def _grid_pairs(self, queries: np.ndarray, reach: float):
        """Per column offset (-1, 0, 1) of a grid of cells `reach` wide: the queries (k,) of queries
        (m, 2) that meet a point in the 3 cells of that column about their own cell, their numbers of
        such points (k,), and per pair (each query's together) the point and the squared distance.
        Every pair closer than reach is among them."""
        if self.n == 0 or len(queries) == 0 or not reach > 0:
            return
        cell = reach * _CELL_MARGIN
        point_cells, query_cells = np.floor(self.data / cell), np.floor(queries / cell)
        low = np.minimum(point_cells.min(axis=0), query_cells.min(axis=0)) - 1
        high = np.maximum(point_cells.max(axis=0), query_cells.max(axis=0)) + 1
        rows, cells = high[1] - low[1] + 1, (high[0] - low[0] + 1) * (high[1] - low[1] + 1)
        if not cells < MAX_CELLS:  # points and queries too far apart to number the cells: every pair
            yield from _all_pairs(queries, self.data)
            return
        keys = ((point_cells[:, 0] - low[0]) * rows + (point_cells[:, 1] - low[1])).astype(np.int64)
        order = np.argsort(keys, kind="stable")  # a column's cells are consecutive numbers
        keys = keys[order]
        below = ((query_cells[:, 0] - low[0]) * rows + (query_cells[:, 1] - low[1] - 1)).astype(np.int64)
        table = np.searchsorted(keys, np.arange(int(cells) + 1)) if cells <= 4 * len(below) + 4096 else None
        for dx in (-1, 0, 1):
            lowest, highest = below + dx * int(rows), below + (dx * int(rows) + 3)
            if table is None:
                start, end = np.searchsorted(keys, lowest, "left"), np.searchsorted(keys, highest, "left")
            else:
                start, end = table[lowest], table[highest]
            counts = end - start
            met = np.flatnonzero(counts)
            start, counts = start[met], counts[met]
            offsets = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)
            pj = order[np.repeat(start, counts) + offsets]
            yield met, counts, pj, _pair_distances(np.repeat(queries[met], counts, axis=0), self.data[pj])


def _pair_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(k,) dx * dx + dy * dy of a - b, rows of (k, 2) each."""
    dx, dy = a[:, 0] - b[:, 0], a[:, 1] - b[:, 1]
    return dx * dx + dy * dy


def _queries(x) -> tuple[np.ndarray, np.ndarray]:
    """(x as float64, its queries (m, 2)); cKDTree's ValueError where one is not finite."""
    x = np.asarray(x, dtype=float)
    if not np.isfinite(x).all():
        raise ValueError("'x' must be finite, check for nan or inf values")
    return x, x.reshape(-1, 2)


def _all_pairs(queries: np.ndarray, points: np.ndarray):
    """`Neighbours._grid_pairs`' arrays for every pair of queries (m, 2) and points (n, 2), in chunks of
    about CHUNK_PAIRS pairs."""
    rows = max(CHUNK_PAIRS // len(points), 1)
    every = np.arange(len(points))
    for start in range(0, len(queries), rows):
        met = np.arange(start, min(start + rows, len(queries)))
        counts = np.full(len(met), len(points))
        yield met, counts, np.tile(every, len(met)), _squared_distances(queries[met], points).reshape(-1)


def _squared_distances(queries: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(m, n) dx * dx + dy * dy of every query (m, 2) minus every point (n, 2)."""
    dx = queries[:, 0:1] - points[None, :, 0]
    dy = queries[:, 1:2] - points[None, :, 1]
    return dx * dx + dy * dy
