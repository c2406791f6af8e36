"""Non-linear refinement of a generalized absolute pose on angular (tangent-plane) ray errors.

Residual of correspondence i for a pose (R, t) (x_rig = R @ M + t): with p_i = R M_i + t - v_i
the vector from the ray origin to the transformed world point and u_i = p_i / ||p_i||,

    r_i = B_i u_i   (2,),   B_i = [b1_i; b2_i] (2, 3) a fixed orthonormal basis of the plane
                            orthogonal to the unit direction f_i (`tangent_bases`).

||r_i|| = sin(angle between p_i and f_i), i.e. radians for small errors; the sign of the depth
alpha_i = f_i . p_i is not seen by r_i (see `ray_errors` for a test that rejects alpha_i <= 0).

Parameters of the Gauss-Newton / Levenberg-Marquardt iteration, in this order,

    x = (omega (3), delta_t (3)):   R <- exp(omega) R,   t <- t + delta_t,

a left (rig-frame) rotation increment and an additive translation increment. With
q_i = R M_i the analytic Jacobian is

    d r_i / d p_i = B_i (I - u_i u_i^T) / ||p_i||,   d p_i / d omega = -[q_i]x,   d p_i / d t = I.

The covariance of the estimate in the same order, cov(omega, t) = s^2 (J^T J)^-1 (6, 6), where
omega is the error rotation R_true = exp(omega) R_estimate, and s^2 is sigma^2 when sigma
(radians, per residual component) is given, otherwise the a-posteriori variance of unit weight
sum ||r_i||^2 / (2 n - 6).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import PoseError
from ..geometry import skew
from . import _refine
from .statistics import ZERO_DIRECTION, validate_correspondences

#: Iteration limit of `refine_pose`.
MAX_ITERATIONS = 50
#: Stop when the step is below this (radians for omega, relative to the scene size for t).
STEP_TOLERANCE = 1e-12
#: Stop when the cost decreases, or the Gauss-Newton model predicts it to decrease, by less than this fraction.
COST_TOLERANCE = 1e-14


@dataclass(frozen=True)
class RefinedPose:
    """Result of `refine_pose`.

    R (3, 3), t (3,): the refined pose, x_rig = R @ M + t. covariance (6, 6): of
    (omega, t) with R_true = exp(omega) R (module docstring). residual_rms: sqrt(sum_i ||r_i||^2
    / n), the RMS angular error per ray in radians. n_iterations: iterations performed.
    converged: a stopping tolerance was met before the iteration limit. objective: the paper's
    eq. objfun at (R, t), sum_i ||f_i x (R M_i + t - v_i)||^2 with unit f_i (the solver's cost).
    """

    R: np.ndarray
    t: np.ndarray
    covariance: np.ndarray
    residual_rms: float
    n_iterations: int
    converged: bool
    objective: float = math.nan


def tangent_bases(directions: np.ndarray) -> np.ndarray:
    """(n, 2, 3) orthonormal bases [b1; b2] of the planes orthogonal to unit directions (n, 3).

    b1 = f x a / ||f x a|| with a the coordinate axis least aligned with f, b2 = f x b1.
    """
    f = np.asarray(directions, dtype=float)
    axis = np.zeros_like(f)
    axis[np.arange(len(f)), np.argmin(np.abs(f), axis=1)] = 1.0
    b1 = np.cross(f, axis)
    b1 /= np.linalg.norm(b1, axis=1)[:, None]
    b2 = np.cross(f, b1)
    return np.stack([b1, b2], axis=1)


def angular_residuals(origins, bases, points, R, t) -> np.ndarray:
    """(n, 2) residuals r_i = B_i (R M_i + t - v_i) / ||.|| (radians for small errors).

    origins: (n, 3); bases: (n, 2, 3) from `tangent_bases`; points: (n, 3); R (3, 3), t (3,).
    """
    p = points @ R.T + t - origins
    u = p / np.linalg.norm(p, axis=1)[:, None]
    return np.einsum("nij,nj->ni", bases, u)


def ray_errors(origins, directions, points, R, t) -> np.ndarray:
    """(n,) angular error in radians of each correspondence, inf where the point is behind its ray.

    The error is ||r_i|| = sin of the angle between R M_i + t - v_i and f_i (the norm of the
    `angular_residuals`, basis-independent); points with depth alpha_i = f_i . p_i <= 0 get inf.
    """
    p = points @ R.T + t - origins
    norm = np.linalg.norm(p, axis=1)
    alpha = np.einsum("ij,ij->i", p, directions)
    sine = np.linalg.norm(np.cross(p, directions), axis=1) / np.where(norm > 0, norm, 1.0)
    return np.where((alpha > 0) & (norm > 0), sine, np.inf)


def _jacobian(origins, bases, points, R, t) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (2n,) and Jacobian (2n, 6) with respect to (omega, delta_t).

    R (3, 3) and t (3,) one pose, or R (n, 3, 3) and t (n, 3) a pose per row (many frames at once).
    """
    q = np.einsum("...ij,...j->...i", R, points)
    p = q + t - origins
    norm = np.linalg.norm(p, axis=1)
    u = p / norm[:, None]
    r = np.einsum("nij,nj->ni", bases, u)
    # d r / d p = B (I - u u^T) / ||p|| = (B - (B u) u^T) / ||p||
    dr_dp = (bases - r[:, :, None] * u[:, None, :]) / norm[:, None, None]
    J = np.empty((len(points), 2, 6))
    J[:, :, :3] = np.cross(q[:, None, :], dr_dp)  # row^T (-[q]x) = -(row x q) = q x row
    J[:, :, 3:] = dr_dp
    return r.reshape(-1), J.reshape(-1, 6)


def refine_pose(origins, directions, points, R, t, sigma: float | None = None,
                max_iterations: int = MAX_ITERATIONS) -> RefinedPose:
    """Levenberg-Marquardt refinement of (R, t) on the angular ray residuals (module docstring).

    origins: (n, 3) ray origins v_i; directions: (n, 3) ray directions f_i (normalized here);
    points: (n, 3) world points M_i; R (3, 3), t (3,): the starting pose, x_rig = R @ M + t.
    sigma: a-priori standard deviation of one residual component in radians, or None to use the
    a-posteriori estimate (needs n >= 4; for n == 3 the covariance is NaN). Parameter order of
    the covariance: (omega_x, omega_y, omega_z, t_x, t_y, t_z).

    The iteration runs compiled (`_refine.refine`): damped Gauss-Newton steps on the 6-vector
    (omega, delta_t), J^T J and J^T r accumulated point by point from the analytic Jacobian. It
    works about the points' centroid m (t' = t + R m): with map coordinates (|M| ~ 1e6 m) the
    rotation and translation steps are so correlated that the iteration would stall early. One
    call reads C-contiguous float64 arrays in place and returns the pose, its covariance and
    eq. objfun (other inputs take the Python checks first): at 10 points the per-call overhead,
    not the iteration, is most of the time.
    """
    if sigma is not None and not (np.isfinite(sigma) and sigma > 0):
        raise PoseError(f"refine_pose: sigma must be a positive number of radians, got {sigma}")
    sigma = np.nan if sigma is None else float(sigma)
    found = _refine.refine(origins, directions, points, R, t, int(max_iterations), STEP_TOLERANCE, COST_TOLERANCE,
                           sigma, ZERO_DIRECTION)
    if found is None:  # other input types, or input that fails a check: the Python checks name the fault
        v, f, M = validate_correspondences(origins, directions, points)
        R, t = _checked_pose(R, t)
        found = _refine.refine(v, f, M, R, t, int(max_iterations), STEP_TOLERANCE, COST_TOLERANCE, sigma,
                               ZERO_DIRECTION)
        if found is None:
            raise PoseError("refine_pose: the correspondences or the starting pose are not finite")
    R, t, covariance, cost, n_iterations, converged, objective = found
    return RefinedPose(R, t, covariance, math.sqrt(cost / len(points)), n_iterations, converged, objective)


def cramer_rao_bound(origins, directions, points, R, t, sigma: float) -> tuple[float, float]:
    """Cramer-Rao bound of a generalized pose at (R, t): (position, attitude) RMS errors (m, rad).

    The bound for any unbiased estimator when every angular residual component has independent
    Gaussian noise of `sigma` radians: cov = sigma^2 (J^T J)^-1 at the pose (module docstring). The
    rig centre c = -R^T t moves by dc = -R^T ([t]x omega + delta_t), so its covariance is
    G cov G^T with G = -R^T [[t]x, I]. Returns sqrt(trace) of the centre covariance (m) and of the
    omega block (rad); NaN where the pose is not observable.
    """
    v, f, M = validate_correspondences(origins, directions, points)
    R, t = _checked_pose(R, t)
    if not (np.isfinite(sigma) and sigma > 0):
        raise PoseError(f"cramer_rao_bound: sigma must be a positive number of radians, got {sigma}")
    m = M.mean(axis=0)  # about the centroid (t' = t + R m), as refine_pose: the centre moves alike
    t = t + R @ m
    _, J = _jacobian(v, tangent_bases(f), M - m, R, t)
    covariance = sigma**2 * _inverse_normal_matrix(J)
    G = -R.T @ np.hstack([skew(t), np.eye(3)])
    return float(np.sqrt(np.trace(G @ covariance @ G.T))), float(np.sqrt(np.trace(covariance[:3, :3])))


def _checked_pose(R, t) -> tuple[np.ndarray, np.ndarray]:
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float)
    if R.shape != (3, 3) or t.shape != (3,):
        raise PoseError(f"refine_pose: R must be (3, 3) and t (3,), got {R.shape} and {t.shape}")
    if not (np.isfinite(R).all() and np.isfinite(t).all()):
        raise PoseError("refine_pose: the starting pose is not finite")
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise PoseError("refine_pose: R is not a rotation matrix")
    U, _, Vt = np.linalg.svd(R)  # re-orthonormalize
    return U @ Vt, t


def _inverse_normal_matrix(J) -> np.ndarray:
    """(J^T J)^-1 (6, 6), or NaN if the pose is not observable (rank-deficient Jacobian)."""
    return inverse_normal_matrices(J.T @ J)


def inverse_normal_matrices(normal) -> np.ndarray:
    """Inverses (..., k, k) of symmetric normal matrices (..., k, k); NaN where one is singular
    (a zero diagonal entry, or condition number above 1e12 after scaling to a unit diagonal)."""
    normal = np.asarray(normal, dtype=float)
    shape, k = normal.shape, normal.shape[-1]
    normal = normal.reshape(-1, k, k)
    scale = np.sqrt(np.clip(np.diagonal(normal, axis1=-2, axis2=-1), 0.0, None))
    observable = (scale > 0).all(axis=-1)
    scale = np.where(observable[..., None], scale, 1.0)
    outer = scale[..., :, None] * scale[..., None, :]
    normalized = np.where(observable[..., None, None], normal / outer, np.eye(k))
    inverse = _inverses(normalized)
    observable &= _conditioned(normalized, inverse)
    if inverse is None:
        normalized[~observable] = np.eye(k)
        inverse = np.linalg.inv(normalized)
    else:  # numpy's inverse of the identity, where the matrix is singular
        inverse[~observable] = np.eye(k)
    inverse = inverse / outer
    inverse = 0.5 * (inverse + np.swapaxes(inverse, -1, -2))
    inverse[~observable] = np.nan
    return inverse.reshape(shape)


#: The largest condition number (unit diagonal) of an invertible normal matrix.
MAX_CONDITION = 1e12


def _inverses(normalized: np.ndarray) -> np.ndarray | None:
    """np.linalg.inv of matrices (F, k, k), None where one of them is exactly singular."""
    try:
        with np.errstate(all="ignore"):
            return np.linalg.inv(normalized)
    except np.linalg.LinAlgError:
        return None


def _conditioned(normalized: np.ndarray, inverse: np.ndarray | None) -> np.ndarray:
    """(F,) np.linalg.cond(normalized) <= MAX_CONDITION for matrices (F, k, k), with their inverses
    (`_inverses`) if made: cond = |A|_2 |A^-1|_2 <= |A|_F |A^-1|_F, so a product of the Frobenius norms
    at most half the limit (room for the inverse's rounding) is conditioned; numpy's singular values
    (most of the time of the error model's inverses) decide the others, and every frame without the
    inverses."""
    if inverse is None:
        return np.linalg.cond(normalized) <= MAX_CONDITION
    bound = np.sqrt(np.sum(normalized**2, axis=(1, 2))) * np.sqrt(np.sum(inverse**2, axis=(1, 2)))
    conditioned = bound <= 0.5 * MAX_CONDITION  # NaN: not sure
    unsure = ~conditioned
    if unsure.any():
        conditioned[unsure] = np.linalg.cond(normalized[unsure]) <= MAX_CONDITION
    return conditioned
