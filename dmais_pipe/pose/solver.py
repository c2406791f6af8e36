"""The paper's generalized absolute pose solver (section Absolute Pose Estimation).

For generalized rays (origins v_i, unit directions f_i, rig frame) and world points M_i, find
(R, t) with x_rig = R M + t minimising eq. objfun, sum_i ||[f_i]x (R M_i + t - v_i)||^2:

1. O(n) statistics H, g, c with t eliminated (eq. t, objfun3; `statistics.py`);
2. the six optimality conditions E12 ... F23 of eq. EF6 in Cayley parameters q, degree 4 after
   multiplying by (1 + q.q)^2 (`equations.py`, generated with sympy);
3. the elimination template (`_template.json`, built over a prime field by `template.py`):
   one LU solve gives the 40 x 40 action matrix of the action variable on the standard-monomial
   basis, whose eigenvectors hold the 40 (complex) solutions;
4. real (and nearly real) roots are polished by Gauss-Newton on the six equations, mapped to
   rotations, their translations follow from eq. t, and the least cost wins.

Cayley's blind spot: q = tan(angle / 2) axis is infinite at 180 degrees, and a down-looking rig
over a z-up world is a 180-degree rotation at every yaw. The problem is therefore solved in a
pre-rotated world M' = P M (R = R' P), with P near the sought rotation so that R' stays near
q = 0, where the roots are most accurate: P is a local minimum of the cost with most points in
front, descended from the most promising rotations of the octahedral group (`solving_frame`).
When the solution still lies beyond 120 deg in that frame, the problem is solved once more in the
frame of the solution. Changing frame costs nothing in n: H' = K^T H K and g' = K^T g with
r = K r', K = blockdiag(P^T, P^T, P^T).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path

import numpy as np

from ..geometry import rotation_from_cayley, skew
from . import PoseError
from .equations import MONOMIALS, coefficients_of, evaluate_equations
from .statistics import PoseStatistics, pose_statistics, validate_correspondences
from .template import Template, template_entries

TEMPLATE_PATH = Path(__file__).with_name("_template.json")
#: Roots whose imaginary part is below this (relative to 1 + |q|) are polished as real ones:
#: nearly real pairs are where a real double root lost to rounding reappears.
IMAGINARY_TOLERANCE = 1e-1
#: Gauss-Newton steps on the six equations for every candidate root.
POLISH_ITERATIONS = 5
#: A polished root is kept when every equation is below this fraction of |coefficients| max(1, |q|)^4.
ROOT_TOLERANCE = 1e-6
#: Rotations closer than this (max abs entry difference) are one candidate.
DUPLICATE_TOLERANCE = 1e-9
#: Gauss-Newton steps that move the solving frame from the best octahedral rotation to a minimum.
DESCENT_ITERATIONS = 30
#: Longest descent step (radians).
MAX_STEP = 0.5
#: The descent stops after a step shorter than this (radians).
STEP_TOLERANCE = 1e-10
#: Octahedral rotations descended to find the solving frame.
FRAME_STARTS = 3
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
    target: np.ndarray  # flat indices into the (m, n_columns) template
    source: np.ndarray  # flat indices into the (6, n_monomials) coefficients
    shift_rows: np.ndarray  # basis rows whose x * b is a basis monomial ...
    shift_cols: np.ndarray  # ... namely this one
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
    shift_rows, shift_cols, reduced_rows, reduced_index = [], [], [], []
    for i, b in enumerate(template.basis):
        product = (b[0] + unit[0], b[1] + unit[1], b[2] + unit[2])
        if product in basis:
            shift_rows.append(i)
            shift_cols.append(basis[product])
        else:
            reduced_rows.append(i)
            reduced_index.append(reducible[product])
    units = [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)]
    return _Runtime(
        m=m,
        n_columns=n_columns,
        n_reducible=template.n_reducible,
        target=target,
        source=source,
        shift_rows=np.array(shift_rows),
        shift_cols=np.array(shift_cols),
        reduced_rows=np.array(reduced_rows),
        reduced_index=np.array(reduced_index),
        unit_index=np.array([basis[u] for u in units]),
    )


def action_matrices(coeffs: np.ndarray) -> np.ndarray:
    """Action matrices (F, 40, 40) for equation coefficients (F, 6, n_monomials).

    Row i expresses x * b_i in the basis: x * B(q) = M B(q) at every solution q.
    """
    rt = runtime()
    frames = coeffs.shape[0]
    template = np.zeros((frames, rt.m * rt.n_columns))
    template[:, rt.target] = coeffs.reshape(frames, -1)[:, rt.source]
    template = template.reshape(frames, rt.m, rt.n_columns)
    eliminated = np.linalg.solve(template[:, :, : rt.m], template[:, :, rt.m :])  # (F, m, 40)
    reduced = eliminated[:, rt.m - rt.n_reducible :]  # rows r + reduced @ B = 0, r in R
    n_basis = rt.n_columns - rt.m
    M = np.zeros((frames, n_basis, n_basis))
    M[:, rt.shift_rows, rt.shift_cols] = 1.0
    M[:, rt.reduced_rows] = -reduced[:, rt.reduced_index]
    return M


def roots(coeffs: np.ndarray) -> np.ndarray:
    """All 40 complex solutions q, (F, 40, 3), of the equations with coefficients (F, 6, n_monomials)."""
    rt = runtime()
    _, vectors = np.linalg.eig(action_matrices(coeffs))
    units = vectors[:, rt.unit_index, :]  # (F, 4, 40): values of 1, qx, qy, qz
    return np.transpose(units[:, 1:] / units[:, :1], (0, 2, 1))


# ------------------------------------------------------------------------------ polishing


_EXPONENTS = MONOMIALS.T  # (3, n_monomials)


def _monomials_and_derivatives(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Monomial values (k, n_monomials) and their gradients (k, n_monomials, 3) at q (k, 3)."""
    powers = q[:, :, None] ** np.arange(5)  # (k, 3, 5)
    value = [powers[:, i, _EXPONENTS[i]] for i in range(3)]  # each (k, n_monomials)
    lower = [powers[:, i, np.maximum(_EXPONENTS[i] - 1, 0)] * _EXPONENTS[i] for i in range(3)]
    monomials = value[0] * value[1] * value[2]
    gradient = np.stack(
        [lower[0] * value[1] * value[2], value[0] * lower[1] * value[2], value[0] * value[1] * lower[2]], axis=-1
    )
    return monomials, gradient


def polish(coeffs: np.ndarray, q: np.ndarray, iterations: int = POLISH_ITERATIONS) -> np.ndarray:
    """Gauss-Newton on the six equations (coefficients (6, n_monomials)) from real q (k, 3)."""
    q = np.array(q, dtype=float)
    for _ in range(iterations):
        monomials, gradient = _monomials_and_derivatives(q)
        residual = monomials @ coeffs.T  # (k, 6)
        J = np.einsum("em,kmi->kei", coeffs, gradient)  # (k, 6, 3)
        JtJ = np.einsum("kei,kej->kij", J, J)
        Jtr = np.einsum("kei,ke->ki", J, residual)
        ok = np.abs(np.linalg.det(JtJ)) > 1e-300
        if not ok.any():
            break
        q[ok] -= np.linalg.solve(JtJ[ok], Jtr[ok][:, :, None])[:, :, 0]
    return q


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
    K = np.kron(np.eye(3), P.T)
    return K.T @ H @ K, K.T @ g


def _real_roots(H: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Polished real Cayley parameters (k, 3) of the stationary points for statistics H, g."""
    trace = np.trace(H)
    coeffs = coefficients_of(H / trace, g / trace)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = roots(coeffs[None])[0]
    size = 1.0 + np.abs(q).max(axis=1)
    nearly_real = np.abs(q.imag).max(axis=1) < IMAGINARY_TOLERANCE * size  # False for NaN
    q = polish(coeffs, q[nearly_real].real)
    # a complex pair polished as if real converges to a minimum of |equations|, not to a root
    scale = np.abs(coeffs).sum(axis=1) * np.maximum(1.0, np.abs(q).max(axis=1, initial=0.0))[:, None] ** 4
    residual = np.abs(evaluate_equations(coeffs, q)).reshape(-1, 6) / scale
    return q[residual.max(axis=1, initial=0.0) < ROOT_TOLERANCE]


def _solve_in_frame(stats: PoseStatistics, P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotations (k, 3, 3) in the original frame, their costs (k,) and Cayley parameters in frame P."""
    q = _real_roots(*_in_frame(stats.H, stats.g, P))
    R = rotation_from_cayley(q).reshape(-1, 3, 3) @ P
    return R, np.atleast_1d(stats.cost(R)), q


def _unique(R: np.ndarray, cost: np.ndarray) -> np.ndarray:
    """Indices of the candidates sorted by cost, duplicate rotations (e.g. polished conjugate
    pairs) removed."""
    order = np.argsort(cost)
    R = R[order]
    same = np.abs(R[:, None] - R[None]).reshape(len(R), len(R), 9).max(axis=2) < DUPLICATE_TOLERANCE
    first = np.argmax(same, axis=1)  # index of the first (cheapest) rotation equal to each
    return order[first == np.arange(len(R))]


_GENERATORS = np.array([skew(e) for e in np.eye(3)])  # [e_k]x, (3, 3, 3)


def descend(stats: PoseStatistics, R: np.ndarray, iterations: int = DESCENT_ITERATIONS) -> np.ndarray:
    """Damped Gauss-Newton descent of the cost on SO(3), R <- exp([w]x) R, from every R (k, 3, 3).

    The Gauss-Newton matrix J^T H J (J = d vec(R) / d w) is positive semi-definite, so each
    damped step goes downhill even far from a minimum; steps are capped at MAX_STEP radians.
    Returns the end points (k, 3, 3).
    """
    R = np.array(R, dtype=float)
    k = len(R)
    cost = stats.cost(R)
    damping = np.full(k, 1e-6)
    scale = np.trace(stats.H)
    active = np.ones(k, dtype=bool)
    for _ in range(iterations):
        J = np.einsum("aij,kjl->kail", _GENERATORS, R).reshape(k, 3, 9)  # rows: d vec(R) / d w_a
        gradient = J @ (R.reshape(k, 9) @ stats.H - stats.g)[:, :, None]
        hessian = J @ stats.H @ J.transpose(0, 2, 1) + (damping * scale)[:, None, None] * np.eye(3)
        step = -np.linalg.solve(hessian, gradient)[:, :, 0]
        norm = np.linalg.norm(step, axis=1)
        step *= np.minimum(1.0, MAX_STEP / np.maximum(norm, 1e-300))[:, None]
        trial = rotation_from_cayley(step / 2) @ R  # Cayley(w / 2) = exp([w]x) + O(|w|^3)
        trial_cost = stats.cost(trial)
        better = (trial_cost <= cost) & active
        R[better], cost[better] = trial[better], trial_cost[better]
        damping = np.where(better, damping / 10, damping * 10)
        active &= ~(better & (norm < STEP_TOLERANCE)) & (damping < 1e8)
        if not active.any():
            break
    return R


def front_fraction(R: np.ndarray, t: np.ndarray, origins, directions, points) -> np.ndarray:
    """Fraction of points in front of their rays (alpha > 0 in eq. projEq) per pose, (k,).

    R: (k, 3, 3), t: (k, 3); O(k n).
    """
    x_rig = np.einsum("kij,nj->kni", R, points) + t[:, None, :] - origins  # (k, n, 3)
    return (np.einsum("kni,ni->kn", x_rig, directions) > 0).mean(axis=1)


def solving_frame(stats: PoseStatistics, origins, directions, points) -> np.ndarray:
    """Rotation P (3, 3) near the sought rotation: a local minimum of the cost with most points
    in front, descended from the most promising rotations of the octahedral group.

    The cost alone misleads: it ignores on which side of its ray origin a point lies, and a
    "mirror" pose with the points behind the cameras, about 180 deg from the truth, often costs
    less than the octahedral rotations near the truth. So each rotation's cost is weighted by the
    fraction of points it puts behind their rays (plus 0.05, so that cost still decides among
    rotations that put every point in front), and the best FRAME_STARTS of them are descended.
    O(24 n).
    """
    front = front_fraction(OCTAHEDRAL, stats.translation(OCTAHEDRAL), origins, directions, points)
    starts = np.argsort(stats.cost(OCTAHEDRAL) * (1.0 - front + 0.05))[:FRAME_STARTS]
    ends = descend(stats, OCTAHEDRAL[starts])
    front = front_fraction(ends, stats.translation(ends), origins, directions, points)
    return ends[_select(stats.cost(ends), front)]


def _select(cost: np.ndarray, front: np.ndarray) -> int:
    """Index of the solution: least cost among the poses with most points in front, if any.

    Eq. objfun measures distances to lines, not rays, so a pose and its mirror that puts the
    points behind the cameras can cost the same: exactly so for a central camera and a planar
    scene (R and R Rz(180 deg) about the plane normal), nearly so for any almost-central rig.
    """
    feasible = front >= 0.5
    pool = np.flatnonzero(feasible) if feasible.any() else np.arange(len(cost))
    return int(pool[np.argmin(cost[pool])])


def solve_statistics(stats: PoseStatistics, origins, directions, points) -> tuple[list[Candidate], int]:
    """All real stationary candidates, least cost first, and the index of the solution among them.

    There is always at least one: the solving frame, a descended local minimum, is a candidate.
    origins, directions, points: the validated correspondences that `stats` summarises.
    """
    # Solve where the sought rotation is near q = 0: the roots are most accurate there (a
    # rotation error of ~1e-16 against up to 1e-4 at 60-120 deg from the frame on narrow-FoV
    # rigs). The descended frame is a stationary point itself and joins the candidates: where the
    # action matrix is ill-conditioned (one narrow-FoV camera over a plane) it can be the only
    # copy of the minimum.
    P = solving_frame(stats, origins, directions, points)
    R, cost, q = _solve_in_frame(stats, P)
    R, cost, q = np.concatenate([R, P[None]]), np.append(cost, stats.cost(P)), np.vstack([q, np.zeros(3)])
    t = stats.translation(R)
    front = front_fraction(R, t, origins, directions, points)
    best = _select(cost, front)
    if np.linalg.norm(q[best]) > np.tan(MAX_FRAME_ANGLE / 2):
        R2, cost2, _ = _solve_in_frame(stats, R[best])
        t2 = stats.translation(R2)
        R, cost, t = np.concatenate([R, R2]), np.concatenate([cost, cost2]), np.concatenate([t, t2])
        front = np.concatenate([front, front_fraction(R2, t2, origins, directions, points)])
    keep = _unique(R, cost)
    candidates = [Candidate(R=R[i], t=t[i], cost=max(float(cost[i]), 0.0), in_front=float(front[i])) for i in keep]
    return candidates, _select(cost[keep], front[keep])


def solve_generalized_pose(origins, directions, points, refine: bool = False, sigma: float | None = None) -> GeneralizedPose:
    """Globally optimal generalized absolute pose (see the module docstring).

    origins: (n, 3) ray origins v_i in the rig frame; directions: (n, 3) ray directions f_i in
    the rig frame (any length > 0); points: (n, 3) world points M_i; n >= 3, not collinear.
    refine: polish the solution on the angular reprojection error (`refine.refine_pose`) and
    return its (6, 6) covariance of (rotation increment, t); sigma: the angular noise (radians)
    for that covariance, else estimated from the residuals. Returns x_rig = R @ M + t.
    """
    origins, directions, points = validate_correspondences(origins, directions, points)
    stats = pose_statistics(origins, directions, points)
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
