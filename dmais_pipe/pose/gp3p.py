"""Minimal generalized absolute pose from three rays (gP3P), our own derivation.

Problem: rays v_i + l_i f_i (rig frame, unit f_i) and world points M_i, i = 1..3; find the
poses (R, t) with R M_i + t = v_i + l_i f_i, l_i > 0 (paper, eq. projEq, for n = 3).

Rigid motions keep distances, so the depths l = (l1, l2, l3) satisfy the three quadrics

    ||v_i + l_i f_i - v_j - l_j f_j||^2 = ||M_i - M_j||^2,   (i, j) in {(1, 2), (1, 3), (2, 3)},

which with w_ij = v_i - v_j, c_ij = f_i . f_j, a_ij = f_i . w_ij, b_ij = f_j . w_ij and
e_ij = ||w_ij||^2 - ||M_i - M_j||^2 read

    E_ij = l_i^2 + l_j^2 - 2 c_ij l_i l_j + 2 a_ij l_i - 2 b_ij l_j + e_ij = 0.

Elimination (x = l2, y = l3):

1. E12 and E13 are monic quadratics in l1: l1^2 + p1 l1 + q1 and l1^2 + p2 l1 + q2 with
   p1 = 2 a12 - 2 c12 x, q1 = x^2 - 2 b12 x + e12, p2 = 2 a13 - 2 c13 y, q2 = y^2 - 2 b13 y + e13.
   Their resultant in l1 is prod_{E12(r)=0} E13(r), and since E13(r) = (p2 - p1) r + (q2 - q1)
   at a root r of E12 (whose roots have sum -p1 and product q1):

       G(x, y) = (p2 - p1)^2 q1 - (p2 - p1)(q2 - q1) p1 + (q2 - q1)^2,   total degree 4.

2. E23 is monic quadratic in y: y^2 + P y + S with P = -2 c23 x - 2 b23, S = x^2 + 2 a23 x + e23.
   Reducing G modulo E23 (y^2 -> -P y - S) leaves alpha(x) y + beta(x), deg alpha <= 3,
   deg beta <= 4, and the resultant of that line with E23 in y is the univariate

       F(x) = beta^2 - P alpha beta + S alpha^2,   degree 8 (the Bezout number of 3 quadrics).

3. Real roots x of F give y = -beta / alpha and l1 = -(q2 - q1) / (p2 - p1) (both from the
   linear relations above), with both quadratic roots as a fallback when a divisor vanishes.
   Each depth triple is polished by Newton steps on (E12, E13, E23), the rig-frame points
   P_i = v_i + l_i f_i are formed and (R, t) follows from the closed-form absolute orientation
   of the point pairs (M_i, P_i) (Kabsch/Umeyama without scale, SVD with reflection guard).

The central case (all v_i equal) is the same system with a = b = 0 (F is then even in x; the
mirrored solutions have negative depths and are discarded). Lengths are scaled by the largest
world distance and origins centred before eliminating, which leaves the depths' equations
invariant up to that scale.
"""

from __future__ import annotations

import numpy as np
from numpy.polynomial import polynomial as P1
from scipy.signal import convolve2d

from ..errors import PoseError
from .statistics import validate_correspondences

#: Newton steps on the depth equations for each candidate.
NEWTON_STEPS = 3
#: Candidates whose depth equations keep a relative residual above this after Newton are dropped.
RESIDUAL_TOLERANCE = 1e-6
#: Roots of F with |imag| above this fraction of (1 + |root|) are complex and dropped.
IMAG_TOLERANCE = 1e-4
#: Triangles of world points with an area below this fraction of (longest side)^2 are degenerate.
DEGENERATE_AREA = 1e-10
#: Relative size below which a divisor of the back-substitution counts as zero (fallback used).
SMALL_DIVISOR = 1e-8

_PAIRS = ((0, 1), (0, 2), (1, 2))


def gp3p(origins, directions, points, *, positive_depth: bool = True) -> list[tuple[np.ndarray, np.ndarray]]:
    """All poses (R, t) with R @ M_i + t on the ray v_i + l_i f_i for three correspondences.

    origins: (3, 3) ray origins v_i (rig frame); directions: (3, 3) ray directions f_i (rig frame,
    normalized here); points: (3, 3) world points M_i. Returns a list of up to 8 pairs
    (R (3, 3), t (3,)) with x_rig = R @ M + t; with `positive_depth` (default) only poses that
    put every point in front of its ray's origin (l_i > 0). Collinear or coincident world
    points have no unique solution and give an empty list. Raises PoseError for invalid input
    (shapes, non-finite values, zero directions, not exactly 3 correspondences).
    """
    v, f, M = validate_correspondences(origins, directions, points)
    if len(M) != 3:
        raise PoseError(f"gp3p: exactly 3 correspondences are needed, got {len(M)}")
    return gp3p_unchecked(v, f, M, positive_depth=positive_depth)


def gp3p_unchecked(v: np.ndarray, f: np.ndarray, M: np.ndarray, *, positive_depth: bool = True):
    """`gp3p` without input validation, for RANSAC loops: v, f (unit), M float arrays (3, 3)."""
    scale = _world_scale(M)
    if scale is None:
        return []
    v_centre = v.mean(axis=0)
    coefficients = _pair_coefficients((v - v_centre) / scale, f, M / scale)
    depths = _solve_depths(coefficients)
    if positive_depth:
        depths = depths[(depths > 0).all(axis=1)]
    if len(depths) == 0:
        return []
    rig_points = v[None, :, :] + scale * depths[:, :, None] * f[None, :, :]  # (m, 3, 3)
    rotations, translations = absolute_orientation(M, rig_points)
    return list(zip(rotations, translations))


def _world_scale(M: np.ndarray) -> float | None:
    """Longest side of the world triangle, or None if the triangle is degenerate."""
    sides = M[[1, 2, 2]] - M[[0, 0, 1]]
    longest = float(np.sqrt((sides**2).sum(axis=1).max()))
    area = 0.5 * float(np.linalg.norm(np.cross(sides[0], sides[1])))
    if not longest > 0 or area < DEGENERATE_AREA * longest**2:
        return None
    return longest


def _pair_coefficients(v: np.ndarray, f: np.ndarray, M: np.ndarray) -> np.ndarray:
    """(3, 4) rows (a_ij, b_ij, c_ij, e_ij) of E12, E13, E23 (module docstring)."""
    rows = []
    for i, j in _PAIRS:
        w = v[i] - v[j]
        d2 = float(np.sum((M[i] - M[j]) ** 2))
        rows.append((f[i] @ w, f[j] @ w, f[i] @ f[j], w @ w - d2))
    return np.array(rows)


def _univariate(coefficients: np.ndarray):
    """F(x) (low-to-high coefficients) and the pieces needed to back-substitute y and l1."""
    (a12, b12, c12, e12), (a13, b13, c13, e13), (a23, b23, c23, e23) = coefficients
    # Bivariate polynomials as arrays C[i, j] of x^i y^j.
    p1 = np.array([[2 * a12], [-2 * c12]])
    q1 = np.array([[e12], [-2 * b12], [1.0]])
    p2 = np.array([[2 * a13, -2 * c13]])
    q2 = np.array([[e13, -2 * b13, 1.0]])
    dp = _add2(p2, -p1)
    dq = _add2(q2, -q1)
    G = _add2(_add2(_mul2(_mul2(dp, dp), q1), -_mul2(_mul2(dp, dq), p1)), _mul2(dq, dq))
    P = np.array([-2 * b23, -2 * c23])  # in x
    S = np.array([e23, 2 * a23, 1.0])
    alpha, beta = _reduce_mod_quadratic(G, P, S)
    F = _add1(_add1(np.convolve(beta, beta), -np.convolve(P, np.convolve(alpha, beta))),
              np.convolve(S, np.convolve(alpha, alpha)))
    return F, alpha, beta


def _add1(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Sum of two univariate coefficient arrays (low to high order) of any lengths."""
    out = np.zeros(max(len(a), len(b)))
    out[: len(a)] += a
    out[: len(b)] += b
    return out


def _add2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out = np.zeros((max(a.shape[0], b.shape[0]), max(a.shape[1], b.shape[1])))
    out[: a.shape[0], : a.shape[1]] += a
    out[: b.shape[0], : b.shape[1]] += b
    return out


def _mul2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return convolve2d(a, b)


def _reduce_mod_quadratic(G: np.ndarray, P: np.ndarray, S: np.ndarray):
    """alpha(x), beta(x) with G(x, y) = alpha y + beta modulo y^2 + P(x) y + S(x)."""
    columns = [G[:, k].copy() for k in range(G.shape[1])]  # coefficient of y^k, a polynomial in x
    for k in range(len(columns) - 1, 1, -1):
        top = columns[k]
        columns[k - 1] = _add1(columns[k - 1], -np.convolve(top, P))
        columns[k - 2] = _add1(columns[k - 2], -np.convolve(top, S))
    return columns[1], columns[0]


def _solve_depths(coefficients: np.ndarray) -> np.ndarray:
    """Real depth triples (m, 3) solving E12 = E13 = E23 = 0, Newton-polished and deduplicated."""
    F, alpha, beta = _univariate(coefficients)
    F = np.trim_zeros(F, "b")
    if len(F) < 2 or not np.all(np.isfinite(F)):
        return np.empty((0, 3))
    roots = P1.polyroots(F / np.abs(F).max())
    real = roots[np.abs(roots.imag) <= IMAG_TOLERANCE * (1.0 + np.abs(roots))].real
    candidates = [c for x in real for c in _back_substitute(coefficients, x, alpha, beta)]
    if not candidates:
        return np.empty((0, 3))
    depths = _newton(coefficients, np.array(candidates))
    residual = np.abs(_equations(coefficients, depths)).max(axis=1)
    size = 1.0 + (depths**2).sum(axis=1)
    keep = np.isfinite(residual) & (residual <= RESIDUAL_TOLERANCE * size)
    return _unique_rows(depths[keep])


def _back_substitute(coefficients: np.ndarray, x: float, alpha, beta) -> list[tuple[float, float, float]]:
    """Depth triples (l1, x, y) for one root x of F."""
    (a12, b12, c12, e12), (a13, b13, c13, e13), (a23, b23, c23, e23) = coefficients
    alpha_x, beta_x = P1.polyval(x, alpha), P1.polyval(x, beta)
    if abs(alpha_x) > SMALL_DIVISOR * (abs(beta_x) + 1.0):
        ys = [-beta_x / alpha_x]
    else:
        ys = _quadratic_roots(-2 * c23 * x - 2 * b23, x * x + 2 * a23 * x + e23)
    triples = []
    for y in ys:
        p1, q1 = 2 * a12 - 2 * c12 * x, x * x - 2 * b12 * x + e12
        p2, q2 = 2 * a13 - 2 * c13 * y, y * y - 2 * b13 * y + e13
        if abs(p2 - p1) > SMALL_DIVISOR * (abs(p1) + abs(p2) + 1.0):
            l1s = [-(q2 - q1) / (p2 - p1)]
        else:
            l1s = _quadratic_roots(p1, q1)
        triples.extend((l1, x, y) for l1 in l1s)
    return triples


def _quadratic_roots(p: float, q: float) -> list[float]:
    """Real roots of z^2 + p z + q (the real part of a complex pair if nearly real)."""
    disc = p * p / 4.0 - q
    if disc < -IMAG_TOLERANCE * (1.0 + p * p):
        return []
    root = np.sqrt(max(disc, 0.0))
    return [-p / 2.0 + root, -p / 2.0 - root]


def _equations(coefficients: np.ndarray, depths: np.ndarray) -> np.ndarray:
    """(m, 3) values of E12, E13, E23 at depth triples (m, 3)."""
    out = np.empty_like(depths)
    for k, (i, j) in enumerate(_PAIRS):
        a, b, c, e = coefficients[k]
        li, lj = depths[:, i], depths[:, j]
        out[:, k] = li * li + lj * lj - 2 * c * li * lj + 2 * a * li - 2 * b * lj + e
    return out


def _newton(coefficients: np.ndarray, depths: np.ndarray, steps: int = NEWTON_STEPS) -> np.ndarray:
    """Newton iterations on (E12, E13, E23) for depth triples (m, 3); singular steps are skipped."""
    depths = depths.copy()
    for _ in range(steps):
        J = np.zeros((len(depths), 3, 3))
        for k, (i, j) in enumerate(_PAIRS):
            a, b, c, _ = coefficients[k]
            li, lj = depths[:, i], depths[:, j]
            J[:, k, i] = 2 * li - 2 * c * lj + 2 * a
            J[:, k, j] = 2 * lj - 2 * c * li - 2 * b
        value = _equations(coefficients, depths)
        ok = np.abs(np.linalg.det(J)) > 1e-14 * np.abs(J).reshape(len(J), -1).max(axis=1) ** 3
        if not ok.any():
            break
        depths[ok] -= np.linalg.solve(J[ok], value[ok][:, :, None])[:, :, 0]
    return depths


def _unique_rows(depths: np.ndarray, tolerance: float = 1e-9) -> np.ndarray:
    unique: list[np.ndarray] = []
    for row in depths:
        if all(np.abs(row - u).max() > tolerance * (1.0 + np.abs(u).max()) for u in unique):
            unique.append(row)
    return np.array(unique).reshape(-1, 3)


def absolute_orientation(world_points: np.ndarray, rig_points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid motion (no scale) with rig_points ~ R @ world_points + t.

    world_points: (k, 3); rig_points: (k, 3) or a batch (m, k, 3). Returns R (3, 3) / (m, 3, 3)
    and t (3,) / (m, 3). Kabsch/Umeyama: SVD of the cross-covariance, the last singular vector
    sign-corrected so that det R = +1 (also for k = 3, where the covariance has rank 2).
    """
    batch = rig_points.ndim == 3
    Q = rig_points if batch else rig_points[None]
    world_mean = world_points.mean(axis=0)
    rig_mean = Q.mean(axis=1)
    cross = np.einsum("mki,kj->mij", Q - rig_mean[:, None, :], world_points - world_mean)
    U, _, Vt = np.linalg.svd(cross)
    sign = np.sign(np.linalg.det(U @ Vt))
    sign[sign == 0] = 1.0
    U = U.copy()
    U[:, :, 2] *= sign[:, None]
    R = U @ Vt
    t = rig_mean - R @ world_mean
    return (R, t) if batch else (R[0], t[0])
