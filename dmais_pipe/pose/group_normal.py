"""The normal equations of a flight group's rig adjustment (pose.mounting) in blocks, solved in time
linear in the frames.

Unknowns, in the order of the flat vectors: F frames of L each (a frame's pose and jitters), the rig's R
(deltas, focal changes), P points of 3. Each of the N observations' residuals (2) depends on l <= L of its
frame's unknowns (`local_cols`), r <= R of the rig's (`rig_cols`) and on its point. The normal matrix

    [[A,    Wr,   Wp ],
     [Wr^T, Hrr,  Hrp],
     [Wp^T, Hpr,  Hpp]]

has A block diagonal (F blocks L x L) and Hpp block diagonal (P blocks 3 x 3): a point is tied to
other unknowns only through the frames that see it. It is kept as those blocks, Wp as one (l, 3)
block per observation, and solved by eliminating one block-diagonal set and then the rest:

- the frames first (`FRAMES_FIRST`), leaving a dense system of the points and the rig (3P + R): a
  group hovering over the same few markers, where every frame sees every point;
- the points first (`POINTS_FIRST`), leaving the frames and the rig: the frames are tied only where
  they share a point, so that system is block diagonal where no point is seen by two frames and
  banded along a line of frames; it is factorised by blocks (no sharing) or as a band (LAPACK's
  banded Cholesky, the frames in the order of the narrowest band), and the rig's R unknowns last by
  their Schur complement.

`elimination` picks the cheaper by counting the work each needs. The blocks are assembled, and the frames
eliminated, by compiled loops over the observations and frames (_group.pyx: a frame's block by its
Cholesky factor, the frames' couplings summed by BLAS dsyrk). Both are exact: the solution and the
rig's block of the inverse equal those of a dense solve of the whole matrix to rounding
(tests/test_group_normal.py). The cost is linear in the frames for a fixed number of points per frame
and frames per point; the dense system of the frames-first order is of the points alone. Frames tied
over a band of b frames (a line: C0 sees the markers the forward camera saw ~17 frames before) give
a factor of F L (b + 1) L numbers (0.94 GiB at 10,000 frames of L = 18): beyond KEPT_FACTOR_BYTES it is
made a segment of frames at a time and not kept, each segment made again for the back substitution from
the factor's coupling to the segment before (`_FramesBand`), so that the memory is that of a segment and
the couplings whatever the frames; the memory they need is refused beyond FACTOR_BYTES.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
from scipy import linalg, sparse
from scipy.sparse import csgraph

from ..errors import DmaisError
from . import _group

FRAMES_FIRST, POINTS_FIRST = "frames first", "points first"
#: Numbers per chunk of frames where the frames-first order builds its dense system (chunk x L x (R + 3P)).
CHUNK_NUMBERS = 4_000_000
#: Up to this many numbers, the frames-first order keeps the frames' couplings between its two passes.
KEPT_NUMBERS = 30_000_000
#: The most memory the band factor of a points-first frames' system may take (bytes; `_FramesBand`).
FACTOR_BYTES = 1.0 * 2**30
#: Up to this many bytes, the frames' band factor is kept through a solve (`_FramesBand`); beyond, it is made
#: a segment of about SEGMENT_BYTES at a time, twice.
KEPT_FACTOR_BYTES = 256 * 2**20
SEGMENT_BYTES = 64 * 2**20
#: Points per chunk where the points-first order sums products over the points.
POINT_CHUNK = 50_000
#: Columns of the frames' band factor per block of its triangular solves (`_band_forward`).
SOLVE_BLOCK = 128
#: The most observations of a group: the largest C int, the type of the observations' columns and pairs
#: (GroupStructure: local_cols, rig_cols, pair_left, pair_right; half the memory of 64-bit ones).
INDEX_MAX = np.iinfo(np.intc).max


@dataclass(frozen=True)
class GroupStructure:
    """Which unknowns each observation touches, fixed for one adjustment, and the order of elimination.

    frame (N,) in [0, F); point (N,) in [0, P); local_cols (N, l) in [0, L) and rig_cols (N, r) in [0, R), C ints;
    by_frame (N,) the observations in frame order, frame_starts (F + 1,) each frame's first in it,
    slot (N,) an observation's place among its frame's (fewer than n_slots); frames_tied: whether some
    point is seen by two frames (the points-first frames' system is then not block diagonal); method:
    FRAMES_FIRST or POINTS_FIRST (`elimination`). For the points first, untied: point_frame (P,) the
    frame of each point and point_slot (P,) its place among that frame's points (fewer than
    n_point_slots); tied: band_rank (F,) each frame's place in the order that ties frames over the
    narrowest band, band the most places apart two tied frames are in it (`_banded_order`),
    pair_left, pair_right (M,) C ints, every ordered pair of observations of one point (each with itself
    too) whose left frame is not after its right one in that order, by the left frame's place, and
    within it by run: pair_runs (U + 1,) the first pair of each run of pairs of the same two frames
    and the same two sets of local columns (their products add up at the same places), and M."""

    n_frames: int
    local_size: int
    rig_size: int
    n_points: int
    frame: np.ndarray
    point: np.ndarray
    local_cols: np.ndarray
    rig_cols: np.ndarray
    by_frame: np.ndarray
    frame_starts: np.ndarray
    slot: np.ndarray
    n_slots: int
    frames_tied: bool
    method: str
    point_frame: np.ndarray
    point_slot: np.ndarray
    n_point_slots: int
    band_rank: np.ndarray
    band: int
    pair_left: np.ndarray
    pair_right: np.ndarray
    pair_runs: np.ndarray

    @property
    def size(self) -> int:
        return self.n_frames * self.local_size + self.rig_size + 3 * self.n_points


def group_structure(frame, point, local_cols, rig_cols, n_frames: int, local_size: int, rig_size: int,
                    n_points: int, method: str | None = None) -> GroupStructure:
    """The GroupStructure of N observations (its docstring), by `method` or `elimination`'s choice."""
    frame, point = np.asarray(frame, dtype=np.int64), np.asarray(point, dtype=np.int64)
    if len(frame) > INDEX_MAX:
        raise DmaisError(f"mounting: a group of {len(frame)} observations is too large to adjust at once; split it "
                         "into groups of fewer frames (frames.csv's group)")
    local_cols, rig_cols = (np.ascontiguousarray(cols, dtype=np.intc) for cols in (local_cols, rig_cols))
    by_frame = np.argsort(frame, kind="stable")
    frame_starts = np.searchsorted(frame[by_frame], np.arange(n_frames + 1))
    slot = np.empty(len(frame), dtype=np.int64)
    slot[by_frame] = np.arange(len(frame)) - frame_starts[frame[by_frame]]
    n_slots = int(np.diff(frame_starts).max(initial=0))
    counts = np.bincount(point, minlength=n_points)
    first_frame = np.full(n_points, -1)
    first_frame[point[::-1]] = frame[::-1]
    tied = bool((frame != first_frame[point]).any())  # a point seen by two frames
    method = method or elimination(n_frames, local_size, rig_size, n_points, local_cols.shape[1],
                                   float(np.sum(counts.astype(float)**2)), tied)
    if method not in (FRAMES_FIRST, POINTS_FIRST):
        raise ValueError(f"unknown elimination {method!r}")
    none, no_pair = np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.intc)
    points, pairs = (none, none, 0), (none, 0, no_pair, no_pair, none)
    if method == POINTS_FIRST and tied:
        pairs = _observation_pairs(frame, point, local_cols, counts, n_frames)
    elif method == POINTS_FIRST:
        points = _points_by_frame(first_frame, n_frames)
    return GroupStructure(n_frames, local_size, rig_size, n_points, frame, point, local_cols, rig_cols, by_frame,
                          frame_starts, slot, n_slots, tied, method, *points, *pairs)


def _points_by_frame(point_frame: np.ndarray, n_frames: int) -> tuple[np.ndarray, np.ndarray, int]:
    """GroupStructure's point_frame, point_slot and n_point_slots of points each seen by one frame."""
    order = np.argsort(point_frame, kind="stable")
    starts = np.searchsorted(point_frame[order], np.arange(n_frames + 1))
    point_slot = np.empty(len(point_frame), dtype=np.int64)
    point_slot[order] = np.arange(len(order)) - starts[point_frame[order]]
    return point_frame, point_slot, int(np.diff(starts).max(initial=0))


def elimination(n_frames: int, local_size: int, rig_size: int, n_points: int, l: int, n_pairs: int,
                tied: bool) -> str:
    """FRAMES_FIRST or POINTS_FIRST, whichever needs fewer operations (module docstring): the frames
    first build a dense (3P + R) system from every frame's L x (3P + R) block and factorise it; the
    points first build one l x l block per pair of observations of a point (n_pairs of them), and a
    sparse factorisation where frames share points (`tied`) costs a few times that."""
    dense = 3 * n_points + rig_size
    frames_first = float(n_frames) * local_size * dense**2 + dense**3 / 3.0
    points_first = n_pairs * 3.0 * l**2 * (4.0 if tied else 1.0)
    return FRAMES_FIRST if frames_first < points_first else POINTS_FIRST


def _observation_pairs(frame: np.ndarray, point: np.ndarray, local_cols: np.ndarray, counts: np.ndarray,
                       n_frames: int):
    """GroupStructure's band_rank, band, pair_left, pair_right and pair_runs."""
    order = np.argsort(point, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    repeat = counts[point[order]]
    left = np.repeat(order, repeat)
    within = np.arange(len(left)) - np.repeat(np.cumsum(repeat) - repeat, repeat)
    right = order[starts[point[left]] + within]
    rank, band = _banded_order(frame[left], frame[right], n_frames)
    upper = rank[frame[left]] <= rank[frame[right]]
    left, right = left[upper], right[upper]
    column_set = _row_sets(local_cols)
    n_sets = int(column_set.max(initial=0)) + 1
    key = ((rank[frame[left]] * n_frames + rank[frame[right]]) * n_sets + column_set[left]) * n_sets \
        + column_set[right]
    by_key = np.argsort(key, kind="stable")
    key = key[by_key]
    runs = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1], [True]]))
    return rank, band, left[by_key].astype(np.intc), right[by_key].astype(np.intc), runs


def _row_sets(cols: np.ndarray) -> np.ndarray:
    """(N,) each row's place among the distinct rows of cols (N, l) (non-negative) in their lexicographic
    order: np.unique(cols, axis=0)'s inverse, by one integer per row where they fit in 62 bits (numpy's
    unique of rows sorts them as records, most of group_structure's time on a line of 10,000 frames)."""
    base = int(cols.max(initial=0)) + 1
    if cols.shape[1] * np.log2(base) >= 62:
        return np.unique(cols, axis=0, return_inverse=True)[1].ravel()
    key = cols @ (base ** np.arange(cols.shape[1] - 1, -1, -1, dtype=np.int64))
    return np.unique(key, return_inverse=True)[1]


def _banded_order(left: np.ndarray, right: np.ndarray, n_frames: int) -> tuple[np.ndarray, int]:
    """(rank (F,), band): each frame's place in whichever order ties the frames over the narrower band,
    their own or the reverse Cuthill-McKee order of the frames tied by the pairs (left, right) (M,),
    and that band (the most places apart two tied frames are)."""
    left, right = np.divmod(np.unique(left * n_frames + right), n_frames)
    graph = sparse.csr_array((np.ones(len(left)), (left, right)), shape=(n_frames, n_frames))
    reordered = np.empty(n_frames, dtype=np.int64)
    reordered[csgraph.reverse_cuthill_mckee(graph, symmetric_mode=True)] = np.arange(n_frames)
    bands = [(int(np.abs(rank[left] - rank[right]).max(initial=0)), k, rank)
             for k, rank in enumerate((np.arange(n_frames), reordered))]
    band, _, rank = min(bands)
    return rank, band


@dataclass(frozen=True)
class GroupNormal:
    """The normal equations in blocks (module docstring): A (F, L, L), Wr (F, L, R), Hrr (R, R), Hpp (P, 3,
    3), Hpr (P, 3, R), Wp (N, l, 3) one block per observation (rows: its local_cols); the gradient b_local
    (F, L), b_rig (R,), b_point (P, 3)."""

    structure: GroupStructure
    A: np.ndarray
    Wr: np.ndarray
    Hrr: np.ndarray
    Hpp: np.ndarray
    Hpr: np.ndarray
    Wp: np.ndarray
    b_local: np.ndarray
    b_rig: np.ndarray
    b_point: np.ndarray

    def blocks(self) -> tuple[np.ndarray, ...]:
        """(A, Wr, b_local, Hrr, Hpp, Hpr, Wp, b_rig, b_point): the order of _group's assemblies."""
        return self.A, self.Wr, self.b_local, self.Hrr, self.Hpp, self.Hpr, self.Wp, self.b_rig, self.b_point

    @property
    def gradient(self) -> np.ndarray:
        """(F L + R + 3P,) the flat gradient."""
        return np.concatenate([self.b_local.ravel(), self.b_rig, self.b_point.ravel()])

    @contextmanager
    def damped(self, damping: float) -> Iterator[GroupNormal]:
        """The equations with every diagonal raised by damping x itself (Levenberg-Marquardt), in place while the
        context lasts: the diagonals are put back as they were after it (A and Hpp are not copied; a line of
        10,000 frames: 55 MB)."""
        diagonals = [(M, index, M[index]) for M, index in (
            (self.A, (slice(None), *np.diag_indices(self.A.shape[1]))),
            (self.Hpp, (slice(None), *np.diag_indices(3))), (self.Hrr, np.diag_indices(len(self.Hrr))))]
        try:
            for M, index, diagonal in diagonals:
                M[index] = diagonal * (1.0 + damping)
            yield self
        finally:
            for M, index, diagonal in diagonals:
                M[index] = diagonal

    def dense(self) -> np.ndarray:
        """(n, n) the whole normal matrix, n = F L + R + 3P: for tests and small groups only."""
        s = self.structure
        F, L, R, P = s.n_frames, s.local_size, s.rig_size, s.n_points
        n, first = s.size, F * L
        N = np.zeros((n, n))
        frames = np.arange(F)[:, None] * L + np.arange(L)
        N[frames[:, :, None], frames[:, None, :]] = self.A
        N[frames[:, :, None], first + np.arange(R)] = self.Wr
        points = first + R + 3 * np.arange(P)[:, None] + np.arange(3)
        N[points[:, :, None], points[:, None, :]] = self.Hpp
        N[first:first + R, points.ravel()] = self.Hpr.reshape(3 * P, R).T
        N[first:first + R, first:first + R] = self.Hrr
        rows = s.frame[:, None] * L + s.local_cols
        np.add.at(N, (rows[:, :, None], points[s.point][:, None, :]), self.Wp)
        upper = np.triu(N, 1)
        return np.triu(N) + upper.T


def assemble(structure: GroupStructure, local_J, rig_J, point_J, e) -> GroupNormal:
    """J^T J and J^T e of N observations' whitened residuals e (N, 2) (two each) with the compact Jacobians local_J
    (N, 2, l), rig_J (N, 2, r) and point_J (N, 2, 3) (columns: structure's local_cols, rig_cols, the
    point's 3); the priors are the caller's to add. One compiled loop over the observations (_group)."""
    if local_J.shape[1] != 2:
        raise ValueError(f"two residuals per observation, got {local_J.shape[1]}")
    s = structure
    normal = zero_normal(s)
    blocks = map(np.ascontiguousarray, (s.local_cols, s.rig_cols, local_J, rig_J, point_J, e))
    _group.assemble(s.frame, s.point, *blocks, *normal.blocks())
    return normal


def zero_normal(structure: GroupStructure) -> GroupNormal:
    """Normal equations of `structure` with every block 0 (Wp unset), for a compiled assembly to add to."""
    s = structure
    F, L, R, P = s.n_frames, s.local_size, s.rig_size, s.n_points
    return GroupNormal(s, np.zeros((F, L, L)), np.zeros((F, L, R)), np.zeros((R, R)), np.zeros((P, 3, 3)),
                       np.zeros((P, 3, R)), np.empty((len(s.frame), s.local_cols.shape[1], 3)), np.zeros((F, L)),
                       np.zeros(R), np.zeros((P, 3)))


def _summed(values: np.ndarray, index: np.ndarray, size: int) -> np.ndarray:
    """(size,) the sums of `values` at their flat `index` (both broadcast to one shape)."""
    values, index = np.broadcast_arrays(values, index)
    return np.bincount(index.ravel(), weights=values.ravel(), minlength=size)


# ------------------------------------------------------------------------------ the solution


def solve(normal: GroupNormal, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The solution (F L + R + 3P, k) of the normal equations for right sides `right` (F L + R + 3P, k),
    and the rig's block (R, R) of the inverse normal matrix, in the structure's order of elimination;
    DmaisError where a frame, a point or the whole is not determined.

    Every step is exact under a scaling of the unknowns by powers of two (Cholesky factors, triangular
    solves, sums of products: each result is scaled as its operands, with the same roundings; `_inverted`
    scales a block's LU by its own diagonal): a group's mix of radians, metres and a long focal length,
    condition numbers of 1e13, gives the solution a unit diagonal would (tests/test_group_normal.py), without
    a scaled copy of the equations."""
    s = normal.structure
    F, L, R = s.n_frames, s.local_size, s.rig_size
    right = np.asarray(right, dtype=float).reshape(s.size, -1 if np.size(right) else 0)
    k = right.shape[1]
    if k == 0:  # the rig's inverse alone: one zero right side keeps every shape
        right = np.zeros((s.size, 1))
    r_local = right[:F * L].reshape(F, L, -1)
    r_rig, r_point = right[F * L:F * L + R], right[F * L + R:].reshape(s.n_points, 3, -1)
    x, rig_inverse = _solved(normal, r_local, r_rig, r_point)
    return x[:, :k], rig_inverse


def rig_columns(normal: GroupNormal) -> tuple[np.ndarray, np.ndarray]:
    """(F L + R + 3P, R) the inverse normal matrix's columns of the rig's unknowns and (R, R) their rows: `solve`
    of the rig's unit columns, without making them (the points' (P, 3, R) zeros are not made where the points
    are eliminated first)."""
    s = normal.structure
    F, L, R = s.n_frames, s.local_size, s.rig_size
    r_point = None if s.method == POINTS_FIRST else np.zeros((s.n_points, 3, R))
    return _solved(normal, np.zeros((F, L, R)), np.eye(R), r_point)


def _solved(normal: GroupNormal, r_local, r_rig, r_point) -> tuple[np.ndarray, np.ndarray]:
    """`solve`'s (solution, rig inverse) of the right sides r_local (F, L, k), r_rig (R, k), r_point (P, 3, k)
    (None: zeros, where the points are eliminated first); the points' part written in place."""
    s = normal.structure
    F, L, R = s.n_frames, s.local_size, s.rig_size
    x = np.empty((s.size, r_rig.shape[1]))
    x_point = x[F * L + R:].reshape(s.n_points, 3, -1)
    if s.method == FRAMES_FIRST:
        x_local, x_rig, x_point[:], rig_inverse = _frames_first(normal, r_local, r_rig, r_point)
    else:
        x_local, x_rig, rig_inverse = _points_first(normal, r_local, r_rig, r_point, x_point)
    x[:F * L], x[F * L:F * L + R] = x_local.reshape(F * L, -1), x_rig
    return x, rig_inverse


def _inverted(blocks: np.ndarray, what: str) -> np.ndarray:
    """(n, b, b) the inverses of SPD blocks; DmaisError naming `what` where one is singular. Each block's
    LU is of the block scaled to a unit diagonal by powers of two (its pivots are then those of any
    scaling of the unknowns)."""
    if blocks.shape[1:] == (3, 3):
        return _inverted_3x3(blocks, what)
    scale = _unit_scale(np.diagonal(blocks, axis1=1, axis2=2))[:, :, None]  # (n, b, 1)
    try:
        return np.linalg.inv(blocks * scale * np.swapaxes(scale, 1, 2)) * scale * np.swapaxes(scale, 1, 2)
    except np.linalg.LinAlgError:
        raise _undetermined(what) from None


def _unit_scale(diagonal: np.ndarray) -> np.ndarray:
    """The powers of two nearest 1 / sqrt(diagonal) (1 where it is not above 0), of the diagonal's shape."""
    return np.exp2(-np.round(0.5 * np.log2(np.where(diagonal > 0, diagonal, 1.0))))


def _inverted_3x3(blocks: np.ndarray, what: str) -> np.ndarray:
    """(n, 3, 3) inverses of symmetric 3 x 3 blocks by their adjugates (rows: cross products of columns);
    singular where the determinant is below 1e-13 of the diagonal's product (its bound for an SPD block;
    their ratio is that of any scaling of the unknowns)."""
    c0, c1, c2 = blocks[:, :, 0], blocks[:, :, 1], blocks[:, :, 2]
    adjugate = np.stack([np.cross(c1, c2), np.cross(c2, c0), np.cross(c0, c1)], axis=1)
    determinant = np.einsum("ni,ni->n", c0, adjugate[:, 0])
    if not (determinant > 1e-13 * np.prod(np.diagonal(blocks, axis1=1, axis2=2), axis=1)).all():
        raise _undetermined(what)
    return adjugate / determinant[:, None, None]


def _undetermined(what: str) -> DmaisError:
    return DmaisError(f"mounting: {what} is not determined by its observations (too few or collinear points)")


def _cho_factor(matrix: np.ndarray):
    try:
        return linalg.cho_factor(matrix)
    except linalg.LinAlgError:
        raise DmaisError("mounting: the group's normal equations are singular") from None


def _frames_first(normal: GroupNormal, r_local, r_rig, r_point):
    """Eliminate the frames' blocks, solve the dense (R + 3P) system of the rig and the points (compiled
    loops over the frames, _group; `_frames_first_numpy` is their reference). Right sides without a
    frames' part (the rig's columns of the inverse) are not reduced: W^T A^-1 0 is 0."""
    s = normal.structure
    F, L, R, P = s.n_frames, s.local_size, s.rig_size, s.n_points
    G = R + 3 * P
    system = _global_system(normal)
    y = np.concatenate([r_rig, r_point.reshape(3 * P, -1)])
    r_local, factors = np.ascontiguousarray(r_local), normal.A.copy()
    local_cols = np.ascontiguousarray(s.local_cols)
    n_shared, width = _group.local_layout(local_cols, factors)
    stacked = np.empty((n_shared * max(1, min(F, CHUNK_NUMBERS // (L * G))), G))
    coupling = (np.ascontiguousarray(normal.Wr), np.ascontiguousarray(normal.Wp), s.by_frame, s.frame_starts,
                local_cols, s.point, n_shared, width)
    r_reduced, y_reduced = (r_local, y) if r_local.any() else (np.empty((F, L, 0)), np.empty((G, 0)))
    if _group.frames_first_reduction(factors, *coupling, r_reduced, system, y_reduced, stacked) >= 0:
        raise _undetermined("a frame's pose")
    system = np.tril(system) + np.tril(system, -1).T  # dsyrk updated the lower triangle
    factor = _cho_factor(system)
    x_global = linalg.cho_solve(factor, y)
    rig_inverse = linalg.cho_solve(factor, np.eye(G)[:, :R])[:R]
    x_local = np.empty_like(r_local)
    _group.frames_first_back(factors, *coupling, r_local, np.ascontiguousarray(x_global), x_local)
    return x_local, x_global[:R], x_global[R:].reshape(P, 3, -1), rig_inverse


def _global_system(normal: GroupNormal) -> np.ndarray:
    """(R + 3P, R + 3P) the normal matrix's rows and columns of the rig and the points."""
    s = normal.structure
    R, P = s.rig_size, s.n_points
    G = R + 3 * P
    system = np.zeros((G, G))
    system[:R, :R] = normal.Hrr
    points = R + 3 * np.arange(P)[:, None] + np.arange(3)
    system[points[:, :, None], points[:, None, :]] = normal.Hpp
    system[points.ravel()[:, None], np.arange(R)] = normal.Hpr.reshape(3 * P, R)
    system[:R, R:] = system[R:, :R].T
    return system


def _frames_first_numpy(normal: GroupNormal, r_local, r_rig, r_point):
    """`_frames_first` by numpy's products of the frames' inverted blocks and dense couplings, in chunks of
    frames: the compiled loops' reference (tests/test_group_normal.py)."""
    s = normal.structure
    F, L, R, P = s.n_frames, s.local_size, s.rig_size, s.n_points
    A_inv = _inverted(normal.A, "a frame's pose")
    G = R + 3 * P
    system = _global_system(normal)
    y = np.concatenate([r_rig, r_point.reshape(3 * P, -1)])
    chunks = np.array_split(np.arange(F), min(F, -(-F * L * G // CHUNK_NUMBERS)))
    kept = [] if F * L * G <= KEPT_NUMBERS else None  # the couplings, built once where they fit
    for chunk in chunks:
        W = _dense_coupling(normal, chunk)  # (c, L, G)
        A_inv_W = A_inv[chunk] @ W
        system -= W.reshape(-1, G).T @ A_inv_W.reshape(-1, G)
        y -= A_inv_W.reshape(-1, G).T @ r_local[chunk].reshape(len(chunk) * L, -1)
        if kept is not None:
            kept.append(W)
    factor = _cho_factor(system)
    x_global = linalg.cho_solve(factor, y)
    rig_inverse = linalg.cho_solve(factor, np.eye(G)[:, :R])[:R]
    x_local = np.empty_like(r_local)
    for k, chunk in enumerate(chunks):
        W = kept[k] if kept is not None else _dense_coupling(normal, chunk)
        x_local[chunk] = A_inv[chunk] @ (r_local[chunk] - W @ x_global)
    return x_local, x_global[:R], x_global[R:].reshape(P, 3, -1), rig_inverse


def _dense_coupling(normal: GroupNormal, chunk: np.ndarray) -> np.ndarray:
    """(c, L, R + 3P) the frames' rows of the normal matrix beside their own blocks, of the frames
    `chunk` (c,) (consecutive)."""
    s = normal.structure
    L, R, G = s.local_size, s.rig_size, s.rig_size + 3 * s.n_points
    rows = s.by_frame[s.frame_starts[chunk[0]]:s.frame_starts[chunk[-1] + 1]]
    index = ((s.frame[rows] - chunk[0])[:, None, None] * L + s.local_cols[rows][:, :, None]) * G \
        + R + 3 * s.point[rows][:, None, None] + np.arange(3)
    W = _summed(normal.Wp[rows], index, len(chunk) * L * G).reshape(len(chunk), L, G)
    W[:, :, :R] = normal.Wr[chunk]
    return W


def _points_first(normal: GroupNormal, r_local, r_rig, r_point, x_point):
    """Eliminate the points' blocks, then solve the frames' and the rig's system (module docstring): (x_local,
    x_rig, the rig's inverse), the points' solution written into x_point (P, 3, k); r_point None: zeros."""
    s = normal.structure
    F, L, R, P = s.n_frames, s.local_size, s.rig_size, s.n_points
    Hpp_inv = _inverted(normal.Hpp, "a point")
    S_rr, y_rig = _rig_reduced(normal, Hpp_inv, r_rig, r_point)
    if s.frames_tied:
        S_fr, y_local, W_point = _tied_reduction(normal, Hpp_inv, r_point, r_local)
        x_local, x_rig, factor = _tied_frames_solved(_FramesBand(normal, Hpp_inv), S_fr, y_local, S_rr, y_rig)
    else:
        blocks, S_fr, y_local, W_point = _untied_reduction(normal, Hpp_inv, r_point, r_local)
        inverse = _inverted(blocks, "a frame's pose")
        solved = inverse @ np.concatenate([S_fr, y_local], axis=2)  # one pass for both
        Z, frames_y = solved[:, :, :R], solved[:, :, R:]  # (F, L, R), (F, L, k)
        factor = _cho_factor(S_rr - S_fr.reshape(F * L, R).T @ Z.reshape(F * L, R))
        x_rig = linalg.cho_solve(factor, y_rig - S_fr.reshape(F * L, R).T @ frames_y.reshape(F * L, -1))
        x_local = frames_y - Z @ x_rig
    x_point[:] = 0.0
    _points_back(normal, Hpp_inv, r_point, x_rig, W_point(x_local, x_point))
    return x_local, x_rig, linalg.cho_solve(factor, np.eye(R))


def _rig_reduced(normal: GroupNormal, Hpp_inv: np.ndarray, r_rig: np.ndarray, r_point: np.ndarray):
    """(S_rr (R, R), y_rig (R, k)): Hrr and r_rig (R, k) less Hpr^T Hpp_inv (Hpr, r_point) summed over the
    points, POINT_CHUNK at a time (their (P, 3, R) products are not held); Hpp_inv (P, 3, 3), r_point (P, 3, k)."""
    R = normal.structure.rig_size
    S_rr, y_rig = normal.Hrr.copy(), np.array(r_rig, dtype=float)
    for chunk in _point_chunks(normal.structure):
        coupled = normal.Hpr[chunk].reshape(-1, R).T
        moved = Hpp_inv[chunk] @ (normal.Hpr[chunk] if r_point is None else
                                  np.concatenate([normal.Hpr[chunk], r_point[chunk]], axis=2))
        if r_point is None:
            S_rr -= coupled @ moved.reshape(-1, R)
            continue
        S_rr -= coupled @ moved[:, :, :R].reshape(-1, R)
        y_rig -= coupled @ moved[:, :, R:].reshape(len(coupled.T), -1)
    return S_rr, y_rig


def _points_back(normal: GroupNormal, Hpp_inv, r_point, x_rig, moved: np.ndarray) -> np.ndarray:
    """(P, 3, k) the points' solution Hpp_inv (r_point - Hpr x_rig - moved) from the rig's x_rig (R, k) and the
    frames' share moved (P, 3, k) (overwritten by it), POINT_CHUNK points at a time; r_point None: zeros."""
    for chunk in _point_chunks(normal.structure):
        moved[chunk] = Hpp_inv[chunk] @ ((0.0 if r_point is None else r_point[chunk])
                                         - normal.Hpr[chunk] @ x_rig - moved[chunk])
    return moved


def _point_chunks(structure: GroupStructure):
    """Slices of the points, POINT_CHUNK each."""
    n = structure.n_points
    return (slice(start, min(start + POINT_CHUNK, n)) for start in range(0, n, POINT_CHUNK))


def _tied_frames_solved(band: _FramesBand, S_fr, y_local, S_rr, y_rig):
    """(x_local (F, L, k), x_rig (R, k), the Cholesky factor of the rig's Schur complement) of the tied frames'
    system and the rig's, from the frames' band factor L L^T (`_FramesBand`): with Y = L^-1 S_fr and w = L^-1
    y_local (one forward pass), the rig's complement is S_rr - Y^T Y and x_local = L^-T (w - Y x_rig) (one
    backward pass); S_fr (F, L, R), y_local (F, L, k), S_rr (R, R), y_rig (R, k)."""
    F, L, R = S_fr.shape
    forward = band.forward(np.concatenate([S_fr, y_local], axis=2).reshape(F * L, -1))
    Y, w = forward[:, :R], forward[:, R:]
    factor = _cho_factor(S_rr - Y.T @ Y)
    x_rig = linalg.cho_solve(factor, y_rig - Y.T @ w)
    return band.backward(w - Y @ x_rig).reshape(F, L, -1), x_rig, factor


def _untied_reduction(normal: GroupNormal, Hpp_inv, r_point, r_local):
    """The frames' system with the points eliminated where each point is seen by one frame: its
    diagonal blocks (F, L, L), its coupling to the rig S_fr (F, L, R), the right sides y (F, L, k), and
    the function x_local (F, L, k) -> (P, 3, k) of the points' coupling Wp^T x. Each frame's points
    are stacked in their slots (zeros up to n_point_slots): products of (L, 3 n_point_slots) blocks."""
    s = normal.structure
    F, L, P, slots = s.n_frames, s.local_size, s.n_points, s.n_point_slots
    index = (s.point[:, None, None] * L + s.local_cols[:, :, None]) * 3 + np.arange(3)
    W = _summed(normal.Wp, index, P * L * 3).reshape(P, L, 3)  # each point's coupling to its frame

    def stacked(values):  # (P, a, b) -> (F, slots, a, b)
        out = np.zeros((F, slots) + values.shape[1:])
        out[s.point_frame, s.point_slot] = values
        return out

    W_stack = stacked(W).transpose(0, 2, 1, 3).reshape(F, L, 3 * slots)
    V_stack = stacked(W @ Hpp_inv).transpose(0, 2, 1, 3).reshape(F, L, 3 * slots)
    blocks = normal.A - V_stack @ W_stack.transpose(0, 2, 1)
    S_fr = normal.Wr - V_stack @ stacked(normal.Hpr).reshape(F, 3 * slots, -1)
    y_local = r_local if r_point is None else r_local - V_stack @ stacked(r_point).reshape(F, 3 * slots, -1)

    def W_point(x_local, out):  # (F, L, k) -> out (P, 3, k), Wp^T x_local
        out[:] = W.transpose(0, 2, 1) @ x_local[s.point_frame]
        return out

    return blocks, S_fr, y_local, W_point


def _tied_reduction(normal: GroupNormal, Hpp_inv, r_point, r_local):
    """As `_untied_reduction` where frames share points, but without the frames' system (`_FramesBand` makes
    its band): S_fr = Wr less, and y_local = r_local less, the sums over the observations i of a point p of
    Wp_i Hpp_inv_p (Hpr_p, r_point_p) at the rows of i's local unknowns, and x_local -> Wp^T x_local summed per
    point, each by one compiled loop over the observations (_group; nothing of the observations' size held)."""
    s = normal.structure
    Hpp_inv = np.ascontiguousarray(Hpp_inv)

    def moved(coupled):  # (P, 3, q) -> (F, L, q)
        out = np.zeros((s.n_frames, s.local_size, coupled.shape[2]))
        _group.frames_from_points(s.frame, s.point, s.local_cols, normal.Wp, Hpp_inv, np.ascontiguousarray(coupled),
                                  out)
        return out

    S_fr = normal.Wr - moved(normal.Hpr)
    y_local = r_local if r_point is None or not r_point.any() else r_local - moved(r_point)

    def W_point(x_local, out):  # (F, L, k) -> out (P, 3, k) (zeros) plus Wp^T x_local
        _group.points_from_frames(s.frame, s.point, s.local_cols, normal.Wp, np.ascontiguousarray(x_local), out)
        return out

    return S_fr, y_local, W_point


def _band_rows(structure: GroupStructure) -> np.ndarray:
    """(F, L) the rows of each frame's unknowns in the frames' system ordered by structure.band_rank."""
    L = structure.local_size
    return structure.band_rank[:, None] * L + np.arange(L)


class _FramesBand:
    """The tied frames' system (the points eliminated) as its band's Cholesky factor L L^T, in the order of
    structure.band_rank (the narrowest band), made a segment of consecutive frames at a time: LAPACK's banded
    Cholesky of the segment's band (`_frames_band`) less the previous segment's share, the factor's coupling
    to the next segment by a triangular solve (`_segment_factor`). Where the whole factor would need more than
    KEPT_FACTOR_BYTES, only the couplings (u x u each, u = (band + 1) L - 1) are kept through the forward pass
    and each segment is made again, from its coupling, for the backward pass: memory bounded by a segment of
    SEGMENT_BYTES and the couplings whatever the frames, for twice the factorisation's work. The same
    operations in the same order, so the same factor bit for bit. DmaisError where the band would need more
    than FACTOR_BYTES."""

    def __init__(self, normal: GroupNormal, Hpp_inv: np.ndarray):
        s = normal.structure
        self.normal, self.Hpp_inv, self.L, self.u = normal, Hpp_inv, s.local_size, (s.band + 1) * s.local_size - 1
        self.frames = np.argsort(s.band_rank)  # the frame at each place
        self.run_place = s.band_rank[s.frame[s.pair_left[s.pair_runs[:-1]]]]  # each run's left frame's place
        self.rows = _band_rows(s).ravel()
        self.bounds = _segment_bounds(s.n_frames, s.band, s.local_size)
        n_segments, total = len(self.bounds) - 1, s.n_frames * s.local_size * (self.u + 1) * 8
        self.kept = [None] * n_segments if n_segments == 1 else None
        needed = total if self.kept else np.diff(self.bounds).max() * s.local_size * (self.u + 1) * 8 \
            + (n_segments - 1) * self.u**2 * 8
        if needed > FACTOR_BYTES:
            raise _too_large(s, f"its frames are tied over {s.band} frames (points seen {s.band} frames apart), "
                                f"and the factor of their system would need ~{needed / 2**30:.1f} GiB")
        self.couplings = [None] * n_segments  # each segment's rows of the factor's columns before it (a, u)

    def forward(self, right: np.ndarray) -> np.ndarray:
        """(F L, k) z = L^-1 right, right (F L, k) in the frames' order, z in the band's (self.rows)."""
        z = np.empty_like(right)
        z[self.rows] = right
        for k in range(len(self.bounds) - 1):
            factor, coupling = _segment_factor(self, k, with_coupling=True)
            r0, r1 = self.bounds[k] * self.L, self.bounds[k + 1] * self.L
            if k:
                z[r0:r0 + len(self.couplings[k])] -= self.couplings[k] @ z[r0 - self.u:r0]
            _band_forward(factor, z[r0:r1])
            if k + 2 < len(self.bounds):
                self.couplings[k + 1] = coupling
            if self.kept:
                self.kept[k] = factor
        return z

    def backward(self, z: np.ndarray) -> np.ndarray:
        """(F L, k) x = L^-T z in the frames' order, z (F L, k) in the band's (`forward`'s, after it)."""
        x = z.copy()
        for k in reversed(range(len(self.bounds) - 1)):
            factor = self.kept[k] if self.kept else _segment_factor(self, k, with_coupling=False)[0]
            r0, r1 = self.bounds[k] * self.L, self.bounds[k + 1] * self.L
            if k + 2 < len(self.bounds):
                coupling = self.couplings[k + 1]
                x[r1 - self.u:r1] -= coupling.T @ x[r1:r1 + len(coupling)]
            _band_backward(factor, x[r0:r1])
        return x[self.rows]


def _segment_bounds(n_frames: int, band: int, L: int) -> np.ndarray:
    """(n + 1,) the places (structure.band_rank) where the n segments of `_FramesBand` start, and the end: one
    segment where the whole factor is at most KEPT_FACTOR_BYTES, else segments of about SEGMENT_BYTES, each of
    at least band + 1 frames (a coupling reaches the next segment alone)."""
    total = n_frames * L * (band + 1) * L * 8
    n = 1 if total <= KEPT_FACTOR_BYTES else max(1, min(-(-total // SEGMENT_BYTES), n_frames // (band + 1)))
    return np.round(np.linspace(0, n_frames, n + 1)).astype(np.int64)


def _segment_factor(band: _FramesBand, k: int, with_coupling: bool):
    """(factor (S, u + 1), coupling (a, u) or None) of segment k of `band` (S rows): LAPACK's banded Cholesky of
    the segment's band less C C^T on its first rows (C = band.couplings[k], the factor's entries there of the
    previous segment's last u columns), and the factor's entries L[r1 + i, r1 - u + j] of the next segment's
    first a rows (r1 the segment's end), E L_last^-T with E the band's entries there (stored past the
    segment's end in its last rows, untouched by the factorisation) and L_last the factor's last u x u."""
    f0, f1 = band.bounds[k], band.bounds[k + 1]
    runs = np.searchsorted(band.run_place, [f0, f1])
    matrix = _frames_band(band.normal, band.Hpp_inv, band.frames[f0:f1], f0, *runs)
    S, u = len(matrix), band.u
    if k:
        C = band.couplings[k]
        i, j = np.tril_indices(len(C))
        matrix[j, i - j] -= (C @ C.T)[i, j]
    a = min(u, (band.bounds[k + 2] - f1) * band.L) if with_coupling and k + 2 < len(band.bounds) else 0
    E = np.triu(_band_view(matrix, S, S + a, S - u, S)) if a else None
    try:
        factor = linalg.cholesky_banded(matrix.T, overwrite_ab=True, lower=True, check_finite=False).T
    except linalg.LinAlgError:
        raise DmaisError("mounting: the group's normal equations are singular") from None
    if not a:
        return factor, None
    last = np.tril(_band_view(factor, S - u, S, S - u, S))
    return factor, linalg.solve_triangular(last, E.T, lower=True, check_finite=False).T


def _band_view(band: np.ndarray, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
    """A view of the entries (r, c) of rows r0 to r1 and columns c0 to c1 of the lower band matrix stored in
    `band` (n, u + 1) (LAPACK's lower band storage transposed: band[c, d] holds (c + d, c)); entries beyond
    the band hold others. (r, c) is flat[c u + r] of the flat band: rows adjacent, columns u apart."""
    flat, u = band.reshape(-1), band.shape[1] - 1
    step = flat.strides[0]
    return np.lib.stride_tricks.as_strided(flat[c0 * u + r0:], shape=(r1 - r0, c1 - c0), strides=(step, u * step),
                                           writeable=False)


def _frames_band(normal: GroupNormal, Hpp_inv: np.ndarray, frames: np.ndarray, first_place: int, first_run: int,
                 last_run: int) -> np.ndarray:
    """(c L, (band + 1) L) the frames' system's band in LAPACK's lower storage, transposed (row r holds the
    entries (r + d, r) at d), of the rows of `frames` (c,), the frames at places first_place to first_place + c
    of structure.band_rank's order (their rows counted from the first's): A on the diagonal blocks less, for
    every pair of observations (i, j) of one point p, Wp_i Hpp_inv_p Wp_j^T at the rows of i's and the columns
    of j's local unknowns (their upper triangle: i's frame is not after j's), summed over each run of pairs
    (structure.pair_runs) first_run to last_run (those whose left frame is one of `frames`) by one compiled
    loop over their pairs (_group.frames_band_subtract); Hpp_inv (P, 3, 3). Entries reaching past the last row
    are kept in it (the coupling to the next frames)."""
    s = normal.structure
    L = s.local_size
    width = (s.band + 1) * L
    band = np.zeros((len(frames) * L, width))
    rows = _band_rows(s) - first_place * L
    row, column = np.triu_indices(L)
    band[rows[frames][:, row], column - row] = normal.A[frames][:, row, column]
    _group.frames_band_subtract(s.pair_left, s.pair_right, s.pair_runs, first_run, last_run, s.frame, s.point,
                                s.local_cols, normal.Wp, np.ascontiguousarray(Hpp_inv), rows, band)
    return band


def _band_forward(factor: np.ndarray, x: np.ndarray) -> None:
    """x (n, k) <- L^-1 x in place, L lower triangular in `factor` (n, u + 1) (`_band_view`'s storage; its
    entries past row n are not read); by blocks of SOLVE_BLOCK columns, each a dense triangle and the rectangle
    below it (LAPACK's band solve goes a column at a time)."""
    n, u = factor.shape[0], factor.shape[1] - 1
    for c0 in range(0, n, min(SOLVE_BLOCK, u + 1)):
        c1, triangle, below = _band_blocks(factor, n, u, c0)
        x[c0:c1] = linalg.solve_triangular(triangle, x[c0:c1], lower=True, check_finite=False)
        x[c1:c1 + len(below)] -= below @ x[c0:c1]


def _band_backward(factor: np.ndarray, x: np.ndarray) -> None:
    """x (n, k) <- L^-T x in place (`_band_forward`'s L)."""
    n, u = factor.shape[0], factor.shape[1] - 1
    for c0 in reversed(range(0, n, min(SOLVE_BLOCK, u + 1))):
        c1, triangle, below = _band_blocks(factor, n, u, c0)
        x[c0:c1] -= below.T @ x[c1:c1 + len(below)]
        x[c0:c1] = linalg.solve_triangular(triangle, x[c0:c1], lower=True, trans="T", check_finite=False)


def _band_blocks(factor: np.ndarray, n: int, u: int, c0: int):
    """(c1, triangle (b, b), below (h, b)) of the band factor's columns c0 to c1 (`_band_forward`):
    L[c0:c1, c0:c1] (its lower triangle; the upper holds other entries) and L[c1:c1 + h, c0:c1] with
    the entries beyond the band zeroed."""
    c1 = min(c0 + min(SOLVE_BLOCK, u + 1), n)  # a triangle wider than the band would reach beyond it
    h = min(c1 + u, n) - c1
    view = _band_view(factor, c0, c1 + h, c0, c1)
    below = view[c1 - c0:].copy()
    beyond = (c1 - c0) + np.arange(h)[:, None] - np.arange(c1 - c0) > u  # row - column beyond the band
    below[beyond] = 0.0
    return c1, view[:c1 - c0], below


def _too_large(structure: GroupStructure, why: str) -> DmaisError:
    return DmaisError(f"mounting: a group of {structure.n_frames} frames is too large to adjust at once: {why}; "
                      "split it into groups of fewer frames (frames.csv's group)")
