"""Robust generalized absolute pose: RANSAC over minimal gP3P samples, then a final solver.

Each iteration draws 3 distinct correspondences, solves them with `gp3p` (up to 8 poses), and
scores every pose on all correspondences with the angular error of `refine.ray_errors` (the norm
of the tangent-plane residual of `refine_pose`; points behind their ray's origin, alpha <= 0,
never count as inliers). Scoring is MSAC: sum_i min(e_i^2, threshold^2), inliers e_i < threshold.
The iteration count adapts to the best inlier ratio w found so far,

    N = log(1 - confidence) / log(1 - w^3),

capped at `max_iterations`. Optionally each new best hypothesis is locally optimised
(LO-RANSAC: `refine_pose` on its inliers, re-scored, repeated while the score improves). The best
inlier set goes to `final_solver` (normally the globally optimal solver of `pose.solver`), whose
pose then re-selects the inliers; this is repeated until the inlier set is stable (a few rounds).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from . import PoseError
from .gp3p import gp3p_unchecked
from .refine import ray_errors, refine_pose
from .statistics import validate_correspondences

#: Rounds of final solve -> re-selected inliers before giving up on a stable inlier set.
FINAL_ROUNDS = 3
#: Iterations of `refine_pose` inside local optimisation.
LO_ITERATIONS = 10
#: Rounds of local optimisation per new best hypothesis.
LO_ROUNDS = 3


@dataclass(frozen=True)
class RobustPose:
    """Result of `ransac_generalized_pose`.

    R (3, 3), t (3,): the final pose (x_rig = R @ M + t), from `final_solver`. inliers: (n,) bool,
    the correspondences within the threshold of that pose. errors: (n,) angular errors in radians
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
    error (radians). final_solver(origins (k, 3), directions (k, 3), points (k, 3)) -> object
    with attributes R (3, 3) and t (3,), called on the inliers. confidence: RANSAC success
    probability for the adaptive stop; max_iterations: cap on minimal samples; seed: of the
    sampler. Raises PoseError for invalid input, fewer than `min_inliers` correspondences, or
    when no pose has at least `min_inliers` inliers (e.g. all data are outliers).
    """
    v, f, M = validate_correspondences(origins, directions, points)
    _check_options(threshold_rad, confidence, max_iterations, min_inliers)
    n = len(M)
    if n < min_inliers:
        raise PoseError(f"ransac: {n} correspondences, but at least min_inliers={min_inliers} are needed")
    best, n_iterations = _ransac(v, f, M, threshold_rad, confidence, max_iterations,
                                 np.random.default_rng(seed), local_optimization)
    n_best = 0 if best is None else int(best.inliers.sum())
    if n_best < min_inliers:
        raise PoseError(
            f"ransac: no pose explains at least {min_inliers} of the {n} correspondences within "
            f"{threshold_rad:.3g} rad after {n_iterations} samples (best: {n_best} inliers); "
            "the data look like outliers only, or the threshold is too tight"
        )
    return _final(v, f, M, best, threshold_rad, final_solver, n_iterations)


def _check_options(threshold_rad, confidence, max_iterations, min_inliers) -> None:
    if not (np.isfinite(threshold_rad) and threshold_rad > 0):
        raise PoseError(f"ransac: threshold_rad must be a positive number, got {threshold_rad}")
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
    required = max_iterations
    iteration = 0
    while iteration < min(required, max_iterations):
        iteration += 1
        sample = _sample(rng, n)
        for R, t in gp3p_unchecked(v[sample], f[sample], M[sample]):
            hypothesis = _score(v, f, M, R, t, threshold)
            if best is not None and hypothesis.cost >= best.cost:
                continue
            if local_optimization:
                hypothesis = _local_optimization(v, f, M, hypothesis, threshold)
            best = hypothesis
            required = required_iterations(int(best.inliers.sum()) / n, confidence)
    return best, iteration


def _sample(rng: np.random.Generator, n: int) -> np.ndarray:
    """(3,) distinct indices in [0, n)."""
    while True:
        sample = rng.integers(0, n, size=3)
        if sample[0] != sample[1] and sample[0] != sample[2] and sample[1] != sample[2]:
            return sample


def _score(v, f, M, R, t, threshold) -> _Hypothesis:
    errors = ray_errors(v, f, M, R, t)
    capped = np.minimum(errors, threshold)  # MSAC; inf (behind the ray) is capped too
    return _Hypothesis(R=R, t=t, errors=errors, inliers=errors < threshold, cost=float(capped @ capped))


def required_iterations(inlier_ratio: float, confidence: float, sample_size: int = 3) -> int:
    """Samples needed to draw one all-inlier sample with probability `confidence` (>= 1)."""
    good = inlier_ratio**sample_size
    if good >= 1.0:
        return 1
    if good <= 0.0:
        return math.inf
    return max(1, math.ceil(math.log(1.0 - confidence) / math.log(1.0 - good)))


def _local_optimization(v, f, M, hypothesis: _Hypothesis, threshold) -> _Hypothesis:
    """Refine on the inliers while the MSAC cost improves (LO-RANSAC)."""
    for _ in range(LO_ROUNDS):
        inliers = hypothesis.inliers
        if inliers.sum() < 4:
            break
        refined = refine_pose(v[inliers], f[inliers], M[inliers], hypothesis.R, hypothesis.t,
                              sigma=1.0, max_iterations=LO_ITERATIONS)
        candidate = _score(v, f, M, refined.R, refined.t, threshold)
        if not candidate.cost < hypothesis.cost:
            break
        hypothesis = candidate
    return hypothesis


def _final(v, f, M, best: _Hypothesis, threshold, final_solver, n_iterations) -> RobustPose:
    """Run the final solver on the inliers until the re-selected inlier set is stable."""
    inliers = best.inliers
    for _ in range(FINAL_ROUNDS):
        result = final_solver(v[inliers], f[inliers], M[inliers])
        R, t = _pose_of(result)
        errors = ray_errors(v, f, M, R, t)
        selected = errors < threshold
        if np.array_equal(selected, inliers) or selected.sum() < 3:
            break
        inliers = selected
    return RobustPose(R=R, t=t, inliers=selected, errors=errors, n_iterations=n_iterations,
                      n_inliers=int(selected.sum()), final=result)


def _pose_of(result) -> tuple[np.ndarray, np.ndarray]:
    try:
        R = np.asarray(result.R, dtype=float)
        t = np.asarray(result.t, dtype=float)
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
