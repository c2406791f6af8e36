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
  banded along a line of frames; it is factorised by blocks (no sharing) or by a sparse LU
  (scipy's SuperLU, a fill-reducing order), and the rig's R unknowns last by their Schur complement.

`elimination` picks the cheaper by counting the work each needs. The blocks are assembled, and the frames
eliminated, by compiled loops over the observations and frames (_group.pyx: a frame's block by its
Cholesky factor, the frames' couplings summed by BLAS dsyrk). Both are exact: the solution and the
rig's block of the inverse equal those of a dense solve of the whole matrix to rounding
(tests/test_group_normal.py). The cost is linear in the frames for a fixed number of points per frame
and frames per point; the dense system of the frames-first order is of the points alone. Frames tied
over a band of b frames (a line: C0 sees the markers the forward camera saw ~17 frames before) give
an LU of ~2 F L (b + 1) L numbers, which is refused beyond FACTOR_BYTES (`_banded_order`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import linalg, sparse
from scipy.sparse import csgraph
from scipy.sparse import linalg as sparse_linalg

from ..errors import DmaisError
from . import _group

FRAMES_FIRST, POINTS_FIRST = "frames first", "points first"
#: Above this size the frames' system of the points-first order is factorised sparse, not dense.
DENSE_FRAMES_SIZE = 2000
#: Numbers per chunk of frames where the frames-first order builds its dense system (chunk x L x (R + 3P)).
CHUNK_NUMBERS = 4_000_000
#: Up to this many numbers, the frames-first order keeps the frames' couplings between its two passes.
KEPT_NUMBERS = 30_000_000
#: The most memory the sparse LU of a points-first frames' system may take (bytes; `_banded_order`).
FACTOR_BYTES = 1.0 * 2**30
#: Observation pairs per chunk where the points-first order accumulates the frames' coupling blocks.
PAIR_CHUNK = 200_000


@dataclass(frozen=True)
class GroupStructure:
    """Which unknowns each observation touches, fixed for one adjustment, and the order of elimination.

    frame (N,) in [0, F); point (N,) in [0, P); local_cols (N, l) in [0, L); rig_cols (N, r) in [0, R);
    by_frame (N,) the observations in frame order, frame_starts (F + 1,) each frame's first in it,
    slot (N,) an observation's place among its frame's (fewer than n_slots); frames_tied: whether some
    point is seen by two frames (the points-first frames' system is then not block diagonal); method:
    FRAMES_FIRST or POINTS_FIRST (`elimination`). For the points first, untied: point_frame (P,) the
    frame of each point and point_slot (P,) its place among that frame's points (fewer than
    n_point_slots); tied: pair_left, pair_right (M,) every
    ordered pair of observations of one point (each with itself too), pair_block (M,) the index of the
    pair's frames (frame of left, frame of right) in frame_pairs (B, 2), the self pairs (f, f) first."""

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
    pair_left: np.ndarray
    pair_right: np.ndarray
    pair_block: np.ndarray
    frame_pairs: np.ndarray

    @property
    def size(self) -> int:
        return self.n_frames * self.local_size + self.rig_size + 3 * self.n_points


def group_structure(frame, point, local_cols, rig_cols, n_frames: int, local_size: int, rig_size: int,
                    n_points: int, method: str | None = None) -> GroupStructure:
    """The GroupStructure of N observations (its docstring), by `method` or `elimination`'s choice."""
    frame, point = np.asarray(frame, dtype=np.int64), np.asarray(point, dtype=np.int64)
    local_cols, rig_cols = np.asarray(local_cols, dtype=np.int64), np.asarray(rig_cols, dtype=np.int64)
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
    none = np.zeros(0, dtype=np.int64)
    points, pairs = (none, none, 0), (none, none, none, np.zeros((0, 2), dtype=np.int64))
    if method == POINTS_FIRST and tied:
        pairs = _observation_pairs(frame, point, counts, n_frames)
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


def _observation_pairs(frame: np.ndarray, point: np.ndarray, counts: np.ndarray, n_frames: int):
    """GroupStructure's pair_left, pair_right, pair_block and frame_pairs."""
    order = np.argsort(point, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    repeat = counts[point[order]]
    left = np.repeat(order, repeat)
    within = np.arange(len(left)) - np.repeat(np.cumsum(repeat) - repeat, repeat)
    right = order[starts[point[left]] + within]
    tied = frame[left] != frame[right]
    others, block = np.unique(frame[left[tied]] * n_frames + frame[right[tied]], return_inverse=True)
    pair_block = frame[left].copy()
    pair_block[tied] = n_frames + block
    keys = np.concatenate([np.arange(n_frames) * (n_frames + 1), others])
    return left, right, pair_block, np.column_stack(np.divmod(keys, n_frames))


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

    @property
    def gradient(self) -> np.ndarray:
        """(F L + R + 3P,) the flat gradient."""
        return np.concatenate([self.b_local.ravel(), self.b_rig, self.b_point.ravel()])

    def damped(self, damping: float) -> GroupNormal:
        """The equations with every diagonal raised by damping x itself (Levenberg-Marquardt)."""
        if not damping:
            return self
        A, Hrr, Hpp = self.A.copy(), self.Hrr.copy(), self.Hpp.copy()
        for M in (A, Hpp):
            n = M.shape[1]
            M[:, np.arange(n), np.arange(n)] *= 1.0 + damping
        Hrr[np.diag_indices(len(Hrr))] *= 1.0 + damping
        return GroupNormal(self.structure, A, self.Wr, Hrr, Hpp, self.Hpr, self.Wp, self.b_local, self.b_rig,
                           self.b_point)

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
    s = structure
    F, L, R, P = s.n_frames, s.local_size, s.rig_size, s.n_points
    A, Wr, b_local = np.zeros((F, L, L)), np.zeros((F, L, R)), np.zeros((F, L))
    Hrr, Hpp, Hpr = np.zeros((R, R)), np.zeros((P, 3, 3)), np.zeros((P, 3, R))
    Wp, b_rig, b_point = np.empty((len(e), s.local_cols.shape[1], 3)), np.zeros(R), np.zeros((P, 3))
    if local_J.shape[1] != 2:
        raise ValueError(f"two residuals per observation, got {local_J.shape[1]}")
    _group.assemble(s.frame, s.point, *map(np.ascontiguousarray, (s.local_cols, s.rig_cols, local_J, rig_J, point_J, e)),
                    A, Wr, b_local, Hrr, Hpp, Hpr, Wp, b_rig, b_point)
    return GroupNormal(s, A, Wr, Hrr, Hpp, Hpr, Wp, b_local, b_rig, b_point)


def _summed(values: np.ndarray, index: np.ndarray, size: int) -> np.ndarray:
    """(size,) the sums of `values` at their flat `index` (both broadcast to one shape)."""
    values, index = np.broadcast_arrays(values, index)
    return np.bincount(index.ravel(), weights=values.ravel(), minlength=size)


# ------------------------------------------------------------------------------ the solution


def solve(normal: GroupNormal, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The solution (F L + R + 3P, k) of the normal equations for right sides `right` (F L + R + 3P, k),
    and the rig's block (R, R) of the inverse normal matrix, in the structure's order of elimination;
    DmaisError where a frame, a point or the whole is not determined. The equations are first scaled
    to a unit diagonal by powers of two (`_equilibrated`: exact, and a group's mix of radians, metres
    and a long focal length gives condition numbers of 1e13 unscaled)."""
    s = normal.structure
    F, L, R = s.n_frames, s.local_size, s.rig_size
    right = np.asarray(right, dtype=float).reshape(s.size, -1 if np.size(right) else 0)
    k = right.shape[1]
    if k == 0:  # the rig's inverse alone: one zero right side keeps every shape
        right = np.zeros((s.size, 1))
    normal, scale = _equilibrated(normal)
    right = right * scale[:, None]
    r_local = right[:F * L].reshape(F, L, -1)
    r_rig, r_point = right[F * L:F * L + R], right[F * L + R:].reshape(s.n_points, 3, -1)
    solver = _frames_first if s.method == FRAMES_FIRST else _points_first
    x_local, x_rig, x_point, rig_inverse = solver(normal, r_local, r_rig, r_point)
    x = np.concatenate([x_local.reshape(F * L, -1), x_rig, x_point.reshape(3 * s.n_points, -1)]) * scale[:, None]
    rig_scale = scale[F * L:F * L + R]
    return x[:, :k], rig_inverse * np.outer(rig_scale, rig_scale)


def _equilibrated(normal: GroupNormal) -> tuple[GroupNormal, np.ndarray]:
    """The normal equations D N D with D (F L + R + 3P,) the powers of two nearest 1 / sqrt(diag N), and D."""
    s = normal.structure
    F, L, R, P = s.n_frames, s.local_size, s.rig_size, s.n_points
    diagonal = np.concatenate([np.diagonal(normal.A, axis1=1, axis2=2).ravel(), np.diag(normal.Hrr),
                               np.diagonal(normal.Hpp, axis1=1, axis2=2).ravel()])
    scale = np.exp2(-np.round(0.5 * np.log2(np.where(diagonal > 0, diagonal, 1.0))))
    local, rig, point = scale[:F * L].reshape(F, L), scale[F * L:F * L + R], scale[F * L + R:].reshape(P, 3)
    Wp = np.empty_like(normal.Wp)
    _group.scaled_couplings(np.ascontiguousarray(normal.Wp), s.frame, s.point, np.ascontiguousarray(s.local_cols),
                            local, point, Wp)
    scaled = GroupNormal(
        s, normal.A * local[:, :, None] * local[:, None, :], normal.Wr * local[:, :, None] * rig,
        normal.Hrr * np.outer(rig, rig), normal.Hpp * point[:, :, None] * point[:, None, :],
        normal.Hpr * point[:, :, None] * rig, Wp, normal.b_local * local, normal.b_rig * rig, normal.b_point * point)
    return scaled, scale


def _inverted(blocks: np.ndarray, what: str) -> np.ndarray:
    """(n, b, b) the inverses of SPD blocks; DmaisError naming `what` where one is singular."""
    if blocks.shape[1:] == (3, 3):
        return _inverted_3x3(blocks, what)
    try:
        return np.linalg.inv(blocks)
    except np.linalg.LinAlgError:
        raise _undetermined(what) from None


def _inverted_3x3(blocks: np.ndarray, what: str) -> np.ndarray:
    """(n, 3, 3) inverses of symmetric 3 x 3 blocks by their adjugates (rows: cross products of columns)."""
    c0, c1, c2 = blocks[:, :, 0], blocks[:, :, 1], blocks[:, :, 2]
    adjugate = np.stack([np.cross(c1, c2), np.cross(c2, c0), np.cross(c0, c1)], axis=1)
    determinant = np.einsum("ni,ni->n", c0, adjugate[:, 0])
    scale = np.abs(blocks).max(axis=(1, 2))
    if not (np.abs(determinant) > 1e-13 * scale**3).all():
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
    loops over the frames, _group; `_frames_first_numpy` is their reference)."""
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
    if _group.frames_first_reduction(factors, *coupling, r_local, system, y, stacked) >= 0:
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


def _points_first(normal: GroupNormal, r_local, r_rig, r_point):
    """Eliminate the points' blocks, then solve the frames' and the rig's system (module docstring)."""
    s = normal.structure
    F, L, R, P = s.n_frames, s.local_size, s.rig_size, s.n_points
    Hpp_inv = _inverted(normal.Hpp, "a point")
    Hpp_inv_Hpr = Hpp_inv @ normal.Hpr  # (P, 3, R)
    Hpp_inv_r = Hpp_inv @ r_point  # (P, 3, k)
    S_rr = normal.Hrr - normal.Hpr.reshape(3 * P, R).T @ Hpp_inv_Hpr.reshape(3 * P, R)
    y_rig = r_rig - normal.Hpr.reshape(3 * P, R).T @ Hpp_inv_r.reshape(3 * P, -1)
    if s.frames_tied:
        blocks, S_fr, y_local, W_point = _tied_reduction(normal, Hpp_inv, Hpp_inv_Hpr, Hpp_inv_r, r_local)
        frames = _frames_factor(blocks, s)
    else:
        blocks, S_fr, y_local, W_point = _untied_reduction(normal, Hpp_inv, r_point, r_local)
        inverse = _inverted(blocks, "a frame's pose")
        frames = lambda right: inverse @ right  # noqa: E731
    Z = frames(S_fr)  # (F, L, R)
    factor = _cho_factor(S_rr - S_fr.reshape(F * L, R).T @ Z.reshape(F * L, R))
    frames_y = frames(y_local)
    x_rig = linalg.cho_solve(factor, y_rig - S_fr.reshape(F * L, R).T @ frames_y.reshape(F * L, -1))
    x_local = frames_y - Z @ x_rig
    back = r_point - normal.Hpr @ x_rig - W_point(x_local)
    return x_local, x_rig, Hpp_inv @ back, linalg.cho_solve(factor, np.eye(R))


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
    y_local = r_local - V_stack @ stacked(r_point).reshape(F, 3 * slots, -1)
    return blocks, S_fr, y_local, lambda x_local: W.transpose(0, 2, 1) @ x_local[s.point_frame]


def _tied_reduction(normal: GroupNormal, Hpp_inv, Hpp_inv_Hpr, Hpp_inv_r, r_local):
    """As `_untied_reduction` where frames share points: the frames' system's blocks (B, L, L) of the
    structure's frame_pairs, one product per pair of observations of a point (`_frame_blocks`)."""
    s = normal.structure
    F, L, P = s.n_frames, s.local_size, s.n_points
    rows = s.frame[:, None] * L + s.local_cols  # (N, l)
    S_fr = normal.Wr - _summed(normal.Wp @ Hpp_inv_Hpr[s.point], rows[:, :, None] * s.rig_size
                               + np.arange(s.rig_size), F * L * s.rig_size).reshape(F, L, -1)
    k = r_local.shape[2]
    y_local = r_local - _summed(normal.Wp @ Hpp_inv_r[s.point], rows[:, :, None] * k + np.arange(k),
                                F * L * k).reshape(F, L, k)

    def W_point(x_local):
        moved = normal.Wp.transpose(0, 2, 1) @ x_local[s.frame[:, None], s.local_cols]  # (N, 3, k)
        index = (3 * s.point[:, None, None] + np.arange(3)[:, None]) * k + np.arange(k)
        return _summed(moved, index, P * 3 * k).reshape(P, 3, k)

    return _frame_blocks(normal, normal.Wp @ Hpp_inv[s.point]), S_fr, y_local, W_point


def _frame_blocks(normal: GroupNormal, V: np.ndarray) -> np.ndarray:
    """(B, L, L) the frames' system's blocks of the frame pairs (structure.frame_pairs): A on the self
    pairs less, for every pair of observations (i, j) of one point, V_i Wp_j^T at the rows of i's and
    the columns of j's local unknowns."""
    s = normal.structure
    L, B = s.local_size, len(s.frame_pairs)
    flat = np.zeros(B * L * L)
    flat[:s.n_frames * L * L] = normal.A.ravel()
    lc = s.local_cols
    for start in range(0, len(s.pair_left), PAIR_CHUNK):
        i, j = s.pair_left[start:start + PAIR_CHUNK], s.pair_right[start:start + PAIR_CHUNK]
        products = V[i] @ normal.Wp[j].transpose(0, 2, 1)  # (m, l, l)
        index = (s.pair_block[start:start + PAIR_CHUNK, None, None] * L + lc[i][:, :, None]) * L + lc[j][:, None, :]
        flat -= np.bincount(index.ravel(), weights=products.ravel(), minlength=len(flat))
    return flat.reshape(B, L, L)


def _frames_factor(blocks: np.ndarray, structure: GroupStructure):
    """A function solving the tied frames' system (its blocks (B, L, L) of structure.frame_pairs) for
    right sides (F, L, k): a dense Cholesky or a sparse LU of the whole, its frames in the order of the
    narrowest band (`_banded_order`) and factorised in that order (a fill-reducing order spreads a
    line's band: 2.6 GB for 3,000 frames)."""
    F, L = structure.n_frames, structure.local_size
    rank = _banded_order(structure)  # rank (F,): a frame's place in the order
    pairs = rank[structure.frame_pairs]
    order = np.lexsort((pairs[:, 1], pairs[:, 0]))
    matrix = sparse.bsr_array((blocks[order], pairs[order, 1], np.searchsorted(pairs[order, 0], np.arange(F + 1))),
                              shape=(F * L, F * L))
    if F * L <= DENSE_FRAMES_SIZE:
        factor = _cho_factor(matrix.toarray())
        solved = lambda right: linalg.cho_solve(factor, right)  # noqa: E731
    else:
        try:
            lu = sparse_linalg.splu(matrix.tocsc(), permc_spec="NATURAL", diag_pivot_thresh=0.0,
                                    options={"SymmetricMode": True})
        except RuntimeError:  # SuperLU: "Factor is exactly singular"
            raise DmaisError("mounting: the group's normal equations are singular") from None
        except MemoryError:
            raise _too_large(structure, "its factorization ran out of memory") from None
        solved = lu.solve

    return lambda right: solved(right[np.argsort(rank)].reshape(F * L, -1)).reshape(right.shape)[rank]


def _banded_order(structure: GroupStructure) -> np.ndarray:
    """(F,) each frame's place in whichever order ties frames over the narrower band: their own or the
    reverse Cuthill-McKee order of their pairs. DmaisError where the LU of the frames' system in it
    would need more than FACTOR_BYTES: frames tied over a band of b frames fill ~2 F L (b + 1) L numbers."""
    F, L = structure.n_frames, structure.local_size
    pairs = structure.frame_pairs
    graph = sparse.csr_array((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(F, F))
    reordered = np.empty(F, dtype=np.int64)
    reordered[csgraph.reverse_cuthill_mckee(graph, symmetric_mode=True)] = np.arange(F)
    bands = [(int(np.abs(rank[pairs[:, 0]] - rank[pairs[:, 1]]).max(initial=0)), k, rank)
             for k, rank in enumerate((np.arange(F), reordered))]
    band, _, rank = min(bands)
    needed = 2.0 * F * L * (band + 1) * L * 8
    if needed > FACTOR_BYTES and F * L > DENSE_FRAMES_SIZE:
        raise _too_large(structure, f"its frames are tied over {band} frames (points seen {band} frames apart), and "
                                    f"the LU of their system would need ~{needed / 2**30:.1f} GiB")
    return rank


def _too_large(structure: GroupStructure, why: str) -> DmaisError:
    return DmaisError(f"mounting: a group of {structure.n_frames} frames is too large to adjust at once: {why}; "
                      "split it into groups of fewer frames (frames.csv's group)")
