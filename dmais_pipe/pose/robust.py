"""Robust generalized absolute pose: RANSAC over minimal gP3P samples, then a final solver.

Each iteration draws 3 distinct correspondences, solves them with `gp3p` (up to 8 poses), and
scores every pose on all correspondences with the angular error of `refine.ray_errors` (the norm
of the tangent-plane residual of `refine_pose`; points behind their ray's origin, alpha <= 0,
never count as inliers). Each correspondence has its own threshold theta_i (radians), so that
cameras of different resolution get the same threshold in pixels (`theta_i = px / f_i`). Scoring
is MSAC on the normalized errors: sum_i min(e_i / theta_i, 1)^2, inliers e_i < theta_i. The
iteration count adapts to the best inlier ratio w found so far,

    N = log(1 - confidence) / log(1 - w^3),

capped at `max_iterations`; with at most EXHAUSTIVE_TRIPLES triples (n <= 12) every triple is drawn
once, in random order, unless a pose explains all correspondences first. Each new best hypothesis
(and each with more correspondences within LO_MULTIPLIER x theta than the best has inliers, which
its refit may turn into a new best) is locally optimised as in LO-RANSAC's
iterative least squares (Chum, Matas, Kittler 2003; Lebeda, Matas, Chum 2012, "Fixing the locally
optimized RANSAC"): `refine_pose` on the correspondences within LO_MULTIPLIER x theta, then within
a threshold shrinking to theta over LO_STEPS refits, every refit re-selecting from all
correspondences and re-scored; the best-scoring pose is kept. A minimal-sample pose is often tens
of pixels off at the far cameras, so correct points there fall just outside theta until a refit
brings them in. The best inlier set then goes to `final_solver` (normally the globally optimal
solver of `pose.solver`), whose pose re-selects the inliers from all correspondences and is
re-solved until the set is stable: the returned pose is always the solve of the returned inliers.

The minimal solves with their scores, the scoring and the local refits run compiled (`_refine`:
`gp3p.py`'s and `refine.py`'s arithmetic); only the sampling and the bookkeeping are Python.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from ..errors import PoseError
from . import _refine
from .refine import COST_TOLERANCE, STEP_TOLERANCE
from .statistics import ZERO_DIRECTION, validate_correspondences

#: Rounds of final solve -> re-selected inliers before giving up on a stable inlier set.
FINAL_ROUNDS = 10
#: Iterations of `refine_pose` per local-optimisation refit.
LO_ITERATIONS = 10
#: Local optimisation starts from the correspondences within LO_MULTIPLIER x threshold (Lebeda et
#: al. use 3) and shrinks the threshold to 1 x over LO_STEPS refits.
LO_MULTIPLIER = 3.0
LO_STEPS = 4
#: With at most this many triples (n <= 12), RANSAC draws each once instead of adapting its count.
EXHAUSTIVE_TRIPLES = 220


@dataclass(frozen=True)
class RobustPose:
    """Result of `ransac_generalized_pose`.

    R (3, 3), t (3,): the final pose (x_rig = R @ M + t), from `final_solver` on `inliers`: (n,)
    bool, the correspondences within their threshold of that pose (or within LO_MULTIPLIER x
    their threshold, where solving those scored better). errors: (n,) angular errors in radians
    (inf for points behind their ray). n_iterations: RANSAC iterations drawn. n_inliers: inliers
    of the final pose. final: the object `final_solver` returned last.
    """

    R: np.ndarray
    t: np.ndarray
    inliers: np.ndarray
    errors: np.ndarray
    n_iterations: int
    n_inliers: int
    final: Any


@dataclass
class _Hypothesis:
    R: np.ndarray
    t: np.ndarray
    errors: np.ndarray
    inliers: np.ndarray
    cost: float


def ransac_generalized_pose(
    origins, directions, points, threshold_rad: float, *,
    final_solver: Callable[[np.ndarray, np.ndarray, np.ndarray], Any],
    confidence: float = 0.999, max_iterations: int = 10000, seed: int = 0,
    min_inliers: int = 6, local_optimization: bool = True,
) -> RobustPose:
    """Robust pose of a generalized camera from correspondences with outliers.

    origins: (n, 3) ray origins v_i and directions: (n, 3) ray directions f_i, both in the rig
    frame; points: (n, 3) world points M_i. threshold_rad: inlier threshold on the angular
    error (radians), one for all or (n,) one per correspondence. final_solver(origins (k, 3),
    directions (k, 3), points (k, 3)) -> object with attributes R (3, 3) and t (3,), called on
    the inliers. confidence: RANSAC success probability for the adaptive stop; max_iterations: cap
    on minimal samples; seed: of the sampler. Raises PoseError for invalid input, fewer than `min_inliers` correspondences, or
    when no pose has at least `min_inliers` inliers (e.g. all data are outliers).
    """
    v, f, M = map(np.ascontiguousarray, validate_correspondences(origins, directions, points))
    _check_options(threshold_rad, confidence, max_iterations, min_inliers)
    n = len(M)
    threshold_rad = np.ascontiguousarray(_thresholds(threshold_rad, n), dtype=float)
    if n < min_inliers:
        raise PoseError(f"ransac: {n} correspondences, but at least min_inliers={min_inliers} are needed")
    best, n_iterations = _ransac(v, f, M, threshold_rad, confidence, max_iterations,
                                 np.random.default_rng(seed), local_optimization)
    n_best = 0 if best is None else int(best.inliers.sum())
    result = None
    if n_best >= min_inliers:
        result = _final(v, f, M, best, threshold_rad, final_solver, n_iterations)
    elif n_best >= 4:  # the final solve on all of them may re-select enough (a camera's lone point)
        try:
            result = _final(v, f, M, best, threshold_rad, final_solver, n_iterations)
        except PoseError:
            result = None
        if result is not None and result.n_inliers < min_inliers:
            result = None
    if result is None:
        raise PoseError(
            f"ransac: no pose explains at least {min_inliers} of the {n} correspondences within "
            f"{np.median(threshold_rad):.3g} rad after {n_iterations} samples (best: {n_best} inliers); "
            "the data look like outliers only, or the threshold is too tight"
        )
    return result


def _thresholds(threshold_rad, n: int) -> np.ndarray:
    """(n,) per-correspondence thresholds from a scalar or an (n,) array."""
    threshold = np.asarray(threshold_rad, dtype=float)
    if threshold.ndim == 0:
        return np.full(n, float(threshold))
    if threshold.shape != (n,):
        raise PoseError(f"ransac: threshold_rad must be a number or have shape ({n},), got {threshold.shape}")
    return threshold


def _check_options(threshold_rad, confidence, max_iterations, min_inliers) -> None:
    threshold = np.asarray(threshold_rad, dtype=float)
    if not (np.all(np.isfinite(threshold)) and np.all(threshold > 0)):
        raise PoseError(f"ransac: threshold_rad must be positive numbers, got {threshold_rad}")
    if not 0 < confidence < 1:
        raise PoseError(f"ransac: confidence must lie in (0, 1), got {confidence}")
    if int(max_iterations) < 1:
        raise PoseError(f"ransac: max_iterations must be at least 1, got {max_iterations}")
    if int(min_inliers) < 3:
        raise PoseError(f"ransac: min_inliers must be at least 3, got {min_inliers}")


def _ransac(v, f, M, threshold, confidence, max_iterations, rng, local_optimization):
    """Best hypothesis (or None) and the number of samples drawn."""
    n = len(M)
    best: _Hypothesis | None = None
    n_best = 0
    required = max_iterations
    iteration = 0
    # Few correspondences: every triple, in random order, until one pose explains all of them. With
    # 6 correct of 10, the adaptive count (52 samples) often misses the triples whose pose comes
    # near a camera's lone point; the bench's frames lost 1 in 9 that way (issue 16 item 4).
    triples = None
    if math.comb(n, 3) <= EXHAUSTIVE_TRIPLES:
        triples = rng.permutation(np.array(list(itertools.combinations(range(n), 3))))
    while iteration < min(len(triples) if triples is not None and n_best < n else required, max_iterations):
        iteration += 1
        i, j, k = _sample(rng, n) if triples is None else triples[iteration - 1]
        # the gP3P poses, their MSAC costs and counts within LO_MULTIPLIER x theta in one compiled call
        for R, t, cost, wide in zip(*_refine.sample_hypotheses(v, f, M, threshold, LO_MULTIPLIER, i, j, k)):
            if best is None or cost < best.cost:
                hypothesis = _score(v, f, M, R, t, threshold)
                if local_optimization:
                    hypothesis = _local_optimization(v, f, M, hypothesis, threshold)
            elif local_optimization and wide > n_best:
                # More correspondences near this pose than the best has inliers: a minimal-sample pose
                # is tens of pixels off at the far cameras (one of a camera's few points is enough), so
                # it may still beat the best once refined.
                hypothesis = _local_optimization(v, f, M, _score(v, f, M, R, t, threshold), threshold)
                if not hypothesis.cost < best.cost:
                    continue
            else:
                continue
            best = hypothesis
            n_best = int(best.inliers.sum())
            required = required_iterations(n_best / n, confidence)
    return best, iteration


def _sample(rng: np.random.Generator, n: int) -> np.ndarray:
    """(3,) distinct indices in [0, n)."""
    while True:
        sample = rng.integers(0, n, size=3)
        if sample[0] != sample[1] and sample[0] != sample[2] and sample[1] != sample[2]:
            return sample


def _score(v, f, M, R, t, threshold) -> _Hypothesis:
    """MSAC score of a pose against per-correspondence thresholds (n,): the errors of
    `refine.ray_errors` and sum_i min(e_i / theta_i, 1)^2 (inf, behind the ray, is capped too),
    compiled (`_refine.score`)."""
    errors, cost = _refine.score(v, f, M, R, t, threshold)
    return _Hypothesis(R=R, t=t, errors=errors, inliers=errors < threshold, cost=cost)


def required_iterations(inlier_ratio: float, confidence: float, sample_size: int = 3) -> int:
    """Samples needed to draw one all-inlier sample with probability `confidence` (>= 1)."""
    good = inlier_ratio**sample_size
    if good >= 1.0:
        return 1
    if good <= 0.0:
        return math.inf
    return max(1, math.ceil(math.log(1.0 - confidence) / math.log(1.0 - good)))


def _local_optimization(v, f, M, hypothesis: _Hypothesis, threshold) -> _Hypothesis:
    """Iterative least squares with a shrinking threshold (module docstring); the best-scoring pose."""
    best, current = hypothesis, hypothesis
    for scale in np.linspace(LO_MULTIPLIER, 1.0, LO_STEPS):
        selected = current.errors < scale * threshold
        if selected.sum() < 4:
            break
        # refine_pose's iteration without its checks and covariance (the inputs are checked already)
        refined = _refine.refine(v[selected], f[selected], M[selected], current.R, current.t, LO_ITERATIONS,
                                 STEP_TOLERANCE, COST_TOLERANCE, 1.0, ZERO_DIRECTION, False)
        if refined is None:
            break
        R, t = refined[:2]
        current = _score(v, f, M, R, t, threshold)
        if current.cost < best.cost:
            best = current
    return best


def _final(v, f, M, best: _Hypothesis, threshold, final_solver, n_iterations) -> RobustPose:
    """Solve the inliers with the final solver and re-select them from all correspondences until
    the set is stable (or FINAL_ROUNDS); the returned inliers are the set the returned pose solves.

    A stable set is then offered the correspondences within LO_MULTIPLIER x threshold: their
    solve replaces it when it scores better (the final solver's counterpart of the local
    optimisation, for a correct point that the inlier-only solve leaves just outside)."""
    solved, kept = best.inliers, None
    for _ in range(FINAL_ROUNDS):
        try:
            result = final_solver(v[solved], f[solved], M[solved])
        except PoseError:
            if kept is None:
                raise
            break  # a re-selected or widened set with no pose (e.g. most points behind) ends the search
        R, t = _pose_of(result)
        current = _score(v, f, M, R, t, threshold)
        if kept is not None and not current.cost < kept[1].cost:
            break  # a re-selected or widened set that scores no better ends the search
        kept = (solved, current, result)
        selected = current.inliers
        if np.array_equal(selected, solved):
            selected = current.errors < LO_MULTIPLIER * threshold
            if np.array_equal(selected, solved):
                break
        if selected.sum() < 3:
            break
        solved = selected
    solved, current, result = kept
    return RobustPose(R=current.R, t=current.t, inliers=solved, errors=current.errors,
                      n_iterations=n_iterations, n_inliers=int(solved.sum()), final=result)


def _pose_of(result) -> tuple[np.ndarray, np.ndarray]:
    try:
        R = np.ascontiguousarray(result.R, dtype=float)
        t = np.ascontiguousarray(result.t, dtype=float)
    except AttributeError:
        raise PoseError(f"ransac: final_solver returned {type(result).__name__}, without R and t") from None
    if R.shape != (3, 3) or t.shape != (3,) or not (np.isfinite(R).all() and np.isfinite(t).all()):
        raise PoseError(f"ransac: final_solver returned an invalid pose (R {R.shape}, t {t.shape})")
    return R, t


def solve_robust(origins, directions, points, threshold_rad: float, *, refine: bool = False, seed: int = 0) -> RobustPose:
    """RANSAC over gP3P samples, then the paper's globally optimal solver on the inliers.

    `final` of the result is the solver's GeneralizedPose (with covariance when refine=True).
    """
    from .solver import solve_generalized_pose

    return ransac_generalized_pose(
        origins, directions, points, threshold_rad, seed=seed,
        final_solver=lambda v, f, M: solve_generalized_pose(v, f, M, refine=refine),
    )
