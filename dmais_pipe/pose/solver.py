"""The paper's generalized absolute pose solver (section Absolute Pose Estimation).

For generalized rays (origins v_i, unit directions f_i, rig frame) and world points M_i, find
(R, t) with x_rig = R M + t minimising eq. objfun, sum_i ||[f_i]x (R M_i + t - v_i)||^2:

1. O(n) statistics H, g, c with t eliminated (eq. t, objfun3; `statistics.py`);
2. the six optimality conditions E12 ... F23 of eq. EF6 in Cayley parameters q, degree 4 after
   multiplying by (1 + q.q)^2 (`equations.py`, generated with sympy);
3. the elimination template (`_template.json`, built over a prime field by `template.py`):
   one LU factorisation gives the 40 x 40 action matrix of the action variable on the
   standard-monomial basis, whose eigenvectors hold the 40 (complex) solutions;
4. real (and nearly real) roots are mapped to rotations and polished by Newton's method on the
   cost over SO(3) (which also tells true stationary points from complex pairs taken as real),
   their translations follow from eq. t, and the least cost with most points in front wins.

Cayley's blind spot: q = tan(angle / 2) axis is infinite at 180 degrees, and a down-looking rig
over a z-up world is a 180-degree rotation at every yaw. The problem is therefore solved in a
pre-rotated world M' = P M (R = R' P), with P near the sought rotation so that R' stays near
q = 0: P is the most promising of the octahedral group and of a sphere relaxation of eq. objfun3
(`solving_frame`). Unless the first descent step from P heads to the solution found, P is also
descended to a local minimum, which joins the candidates (where the action matrix is
ill-conditioned, e.g. one narrow-FoV camera over a plane, it can be the only copy of the minimum). When the solution lies
beyond 120 deg in that frame, the problem is solved once more in the frame of the solution.
Changing frame costs nothing in n: H' = K^T H K and g' = K^T g with r = K r',
K = blockdiag(P^T, P^T, P^T).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path

import numpy as np
from scipy.linalg.lapack import dgeev, dgesv, dgetrf, dsyevd, dtrtrs

from ..geometry import rotation_angle, skew
from . import PoseError
from .equations import coefficients_of
from .statistics import PoseStatistics, statistics_of, validate_correspondences
from .template import Template, template_entries

TEMPLATE_PATH = Path(__file__).with_name("_template.json")
#: Roots whose imaginary part is below this (relative to 1 + |q|) are polished as real ones:
#: nearly real pairs are where a real double root lost to rounding reappears.
IMAGINARY_TOLERANCE = 1e-1
#: Newton steps on the cost (on SO(3)) that polish every candidate rotation.
NEWTON_ITERATIONS = 2
#: A polished rotation is stationary when its Riemannian gradient is below this fraction of
#: trace(H) + |g|.
STATIONARY_TOLERANCE = 1e-8
#: Rotations closer than this (max abs entry difference) are one candidate.
DUPLICATE_TOLERANCE = 1e-9
#: Gauss-Newton steps at most that move the solving frame from its start to a minimum.
DESCENT_ITERATIONS = 30
#: Longest descent step (radians).
MAX_STEP = 0.5
#: The descent stops after a step shorter than this (radians); Newton polishing continues.
STEP_TOLERANCE = 1e-3
#: Relative rounding level of the cost evaluated as a quadratic form (of trace H + |g| + |c|).
COST_ROUNDING = 1e-12
#: Newton steps at most on the secular equation of the sphere relaxation, and their relative
#: tolerance (the relaxed rotations only start the descent).
SPHERE_ITERATIONS = 30
SPHERE_TOLERANCE = 1e-6
#: Points whose least spread is below this fraction of the middle one are (nearly) planar: the
#: sphere relaxation then has a null space, and its planar version joins the starts (thickness
#: below 1% of the width).
PLANAR_SPREAD = 1e-4
#: Beyond this angle (|q| > tan(60 deg)) in the solving frame, the problem is solved again in
#: the frame of the winner.
MAX_FRAME_ANGLE = np.deg2rad(120.0)


@dataclass(frozen=True)
class Candidate:
    """A real stationary point of eq. objfun: rotation (3, 3), translation (3,), cost, and the
    fraction of points it puts in front of their rays."""

    R: np.ndarray
    t: np.ndarray
    cost: float
    in_front: float


@dataclass(frozen=True)
class GeneralizedPose:
    """Solution of the generalized absolute pose problem: x_rig = R @ M + t.

    R (3, 3), t (3,), cost: value of eq. objfun at (R, t); candidates: every real stationary
    point found, least cost first (the solution is the cheapest with most points in front of
    their rays, usually candidates[0]); n_points: correspondences.
    covariance: (6, 6) of (rotation increment, t) when refined, else None.
    """

    R: np.ndarray
    t: np.ndarray
    cost: float
    candidates: list[Candidate]
    n_points: int
    covariance: np.ndarray | None = None


# ------------------------------------------------------------------------------ runtime template


@dataclass(frozen=True)
class _Runtime:
    """Index arrays that turn (6, n_monomials) coefficients into the template and action matrix."""

    m: int
    n_columns: int
    n_reducible: int
    target: np.ndarray  # flat indices into the column-major (m, n_columns) template
    source: np.ndarray  # flat indices into the (6, n_monomials) coefficients
    shifts: np.ndarray  # (40, 40) action matrix rows whose x * b is a basis monomial, else zero
    reduced_rows: np.ndarray  # basis rows whose x * b is reducible ...
    reduced_index: np.ndarray  # ... namely this row of the reduced block
    unit_index: np.ndarray  # basis indices of the monomials 1, qx, qy, qz


@lru_cache(maxsize=1)
def runtime() -> _Runtime:
    """The template of `_template.json` prepared for the solver (loaded once)."""
    template = Template.from_json(TEMPLATE_PATH.read_text())
    m, n_columns = template.shape
    target, source = template_entries(template.rows, template.columns)
    basis = {mono: j for j, mono in enumerate(template.basis)}
    reducible = {mono: j for j, mono in enumerate(template.reducible)}
    unit = tuple(int(i == template.action_variable) for i in range(3))
    shifts = np.zeros((len(basis), len(basis)))
    reduced_rows, reduced_index = [], []
    for i, b in enumerate(template.basis):
        product = (b[0] + unit[0], b[1] + unit[1], b[2] + unit[2])
        if product in basis:
            shifts[i, basis[product]] = 1.0
        else:
            reduced_rows.append(i)
            reduced_index.append(reducible[product])
    units = [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)]
    return _Runtime(
        m=m,
        n_columns=n_columns,
        n_reducible=template.n_reducible,
        target=(target % n_columns) * m + target // n_columns,
        source=source,
        shifts=shifts,
        reduced_rows=np.array(reduced_rows),
        reduced_index=np.array(reduced_index),
        unit_index=np.array([basis[u] for u in units]),
    )


def action_matrix(coeffs: np.ndarray) -> np.ndarray:
    """Action matrix (40, 40) for equation coefficients (6, n_monomials).

    Row i expresses x * b_i in the basis: x * B(q) = M B(q) at every solution q. One LU
    factorisation of the whole template [C_E C_R | C_B] = P L [U_11 | U_12] leaves the rows of the
    reducible monomials R alone at the bottom: U_RR R + U_RB B = 0.
    """
    rt = runtime()
    template = np.zeros(rt.m * rt.n_columns)
    template[rt.target] = coeffs.reshape(-1)[rt.source]
    lu, _, _ = dgetrf(template.reshape(rt.n_columns, rt.m).T, overwrite_a=True)
    e = rt.m - rt.n_reducible
    reduced, _ = dtrtrs(lu[e : rt.m, e : rt.m], lu[e : rt.m, rt.m :])
    M = rt.shifts.copy()
    M[rt.reduced_rows] = -reduced[rt.reduced_index]
    return M


def roots(coeffs: np.ndarray) -> np.ndarray:
    """The complex solutions q (k, 3) of the equations with coefficients (6, n_monomials), one of
    each complex conjugate pair (k <= 40)."""
    rt = runtime()
    real, imag, _, vectors, _ = dgeev(action_matrix(coeffs), compute_vl=False)
    units = vectors[rt.unit_index].astype(complex)  # (4, 40): values of 1, qx, qy, qz
    pairs = np.flatnonzero(imag > 0)  # LAPACK packs a pair's vector as re, im in columns j, j + 1
    units[:, pairs] += 1j * vectors[rt.unit_index][:, pairs + 1]
    units = units[:, imag >= 0]
    return (units[1:] / units[:1]).T


# ------------------------------------------------------------------------------ cost on SO(3)


_IDENTITY = np.eye(3)
_GENERATORS = np.array([skew(e) for e in _IDENTITY])  # [e_a]x, (3, 3, 3)
_PRODUCTS = np.einsum("aij,bjk->abik", _GENERATORS, _GENERATORS)
#: Rows vec(G_a) then vec((G_a G_b + G_b G_a) / 2), (12, 9): with A = mat(H r - g) R^T, the
#: gradient of w -> cost(exp([w]x) R) / 2 is <G_a, A> and its curvature term <(G_a G_b + G_b G_a) / 2, A>.
_DERIVATIVE_ROWS = np.vstack([_GENERATORS.reshape(3, 9), (0.5 * (_PRODUCTS + _PRODUCTS.transpose(1, 0, 2, 3))).reshape(9, 9)])


def _cayley(q: np.ndarray) -> np.ndarray:
    """Rotations (k, 3, 3) of Cayley parameters q (k, 3), as `geometry.rotation_from_cayley`.

    Cayley(w / 2) = exp([w]x) + O(|w|^3) makes the update of the descent and of Newton's method.
    """
    qq = np.einsum("ki,ki->k", q, q)
    R = q[:, :, None] * q[:, None, :] + (q @ _GENERATORS.reshape(3, 9)).reshape(-1, 3, 3)
    R *= 2.0
    R += (1.0 - qq)[:, None, None] * _IDENTITY
    return R / (1.0 + qq)[:, None, None]


def _derivatives(stats: PoseStatistics, R: np.ndarray, newton: bool):
    """Half gradient (k, 3) and half Hessian (k, 3, 3) of w -> cost(exp([w]x) R) at w = 0, R (k, 3, 3).

    With r = vec(R), J (k, 3, 9) the rows vec(G_a R) and A = mat(H r - g) R^T: gradient
    <G_a, A> = J (H r - g), Gauss-Newton matrix J H J^T; `newton` adds the curvature term
    <(G_a G_b + G_b G_a) / 2, A>.
    """
    k = len(R)
    J = np.matmul(_GENERATORS[None], R[:, None]).reshape(k, 3, 9)
    A = np.matmul((R.reshape(k, 9) @ stats.H - stats.g).reshape(k, 3, 3), R.transpose(0, 2, 1))
    terms = A.reshape(k, 9) @ (_DERIVATIVE_ROWS.T if newton else _DERIVATIVE_ROWS[:3].T)
    hessian = J @ stats.H @ J.transpose(0, 2, 1)
    if newton:
        hessian += terms[:, 3:].reshape(k, 3, 3)
    return terms[:, :3], hessian


def descend(stats: PoseStatistics, R: np.ndarray, iterations: int = DESCENT_ITERATIONS) -> np.ndarray:
    """Damped Gauss-Newton descent of the cost on SO(3), R <- exp([w]x) R, from R (3, 3).

    The Gauss-Newton matrix J^T H J is positive semi-definite, so each damped step goes downhill
    even far from a minimum; steps are capped at MAX_STEP radians. Stops after a step shorter
    than STEP_TOLERANCE (`polish` finishes the job). Returns the end point (3, 3).
    """
    R = R[None]
    cost = stats.cost(R)
    damping = 1e-6
    scale = np.trace(stats.H)
    for _ in range(iterations):
        gradient, hessian = _derivatives(stats, R, newton=False)
        step = -dgesv(hessian[0] + damping * scale * _IDENTITY, gradient[0])[2]
        norm = np.sqrt(step @ step)
        trial = _cayley(step[None] * min(0.5, 0.5 * MAX_STEP / max(norm, 1e-300))) @ R
        trial_cost = stats.cost(trial)
        if trial_cost[0] <= cost[0]:
            R, cost, damping = trial, trial_cost, damping / 10
            if norm < STEP_TOLERANCE:
                break
        else:
            damping *= 10
            if damping > 1e8:
                break
    return R[0]


def polish(stats: PoseStatistics, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Newton's method on the cost on SO(3) from every R (k, 3, 3): the nearby stationary points.

    Returns the polished rotations (k, 3, 3) and which of them are stationary (k,): Riemannian
    gradient below STATIONARY_TOLERANCE (trace H + |g|) before the last step. Starts that are no
    roots (e.g. a complex pair taken as real) end elsewhere, usually not stationary, or on another
    candidate.
    """
    scale = np.trace(stats.H) + np.linalg.norm(stats.g)
    ridge = 1e-14 * scale * _IDENTITY
    for _ in range(NEWTON_ITERATIONS):
        gradient, hessian = _derivatives(stats, R, newton=True)
        step = -np.linalg.solve(hessian + ridge, gradient[:, :, None])[:, :, 0]
        R = _cayley(0.5 * step) @ R
    return R, np.linalg.norm(gradient, axis=1) < STATIONARY_TOLERANCE * scale


# ------------------------------------------------------------------------------ frames


def _octahedral_group() -> np.ndarray:
    """The 24 rotations that map coordinate axes to coordinate axes, (24, 3, 3)."""
    rotations = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            R = np.zeros((3, 3))
            R[range(3), perm] = signs
            if np.linalg.det(R) > 0:
                rotations.append(R)
    return np.array(rotations)


OCTAHEDRAL = _octahedral_group()


def _in_frame(H: np.ndarray, g: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """H', g' of the problem in the world M' = P M (R = R' P)."""
    K = np.zeros((9, 9))  # r = K r', K = blockdiag(P^T, P^T, P^T)
    K[0:3, 0:3] = K[3:6, 3:6] = K[6:9, 6:9] = P.T
    return K.T @ H @ K, K.T @ g


def _sphere_minimisers(H: np.ndarray, g: np.ndarray, radius2: float) -> np.ndarray:
    """x and -x (2, d) for the minimiser x of x^T H x - 2 g^T x on the sphere |x|^2 = radius2.

    H (d, d) symmetric, g (d,). The trust-region subproblem: x = (H - mu I)^-1 g with mu below the
    least eigenvalue of H, found by Newton's method on 1/|x(mu)| (More and Sorensen), which is
    concave and so approached monotonically from mu's upper bound |b_0| / sqrt(radius2); in the
    hard case (g without weight on the least eigenvector) x is completed along that eigenvector.
    """
    eigenvalues, vectors, _ = dsyevd(H)
    b = vectors.T @ g
    gap = eigenvalues - eigenvalues[0]
    hard = np.zeros_like(b)
    hard[1:] = b[1:] / np.maximum(gap[1:], 1e-300)
    if hard @ hard < radius2 and abs(b[0]) <= 1e-12 * np.linalg.norm(b):
        hard[0] = np.sqrt(radius2 - hard @ hard)
        x = vectors @ hard
    else:
        shift = max(abs(b[0]), 1e-300) / np.sqrt(radius2)  # eigenvalues[0] - mu: a lower bound
        for _ in range(SPHERE_ITERATIONS):
            y = b / (gap + shift)
            norm = np.sqrt(y @ y)
            # Newton on phi(shift) = 1/|y| - 1/sqrt(radius2), d|y|/dshift = -(y . y / (gap + shift)) / |y|
            change = (1.0 / norm - 1.0 / np.sqrt(radius2)) * norm**3 / (y @ (y / (gap + shift)))
            shift = max(shift - change, 0.5 * shift)
            if abs(change) <= SPHERE_TOLERANCE * shift:
                break
        x = vectors @ (b / (gap + shift))
    return np.array([x, -x])


def _rotation_nearest(X: np.ndarray) -> np.ndarray:
    """The rotations (k, 3, 3) nearest (Frobenius) to matrices X (k, 3, 3)."""
    U, _, Vt = np.linalg.svd(X)
    U[:, :, 2] *= np.sign(np.linalg.det(U @ Vt))[:, None]
    return U @ Vt


def relaxed_rotations(stats: PoseStatistics) -> np.ndarray:
    """Rotations (2 or 4, 3, 3) near the minimum from the sphere relaxation |vec R|^2 = 3 of
    eq. objfun3 and, for (nearly) planar points, from its planar version (R on the two widest
    principal axes of the points, which alone matter for planar points, |.|^2 = 2, completed by
    their cross product), each with its mirror. O(1).
    """
    trace = np.trace(stats.H)
    relaxed = [_sphere_minimisers(stats.H / trace, stats.g / trace, 3.0).reshape(2, 3, 3)]
    if stats.point_spread[0] < PLANAR_SPREAD * stats.point_spread[1]:
        axes = stats.point_axes  # M = axes @ m: R M = (R axes) m
        H, g = _in_frame(stats.H / trace, stats.g / trace, axes.T)
        in_plane = np.array([1, 2, 4, 5, 7, 8])  # columns 1, 2 of R axes (the widest axes)
        columns = _sphere_minimisers(H[np.ix_(in_plane, in_plane)], g[in_plane], 2.0).reshape(2, 3, 2)
        a, b = columns[:, :, 0], columns[:, :, 1]
        normal = a[:, [1, 2, 0]] * b[:, [2, 0, 1]] - a[:, [2, 0, 1]] * b[:, [1, 2, 0]]
        relaxed.append(np.concatenate([normal[:, :, None], columns], axis=2) @ axes.T)
    return _rotation_nearest(np.concatenate(relaxed))


def ray_sides(origins, directions, points) -> tuple[np.ndarray, np.ndarray]:
    """What `front_fraction` needs of the correspondences: [kron(f_i, M_i), f_i] (n, 12) and
    v_i . f_i (n,), so that the depth of point i along its ray (alpha in eq. projEq, f unit) is
    f_i . (R M_i + t - v_i) = [vec R, t] . row_i - v_i . f_i."""
    n = len(points)
    kron = (directions[:, :, None] * points[:, None, :]).reshape(n, 9)
    return np.hstack([kron, directions]), np.einsum("ni,ni->n", origins, directions)


def front_fraction(R: np.ndarray, t: np.ndarray, sides) -> np.ndarray:
    """Fraction of points in front of their rays (alpha > 0 in eq. projEq) per pose, (k,).

    R: (k, 3, 3), t: (k, 3), sides: `ray_sides` of the correspondences; O(k n).
    """
    rows, offsets = sides
    depth = np.hstack([R.reshape(-1, 9), t]) @ rows.T - offsets  # (k, n)
    return (depth > 0).mean(axis=1)


def solving_frame(stats: PoseStatistics, sides) -> np.ndarray:
    """Rotation P (3, 3) near the sought rotation: the most promising of the octahedral group and
    the relaxed rotations (`relaxed_rotations`).

    The cost alone misleads: it ignores on which side of its ray origin a point lies, and a
    "mirror" pose with the points behind the cameras, about 180 deg from the truth, often costs
    less than the octahedral rotations near the truth. So each rotation's cost is weighted by the
    fraction of points it puts behind their rays (plus 0.05, so that cost still decides among
    rotations that put every point in front); costs below the rounding level of the quadratic
    form count as that level, so that an exact fit and its mirror are told apart. O(n).
    """
    starts = np.concatenate([OCTAHEDRAL, relaxed_rotations(stats)])
    front = front_fraction(starts, stats.translation(starts), sides)
    rounding = COST_ROUNDING * (np.trace(stats.H) + np.linalg.norm(stats.g) + abs(stats.c))
    score = np.maximum(stats.cost(starts), rounding) * (1.0 - front + 0.05)
    return starts[np.argmin(score)]


def _select(cost: np.ndarray, front: np.ndarray) -> int:
    """Index of the solution: least cost among the poses with most points in front, if any.

    Eq. objfun measures distances to lines, not rays, so a pose and its mirror that puts the
    points behind the cameras can cost the same: exactly so for a central camera and a planar
    scene (R and R Rz(180 deg) about the plane normal), nearly so for any almost-central rig.
    """
    feasible = front >= 0.5
    pool = np.flatnonzero(feasible) if feasible.any() else np.arange(len(cost))
    return int(pool[np.argmin(cost[pool])])


def _real_roots(H: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Real parts (k, 3) of the real and nearly real Cayley roots of the equations for H, g."""
    trace = np.trace(H)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = roots(coefficients_of(H / trace, g / trace))
    size = 1.0 + np.abs(q).max(axis=1)
    return q[np.abs(q.imag).max(axis=1) < IMAGINARY_TOLERANCE * size].real  # False for NaN


def _roots_in_frame(stats: PoseStatistics, P: np.ndarray) -> np.ndarray:
    """Rotations (k, 3, 3) of the real (and nearly real) roots of the equations in the frame P."""
    return _cayley(_real_roots(*_in_frame(stats.H, stats.g, P))) @ P


def _unique(R: np.ndarray, cost: np.ndarray) -> np.ndarray:
    """Indices of the candidates sorted by cost, duplicate rotations (e.g. polished conjugate
    pairs) removed."""
    order = np.argsort(cost)
    R = R[order]
    same = np.abs(R[:, None] - R[None]).reshape(len(R), len(R), 9).max(axis=2) < DUPLICATE_TOLERANCE
    first = np.argmax(same, axis=1)  # index of the first (cheapest) rotation equal to each
    return order[first == np.arange(len(R))]


def _stationary(stats: PoseStatistics, R: np.ndarray) -> np.ndarray:
    """The stationary rotations (k', 3, 3) that `polish` reaches from R (k, 3, 3)."""
    R, stationary = polish(stats, R)
    return R[stationary]


def _evaluate(stats: PoseStatistics, R: np.ndarray, sides):
    """Cost (k,), translation (k, 3) and fraction of points in front (k,) of rotations R (k, 3, 3)."""
    t = stats.translation(R)
    return stats.cost(R), t, front_fraction(R, t, sides)


def _heads_to(P: np.ndarray, step: np.ndarray, solution: np.ndarray) -> bool:
    """Whether the first descent step from P (3, 3), to `step` (3, 3), brings it within a quarter
    of its distance to `solution` (3, 3): then P lies in the basin of the solution, where the
    descent would end."""
    return rotation_angle(step @ solution.T) <= 0.25 * rotation_angle(P @ solution.T)


def solve_statistics(stats: PoseStatistics, origins, directions, points) -> tuple[list[Candidate], int]:
    """All real stationary candidates, least cost first, and the index of the solution among them.

    There is always at least one: unless the first descent step from the solving frame heads to
    the solution, the frame descended to a local minimum is a candidate.
    origins, directions, points: the validated correspondences that `stats` summarises.
    """
    # Solving where the sought rotation is near q = 0 keeps it away from Cayley's blind spot. A
    # descent from P ends at the solution when its first step heads there; otherwise the local
    # minimum it ends at joins the candidates, in case the roots missed it.
    sides = ray_sides(origins, directions, points)
    P = solving_frame(stats, sides)
    R, stationary = polish(stats, np.concatenate([P[None], _roots_in_frame(stats, P)]))
    R = R[stationary]
    cost, t, front = _evaluate(stats, R, sides)
    step = descend(stats, P, iterations=1)
    if not len(R) or not _heads_to(P, step, R[_select(cost, front)]):
        R = np.concatenate([R, polish(stats, descend(stats, step)[None])[0]])
        cost, t, front = _evaluate(stats, R, sides)
    best = _select(cost, front)
    more = []
    if np.trace(R[best] @ P.T) < 1.0 + 2.0 * np.cos(MAX_FRAME_ANGLE):
        more.append(_stationary(stats, _roots_in_frame(stats, R[best])))
    # A cheaper pose with the points behind the rays: its mirror (180 deg about the normal of
    # the points) is where the roots of an ill-conditioned planar scene may have missed the minimum.
    behind = (front < 0.5) & (cost < cost[best])
    if behind.any():
        normal = stats.point_axes[:, 0]
        more.append(_stationary(stats, R[behind] @ (2.0 * np.outer(normal, normal) - _IDENTITY)))
    if more:
        R = np.concatenate([R, *more])
        cost, t, front = _evaluate(stats, R, sides)
    keep = _unique(R, cost)
    cost, front = cost[keep], front[keep]
    candidates = [Candidate(R=Ri, t=ti, cost=max(ci, 0.0), in_front=fi)
                  for Ri, ti, ci, fi in zip(R[keep], t[keep], cost.tolist(), front.tolist())]
    return candidates, _select(cost, front)


def solve_generalized_pose(origins, directions, points, refine: bool = False, sigma: float | None = None) -> GeneralizedPose:
    """Globally optimal generalized absolute pose (see the module docstring).

    origins: (n, 3) ray origins v_i in the rig frame; directions: (n, 3) ray directions f_i in
    the rig frame (any length > 0); points: (n, 3) world points M_i; n >= 3, not collinear.
    refine: polish the solution on the angular reprojection error (`refine.refine_pose`) and
    return its (6, 6) covariance of (rotation increment, t); sigma: the angular noise (radians)
    for that covariance, else estimated from the residuals. Returns x_rig = R @ M + t.
    """
    origins, directions, points = validate_correspondences(origins, directions, points)
    stats = statistics_of(origins, directions, points)
    candidates, best = solve_statistics(stats, origins, directions, points)
    solution = candidates[best]
    pose = GeneralizedPose(R=solution.R, t=solution.t, cost=solution.cost, candidates=candidates, n_points=stats.n)
    if not refine:
        return pose
    from .refine import refine_pose

    refined = refine_pose(origins, directions, points, pose.R, pose.t, sigma=sigma)
    cost = float(np.sum(np.cross(directions, points @ refined.R.T + refined.t - origins) ** 2))
    return replace(pose, R=refined.R, t=refined.t, cost=cost, covariance=refined.covariance)


def solve_batch(problems, refine: bool = False) -> list[GeneralizedPose | PoseError]:
    """Solve many frames in one call: problems is an iterable of (origins, directions, points).

    Returns one GeneralizedPose per frame, or the PoseError that frame raised (so one bad frame
    does not lose the others).
    """
    results: list[GeneralizedPose | PoseError] = []
    for origins, directions, points in problems:
        try:
            results.append(solve_generalized_pose(origins, directions, points, refine=refine))
        except PoseError as error:
            results.append(error)
    return results
