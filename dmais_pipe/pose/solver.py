"""The paper's generalized absolute pose solver (section Absolute Pose Estimation).

For generalized rays (origins v_i, unit directions f_i, rig frame) and world points M_i, find
(R, t) with x_rig = R M + t minimising eq. objfun, sum_i ||[f_i]x (R M_i + t - v_i)||^2:

1. O(n) statistics H, g, c with t eliminated (eq. t, objfun3; `statistics.py`);
2. the six optimality conditions E12 ... F23 of eq. EF6 in Cayley parameters q, degree 4 after
   multiplying by (1 + q.q)^2 (`equations.py`, generated with sympy);
3. the elimination template (`_template.json`, built over a prime field by `template.py`):
   one Gaussian elimination (sparse: rows with a zero in the pivot column are skipped) gives the
   40 x 40 action matrix of the action variable on the standard-monomial basis, whose
   eigenvectors hold the 40 (complex) solutions; its eigenvalues come from a Francis QR
   iteration written out for this size (LAPACK's per-call overheads dominated at n = 40);
4. real (and nearly real) roots are mapped to rotations and polished by Newton's method on the
   cost over SO(3) (which also tells true stationary points from complex pairs taken as real),
   their translations follow from eq. t, and the least cost with most points in front wins.

Cayley's blind spot: q = tan(angle / 2) axis is infinite at 180 degrees, and a down-looking rig
over a z-up world is a 180-degree rotation at every yaw. The problem is therefore solved in a
pre-rotated world M' = P M (R = R' P), with P near the sought rotation so that R' stays near
q = 0: P is the most promising of the octahedral group and of a sphere relaxation of eq. objfun3
(`solving_frame`). Unless the first descent step from P heads to the solution found, P is also
descended to a local minimum, which joins the candidates (where the action matrix is
ill-conditioned, e.g. one narrow-FoV camera over a plane, it can be the only copy of the
minimum). When the solution lies beyond 120 deg in that frame, the problem is solved once more
in the frame of the solution. For (nearly) planar points, the flip of the solution (its plane
normal mirrored about the line of sight) starts one more descent: through a narrow field of view
a plane and its flip look alike, and the cost has minima a few degrees apart that the template's
roots are too inaccurate to tell apart (issue 16: 2% of the 0.5 deg cases missed the minimum).
Front-facing candidates within a thousand rounding levels of the least cost are then compared by
their costs summed over the points, which the quadratic form cannot resolve at 0.5 deg.
Where the dual does not certify the solution, or it puts most points behind their rays, the
global fallback (`fallback.py`, issue 31) refines more starts within its time budget and returns
its pose where that is cheaper and front-facing (`GeneralizedPose.fallback`); no pose with most
points in front at all is a PoseError. A front-facing solution that a tighter dual, with SO(3)'s
redundant constraints, proves (`certificate.py`) needs no search.
Changing frame costs nothing in n: H' = K^T H K and g' = K^T g with r = K r',
K = blockdiag(P^T, P^T, P^T).

The steps run compiled, in `_kernels.pyx` (Cython; LAPACK through scipy.linalg.cython_lapack),
which also holds the tunables (`solving_frame`, `polish`, `descend` and the others named here are
its functions): as numpy calls, the ~100 operations on small matrices cost several times their
arithmetic. One call (`Kernel.solve_rays`) takes the rays and returns the candidates as arrays;
`Candidates` makes `Candidate` tuples only when read. Where the time goes (callgrind, 10 points,
2.0 M instructions per solve with the bench's ray building, ~0.28-0.40 ms on the 2-core machine):
Francis QR 0.47 M, Hessenberg reduction 0.15 M, balancing 0.09 M, template fill and elimination
0.42 M, eigenvectors 0.20 M, small LAPACK calls (dsyev, dgesvd) 0.14 M, polishing and descents
0.10 M, Python around the call < 0.1 M; at 500 points the O(n) statistics and front-of-camera
scoring add ~0.55 M. The sums that bound a step by latency (Hessenberg's left update, the eigenvectors' back
substitution) run four at a time, each in its old order, so that speed changes no rounding.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..blas import limit_blas_threads
from . import PoseError
from ._equations import ENTRIES
from ._kernels import Kernel
from .equations import N_MONOMIALS
from .refine import refine_pose
from . import fallback as global_fallback
from .certificate import tight_certified
from .statistics import COLLINEAR_TOLERANCE, ZERO_DIRECTION, statistics_of, validate_correspondences
from .template import Template, template_entries

TEMPLATE_PATH = Path(__file__).with_name("_template.json")


class Candidate(NamedTuple):
    """A real stationary point of eq. objfun: rotation (3, 3), translation (3,), cost, and the
    fraction of points it puts in front of their rays (counted over every point for the solution
    and the cheaper candidates; beyond 127 points, over a fixed subsample of 64 to 127 for the others)."""

    R: np.ndarray
    t: np.ndarray
    cost: float
    in_front: float


class Candidates(Sequence):
    """The candidates of a solve, least cost first: a read-only sequence of `Candidate` built on
    access from the compiled core's arrays R (k, 3, 3), t (k, 3), cost (k,), in_front (k,) (most
    callers read only the solution, and 20-odd namedtuples cost ~5% of a solve)."""

    __slots__ = ("R", "t", "cost", "in_front")

    def __init__(self, R: np.ndarray, t: np.ndarray, cost: np.ndarray, in_front: np.ndarray):
        self.R, self.t, self.cost, self.in_front = R, t, cost, in_front

    def __len__(self) -> int:
        return len(self.cost)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        return Candidate(self.R[index], self.t[index], float(self.cost[index]), float(self.in_front[index]))

    def __repr__(self) -> str:
        return repr(list(self))


@dataclass(frozen=True)
class GeneralizedPose:
    """Solution of the generalized absolute pose problem: x_rig = R @ M + t.

    R (3, 3), t (3,), cost: value of eq. objfun at (R, t); candidates: every real stationary
    point found, least cost first (`Candidates`; the solution is the cheapest with most points in
    front of their rays, usually candidates[0]); n_points: correspondences.
    covariance: (6, 6) of (rotation increment, t) when refined, else None. certified: the
    Lagrangian dual certifies the solver's solution as the global minimum of eq. objfun (beyond
    the paper; `_kernels.certified`); False says only that the check could not prove it (for
    instance when a cheaper pose puts the points behind the cameras). With refine, it refers to
    the solution before refinement. fallback: the pose comes from the global fallback
    (`fallback.search`), which found a cheaper pose with most points in front than the template's
    roots (it is then among the candidates too; certified refers to it); fallback_ms: the wall
    time of that search, None where it did not run (a certified, front-facing solution).
    """

    R: np.ndarray
    t: np.ndarray
    cost: float
    candidates: Candidates
    n_points: int
    covariance: np.ndarray | None = None
    certified: bool = False
    fallback: bool = False
    fallback_ms: float | None = None


# ------------------------------------------------------------------------------ runtime template


@dataclass(frozen=True)
class _Runtime:
    """Index arrays that turn (6, n_monomials) coefficients into the template and action matrix."""

    m: int
    n_columns: int
    n_reducible: int
    target: np.ndarray  # flat indices into the row-major (m, n_columns) template
    source: np.ndarray  # flat indices into the (6, n_monomials) coefficients
    shift_rows: np.ndarray  # basis rows whose x * b is a basis monomial ...
    shift_columns: np.ndarray  # ... namely this one: a 1 in the action matrix
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
    shift_rows, shift_columns, reduced_rows, reduced_index = [], [], [], []
    for i, b in enumerate(template.basis):
        product = (b[0] + unit[0], b[1] + unit[1], b[2] + unit[2])
        if product in basis:
            shift_rows.append(i)
            shift_columns.append(basis[product])
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
        shift_columns=np.array(shift_columns),
        reduced_rows=np.array(reduced_rows),
        reduced_index=np.array(reduced_index),
        unit_index=np.array([basis[u] for u in units]),
    )


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


@lru_cache(maxsize=1)
def kernel() -> Kernel:
    """The compiled solver with the template of `_template.json` (built once)."""
    rt = runtime()
    return Kernel(rt.m, rt.n_columns, rt.n_reducible, rt.target, rt.source, rt.shift_rows, rt.shift_columns,
                  rt.reduced_rows, rt.reduced_index, rt.unit_index, np.array(ENTRIES), N_MONOMIALS, OCTAHEDRAL)


def solve_generalized_pose(origins, directions, points, refine: bool = False, sigma: float | None = None,
                           attitude_prior=None, fallback: bool = True) -> GeneralizedPose:
    """Globally optimal generalized absolute pose (see the module docstring).

    origins: (n, 3) ray origins v_i in the rig frame; directions: (n, 3) ray directions f_i in
    the rig frame (any length > 0); points: (n, 3) world points M_i; n >= 3, not collinear.
    refine: polish the solution on the angular reprojection error (`refine.refine_pose`) and
    return its (6, 6) covariance of (rotation increment, t); sigma: the angular noise (radians)
    for that covariance, else estimated from the residuals. Returns x_rig = R @ M + t.

    Where the certificate fails (and the tighter one of `certificate.py` too) or the solution puts most
    points behind their rays, the global fallback (`fallback.search`, within its time budget) looks for a
    cheaper front-facing pose, from attitude_prior (3, 3) too (rig_from_world, e.g. the INS attitude)
    when given. Raises PoseError when no pose found puts at least half of the points in front. fallback=False: the
    template's roots alone, as before issue 31, whatever their solution (for comparisons).
    """
    prior = None if attitude_prior is None else _checked_prior(attitude_prior)
    found = None
    if _is_float_rows(origins) and _is_float_rows(directions) and _is_float_rows(points):
        found = kernel().solve_rays(origins, directions, points, COLLINEAR_TOLERANCE, ZERO_DIRECTION)
    if found is None:  # other input types, or input that fails a check: the Python checks name the fault
        origins, directions, points = validate_correspondences(origins, directions, points)
        statistics_of(origins, directions, points)
        found = kernel().solve_rays(origins, directions, points, COLLINEAR_TOLERANCE, ZERO_DIRECTION)
    R, t, cost, front, best, certified = found
    pose = GeneralizedPose(R=R[best], t=t[best], cost=float(cost[best]), candidates=Candidates(R, t, cost, front),
                           n_points=len(points), certified=certified)
    if fallback and not (certified and front[best] >= 0.5):
        pose = _with_fallback(pose, best, origins, directions, points, prior)
    if not refine:
        return pose
    # refine_pose checks its own input, and its objective is eq. objfun about the centroid (more
    # accurate than in map coordinates): at 10 points a second check here cost more than the iteration.
    refined = refine_pose(origins, directions, points, pose.R, pose.t, sigma=sigma)
    return replace(pose, R=refined.R, t=refined.t, cost=refined.objective, covariance=refined.covariance)


def _with_fallback(pose: GeneralizedPose, best: int, origins, directions, points, prior) -> GeneralizedPose:
    """pose, or the cheaper front-facing pose of the global fallback (`fallback.search`), which then
    joins the candidates; best: the index of pose among them. A front-facing pose of rays from more
    than one origin that the dual with SO(3)'s redundant constraints proves (`certificate.tight_certified`)
    is returned as it is, without a search (fallback_ms None; `certified` stays the solver's own dual's).
    Raises PoseError when neither puts at least half of the points in front."""
    begin = time.perf_counter()
    v, f, M = validate_correspondences(origins, directions, points)
    stats = statistics_of(v, f, M)
    front = pose.candidates.in_front[best] >= 0.5
    # one camera alone (rays from one origin) is rarely proven (4 of C0's 136 uncertified hover frames)
    # and a failed proof costs half a search: the search runs at once there
    if front and not np.all(v == v[0]) and tight_certified(stats.H, stats.g, stats.c, pose.R):
        return pose  # the global minimum: the search would find no cheaper pose (certificate.py)
    solver = kernel()
    found = global_fallback.search(v, f, M, stats, pose.candidates.R, pose.candidates.in_front,
                                   certify=lambda R: solver.certify(stats.H, stats.g, stats.c, R), prior=prior)
    if found is not None and front:
        template_cost = global_fallback.centred_costs(v, f, M, stats, pose.R[None])[0][0]
    better = found is not None and (not front or found.cost < template_cost * (1 - global_fallback.IMPROVEMENT))
    ms = (time.perf_counter() - begin) * 1e3
    if not better and not front:
        raise PoseError(f"pose: no pose found puts most of the {len(M)} points in front of their rays (the least-cost "
                        f"one puts {1 - pose.candidates.in_front[best]:.0%} behind them)")
    if not better:
        return replace(pose, fallback_ms=ms)
    c = pose.candidates
    costs = np.append(c.cost, found.cost)
    order = np.argsort(costs, kind="stable")
    candidates = Candidates(np.concatenate([c.R, found.R[None]])[order], np.concatenate([c.t, found.t[None]])[order],
                            costs[order], np.append(c.in_front, found.front)[order])
    return replace(pose, R=found.R, t=found.t, cost=found.cost, candidates=candidates, certified=found.certified,
                   fallback=True, fallback_ms=ms)


def _checked_prior(prior) -> np.ndarray:
    """The attitude prior as the nearest rotation (3, 3); PoseError if it is not one."""
    R = np.asarray(prior, dtype=float)
    if R.shape != (3, 3) or not np.isfinite(R).all() or not np.allclose(R @ R.T, np.eye(3), atol=1e-3) \
            or np.linalg.det(R) < 0:
        raise PoseError(f"pose: attitude_prior must be a rotation matrix (3, 3), got {np.array2string(R)}")
    U, _, Vt = np.linalg.svd(R)
    return U @ Vt


def _is_float_rows(x) -> bool:
    """Whether x can go to the compiled core as it is: a C-contiguous float64 (n, 3) array."""
    return type(x) is np.ndarray and x.dtype == np.float64 and x.ndim == 2 and x.flags.c_contiguous


def solve_batch(problems, refine: bool = False, workers: int = 1) -> list[GeneralizedPose | PoseError]:
    """Solve many frames in one call: problems is an iterable of (origins, directions, points).

    Returns one GeneralizedPose per frame, in order, or the PoseError that frame raised (so one bad
    frame does not lose the others). workers > 1 solves that many frames at a time in threads:
    the compiled core runs without the GIL, each thread with single-threaded BLAS.
    """

    def solve(problem) -> GeneralizedPose | PoseError:
        try:
            return solve_generalized_pose(*problem, refine=refine)
        except PoseError as error:
            return error

    if workers <= 1:
        return [solve(problem) for problem in problems]
    with ThreadPoolExecutor(max_workers=workers, initializer=limit_blas_threads) as pool:
        return list(pool.map(solve, problems))
