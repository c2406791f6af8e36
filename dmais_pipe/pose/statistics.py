"""The n-independent statistics of the generalized absolute pose problem (paper, eq. objfun2 to t).

With r = vec(R) row-major (the paper's r = [R_1, ..., R_9]), Y_i = blockdiag(M_i^T, M_i^T, M_i^T)
so that R M_i = Y_i r, and the stacked (3n, .) matrices

    A = [[f_i]x Y_i],   B = [[f_i]x],   D = [[f_i]x v_i],

the objective of eq. objfun2 is ||A r + B t - D||^2. For fixed R the optimal translation is
(eq. t)

    t(r) = -B^+ (A r - D) = -(B^T B)^-1 (B^T A r - B^T D),

and substituting it gives eq. objfun3 with G = I - B B^+:

    cost(r) = (A r - D)^T G (A r - D) = r^T H r - 2 g^T r + c,
    H = A^T G A (9, 9),   g = A^T G D (9,),   c = D^T G D.

Nothing here builds a 3n x 9 matrix. For unit f, [f]x^T [f]x = I - f f^T =: Q, so every product
is a sum over points, computed in O(n) in one pass (compiled: `_kernels.statistics`):

    A^T A = kron(I3, sum M M^T) - U^T U,           U_i = kron(f_i, M_i)  (9,)
    A^T B = kron(I3, sum M) - U^T F,               F = [f_i] (n, 3)
    B^T B = n I - F^T F
    A^T D = vec(sum w_i M_i^T),  B^T D = sum w_i,  D^T D = sum v_i . w_i,   w_i = Q_i v_i
    H = A^T A - A^T B (B^T B)^-1 B^T A, and likewise g, c (Schur complements).

Conditioning: the world points are centred (their mean m is subtracted) before accumulating.
Since t is free, R M_i + t = R (M_i - m) + (t + R m), so H, g, c (and the cost as a function
of R) are unchanged in exact arithmetic, while the sums no longer carry the large common offset
of a survey frame (e.g. UTM coordinates at 350 m flying height). `translation` returns the
translation of the original, uncentred world frame: t(R) = t_centred(R) - R m.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import PoseError
from ._kernels import statistics

#: Relative tolerance of the collinearity test: the second singular value of the centred points
#: must exceed this fraction of the first (tested on the scatter matrix, whose eigenvalues are the
#: squared singular values, so smaller tolerances would drown in rounding).
COLLINEAR_TOLERANCE = 1e-6
#: Directions with a norm below this are treated as zero (invalid).
ZERO_DIRECTION = 1e-12


@dataclass(frozen=True)
class PoseStatistics:
    """Everything the solver needs, independent of n (see the module docstring).

    H: (9, 9) symmetric, g: (9,), c: scalar, such that cost(r) = r^T H r - 2 g^T r + c for the
    row-major r = vec(R). The translation map of eq. t is t_centred(r) = t_matrix @ r + t_offset in
    the frame of the centred world points; `centroid` (3,) is the subtracted mean of the points.
    BtB = B^T B = sum (I - f f^T) (3, 3). n: number of correspondences. point_axes (3, 3): a rotation
    whose columns are the principal axes of the centred world points, least spread first (the
    first is the normal of the best-fitting plane); point_spread (3,): the sums of squared
    distances along them (eigenvalues of the scatter matrix, ascending).
    """

    H: np.ndarray
    g: np.ndarray
    c: float
    t_matrix: np.ndarray
    t_offset: np.ndarray
    centroid: np.ndarray
    BtB: np.ndarray
    n: int
    point_axes: np.ndarray
    point_spread: np.ndarray

    def cost(self, R) -> np.ndarray | float:
        """Value of eq. objfun (t eliminated) for rotations R (3, 3) -> float or (m, 3, 3) -> (m,).

        Equals sum_i ||[f_i]x (R M_i + t(R) - v_i)||^2 up to rounding (it can be a tiny negative
        number at an exact fit, since it is evaluated as a quadratic form).
        """
        R = np.asarray(R, dtype=float)
        r = R.reshape(-1, 9)
        value = np.einsum("mi,mi->m", r @ self.H - 2.0 * self.g, r) + self.c
        return float(value[0]) if R.ndim == 2 else value

    def translation(self, R) -> np.ndarray:
        """Optimal translation t(R) of eq. t, (3,) for R (3, 3) or (m, 3) for R (m, 3, 3).

        In the original world frame (x_rig = R @ M + t), the centring undone.
        """
        R = np.asarray(R, dtype=float)
        Rs = R.reshape(-1, 3, 3)
        t = Rs.reshape(-1, 9) @ self.t_matrix.T + self.t_offset - Rs @ self.centroid
        return t[0] if R.ndim == 2 else t


def _as_rows(name: str, value) -> np.ndarray:
    try:
        array = np.ascontiguousarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise PoseError(f"pose: {name} is not a numeric array ({exc})") from None
    if array.ndim != 2 or array.shape[1] != 3:
        raise PoseError(f"pose: {name} must have shape (n, 3), got {array.shape}")
    if not np.isfinite(array).all():
        bad = ~np.isfinite(array).all(axis=1)
        raise PoseError(f"pose: {name} row {int(np.flatnonzero(bad)[0])} is not finite: {array[bad][0]}")
    return array


def validate_correspondences(origins, directions, points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Checked float copies of the inputs, directions normalized to unit length.

    Raises PoseError for wrong shapes, mismatched lengths, NaN/inf, zero directions and fewer than
    3 points. (Collinear points and all-parallel rays are caught by `pose_statistics`, which forms
    the matrices those tests need anyway.)
    """
    origins = _as_rows("origins", origins)
    directions = _as_rows("directions", directions)
    points = _as_rows("points", points)
    n = len(points)
    if not (len(origins) == len(directions) == n):
        raise PoseError(
            f"pose: mismatched lengths: {len(origins)} origins, {len(directions)} directions, "
            f"{n} points"
        )
    if n < 3:
        raise PoseError(f"pose: at least 3 correspondences are needed, got {n}")
    norms = np.sqrt(np.einsum("ij,ij->i", directions, directions))
    zero = norms < ZERO_DIRECTION
    if zero.any():
        raise PoseError(f"pose: directions row {int(np.flatnonzero(zero)[0])} is zero")
    directions = directions / norms[:, None]
    return origins, directions, points


def pose_statistics(origins, directions, points) -> PoseStatistics:
    """Statistics of eq. objfun3 from generalized rays and world points.

    origins: (n, 3) ray origins v_i in the rig frame; directions: (n, 3) ray directions f_i in the
    rig frame (normalized here); points: (n, 3) world points M_i. O(n), vectorized.
    """
    return statistics_of(*validate_correspondences(origins, directions, points))


def statistics_of(v: np.ndarray, f: np.ndarray, M: np.ndarray) -> PoseStatistics:
    """`pose_statistics` of correspondences already checked by `validate_correspondences`:
    origins v (n, 3), unit directions f (n, 3), world points M (n, 3), C-contiguous. The sums run
    compiled (`_kernels.statistics`), one pass over the points.

    point_axes: eigenvectors of the scatter matrix of the centred points as the columns of a
    rotation, least spread first; point_spread: its eigenvalues (the squared singular values of
    the centred points). Raises PoseError for collinear points and all-parallel rays.
    """
    n = len(M)
    H, g, c, t_matrix, t_offset, centroid, BtB, point_axes, point_spread, least_BtB = statistics(v, f, M)
    if not point_spread[1] > COLLINEAR_TOLERANCE**2 * point_spread[2]:
        raise PoseError(f"pose: the {n} world points are collinear (or coincident)")
    if not least_BtB > 1e-12 * n:
        raise PoseError("pose: all rays are parallel; the translation along them is undetermined")
    return PoseStatistics(
        H=H, g=g, c=c, t_matrix=t_matrix, t_offset=t_offset, centroid=centroid, BtB=BtB, n=n, point_axes=point_axes,
        point_spread=point_spread,
    )
