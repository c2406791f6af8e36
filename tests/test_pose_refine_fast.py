"""refine_pose's compiled per-call path (issue 31 item 2: `_refine.refine` reads the arrays in place
and returns the covariance and eq. objfun with the pose) against slow, obviously correct numpy:
the documented Levenberg-Marquardt iteration written plainly, the covariance from numeric
Jacobians, numpy's eq. objfun; and the same answer whatever the arrays' memory layout or thread."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dmais_pipe.bench import pose as bench
from dmais_pipe.geometry import skew
from dmais_pipe.pose import _refine
from dmais_pipe.pose.refine import (COST_TOLERANCE, MAX_ITERATIONS, STEP_TOLERANCE, _jacobian, angular_residuals,
                                    inverse_normal_matrices, refine_pose, tangent_bases)
from dmais_pipe.pose.solver import solve_generalized_pose
from dmais_pipe.pose.statistics import ZERO_DIRECTION
from pose_scenes import dmais_scene, generalized_scene


def numpy_levenberg_marquardt(v, f, M, R0, t0, sigma=None, max_iterations=MAX_ITERATIONS):
    """refine_pose's iteration as its docstrings state it, in numpy: (R, t, covariance, cost,
    n_iterations, converged). About the centroid m; the Gauss-Newton model's predicted decrease
    ends it first; damped trials R <- exp(omega) R, t <- t + delta_t, damping x10 on a rejected
    trial, /10 on an accepted one; a step below STEP_TOLERANCE or a relative decrease below
    COST_TOLERANCE ends it too."""
    f = f / np.linalg.norm(f, axis=1)[:, None]
    bases = tangent_bases(f)
    U, _, Vt = np.linalg.svd(R0)
    R = U @ Vt
    m = M.mean(axis=0)
    Mc = M - m
    t = t0 + R @ m
    size = 1.0 + np.abs(Mc - Mc.mean(axis=0)).max() + np.abs(t).max()

    def linearized(R, t):
        r, J = _jacobian(v, bases, Mc, R, t)
        return r @ r, J.T @ J, J.T @ r

    def cost_at(R, t):
        return float(np.sum(angular_residuals(v, bases, Mc, R, t) ** 2))

    cost, JtJ, g = linearized(R, t)
    damping, converged, iteration = 1e-6, False, max_iterations
    for iteration in range(1, max_iterations + 1):
        try:
            if 0.5 * g @ np.linalg.solve(JtJ, g) <= COST_TOLERANCE * cost:
                converged = True
                break
        except np.linalg.LinAlgError:
            pass
        while True:
            A = JtJ + damping * np.diag(np.maximum(np.diag(JtJ), 1e-300))
            step = -np.linalg.solve(A, g)
            R_new, t_new = Rotation.from_rotvec(step[:3]).as_matrix() @ R, t + step[3:]
            cost_new = cost_at(R_new, t_new)
            if cost_new <= cost or damping > 1e12:
                break
            damping *= 10.0
        if not cost_new <= cost:
            converged = True
            break
        decrease = cost - cost_new
        R, t = R_new, t_new
        cost, JtJ, g = linearized(R, t)
        damping = max(damping / 10.0, 1e-12)
        if max(np.abs(step[:3]).max(), np.abs(step[3:]).max() / size) < STEP_TOLERANCE or decrease <= COST_TOLERANCE * cost:
            converged = True
            break
    n = len(M)
    variance = sigma**2 if sigma is not None else (cost / (2 * n - 6) if n > 3 else np.nan)
    T = np.eye(6)
    T[3:, :3] = skew(R @ m)
    covariance = variance * T @ inverse_normal_matrices(JtJ) @ T.T
    return R, t - R @ m, covariance, cost, iteration, converged


def numeric_jacobian(v, f, M, R, t, h=1e-6):
    """(2n, 6) central differences of the angular residuals at (R, t) in (omega, t), R <- exp(omega) R."""
    bases = tangent_bases(f / np.linalg.norm(f, axis=1)[:, None])
    columns = []
    for j in range(6):
        e = np.zeros(6)
        e[j] = h
        plus = angular_residuals(v, bases, M, Rotation.from_rotvec(e[:3]).as_matrix() @ R, t + e[3:])
        minus = angular_residuals(v, bases, M, Rotation.from_rotvec(-e[:3]).as_matrix() @ R, t - e[3:])
        columns.append((plus - minus).reshape(-1) / (2 * h))
    return np.column_stack(columns)


def _bench_problems(rng, counts=(10, 20, 50, 100, 500), per_count=4):
    """The bench's frames (the paper's rig, UTM coordinates, 4 px noise) from the solver's solution."""
    for n in counts:
        for _ in range(per_count):
            cams, uv, points, _ = bench.dmais_frame(rng, n)
            origins, directions = bench._rays(cams, uv)
            pose = solve_generalized_pose(origins, directions, points)
            yield origins, directions, points, pose.R, pose.t


def _offset_problems(rng, count=12):
    """OpenGV-like scenes 100 m from the world origin, unnormalized directions, a start 3 deg and
    0.3 m off (about the points' centroid)."""
    for _ in range(count):
        n = int(rng.integers(4, 80))
        v, f, M, R, t = generalized_scene(rng, n, noise=1e-3, offset=(100.0, -50.0, 20.0))
        f = f * rng.uniform(0.5, 3.0, size=(n, 1))
        R0 = Rotation.from_rotvec(np.radians(3.0) * rng.normal(size=3)).as_matrix() @ R
        m = M.mean(axis=0)
        yield v, f, M, R0, t + R @ m - R0 @ m + 0.3 * rng.normal(size=3)


@pytest.mark.parametrize("sigma", [None, 1e-4])
def test_refine_equals_the_numpy_iteration(sigma):
    rng = np.random.default_rng(3120)
    problems = list(_bench_problems(rng)) + list(_offset_problems(rng))
    for v, f, M, R0, t0 in problems:
        fast = refine_pose(v, f, M, R0, t0, sigma=sigma)
        R, t, covariance, cost, n_iterations, converged = numpy_levenberg_marquardt(v, f, M, R0, t0, sigma)
        scale = max(1.0, np.abs(t).max())
        assert fast.converged and converged
        assert abs(fast.n_iterations - n_iterations) <= 1  # rounding may move a stop by one iteration
        np.testing.assert_allclose(fast.R, R, rtol=0, atol=1e-9)
        np.testing.assert_allclose(fast.t, t, rtol=0, atol=1e-9 * scale)
        assert fast.residual_rms**2 * len(M) == pytest.approx(cost, rel=1e-8, abs=1e-20)
        np.testing.assert_allclose(fast.covariance, covariance, rtol=1e-6, atol=1e-9 * np.abs(covariance).max())


def test_covariance_equals_numeric_jacobians():
    """cov = s^2 (J^T J)^-1 with J by central differences in (omega, t) at the refined pose, in
    the world frame of each scene (no centring in the test: the offset scenes check the compiled
    path's move back from the centroid)."""
    rng = np.random.default_rng(3121)
    for k, (v, f, M, R0, t0) in enumerate(_offset_problems(rng, 8)):
        sigma = 2e-4 if k % 2 else None
        fast = refine_pose(v, f, M, R0, t0, sigma=sigma)
        J = numeric_jacobian(v, f, M, fast.R, fast.t)
        n = len(M)
        variance = sigma**2 if sigma else n * fast.residual_rms**2 / (2 * n - 6)
        expected = variance * np.linalg.inv(J.T @ J)
        np.testing.assert_allclose(fast.covariance, expected, rtol=1e-5, atol=1e-7 * np.abs(expected).max())


def test_covariance_of_map_coordinates_equals_numeric_jacobians_about_the_centroid():
    """The paper's rig in UTM coordinates: there J in (omega, t) is too ill-conditioned to invert in
    the test, so J is taken numerically in (omega, t' = t + R m) and moved by delta_t = delta_t' +
    [R m]x omega."""
    rng = np.random.default_rng(3122)
    for v, f, M, R0, t0 in _bench_problems(rng, counts=(10, 50), per_count=3):
        fast = refine_pose(v, f, M, R0, t0)
        m = M.mean(axis=0)
        J = numeric_jacobian(v, f, M - m, fast.R, fast.t + fast.R @ m)
        n = len(M)
        T = np.eye(6)
        T[3:, :3] = skew(fast.R @ m)
        expected = n * fast.residual_rms**2 / (2 * n - 6) * T @ np.linalg.inv(J.T @ J) @ T.T
        np.testing.assert_allclose(fast.covariance, expected, rtol=1e-5, atol=1e-7 * np.abs(expected).max())


def _nearly_collinear(rng, spread):
    """12 rays to points within `spread` of a line: the rotation about the line is nearly unobservable."""
    s = rng.uniform(-3, 3, 12)
    M = np.column_stack([s, 0.5 * s, 5.0 + 0.0 * s]) + spread * rng.normal(size=(12, 3))
    v = rng.uniform(-1, 1, (12, 3))
    f = M - v + 1e-3 * rng.normal(size=(12, 3))
    return v, f / np.linalg.norm(f, axis=1)[:, None], M, np.eye(3), np.zeros(3)


@pytest.mark.parametrize("spread, observable", [(3e-6, True), (1e-7, False)])
def test_ill_conditioned_covariance_follows_the_condition_number(spread, observable):
    """Past the Cholesky shortcut's bound (its unit-diagonal condition number here is 1e10..1e12,
    or above 1e12), the eigenvalues decide as numpy's `inverse_normal_matrices` does."""
    v, f, M, R0, t0 = _nearly_collinear(np.random.default_rng(0 if observable else 5), spread)
    fast = refine_pose(v, f, M, R0, t0)
    m = M.mean(axis=0)
    _, J = _jacobian(v, tangent_bases(f), M - m, fast.R, fast.t + fast.R @ m)
    normal = J.T @ J
    scale = np.sqrt(np.diag(normal))
    condition = np.linalg.cond(normal / np.outer(scale, scale))
    assert (1e10 < condition < 1e12) if observable else condition > 1e12
    T = np.eye(6)
    T[3:, :3] = skew(fast.R @ m)
    expected = len(M) * fast.residual_rms**2 / (2 * len(M) - 6) * T @ inverse_normal_matrices(normal) @ T.T
    assert np.isfinite(fast.covariance).all() == observable
    if observable:
        np.testing.assert_allclose(fast.covariance, expected, rtol=1e-3, atol=1e-6 * np.abs(expected).max())
    else:
        assert np.isnan(fast.covariance).all()


def test_objective_is_the_papers_cost():
    rng = np.random.default_rng(3123)
    for v, f, M, R0, t0 in list(_bench_problems(rng, counts=(10, 500), per_count=2)) + list(_offset_problems(rng, 4)):
        fast = refine_pose(v, f, M, R0, t0)
        unit = f / np.linalg.norm(f, axis=1)[:, None]
        expected = np.sum(np.cross(unit, M @ fast.R.T + fast.t - v) ** 2)
        assert fast.objective == pytest.approx(expected, rel=1e-8)


def test_any_memory_layout_of_the_start_gives_the_same_answer():
    """R0 and t0 are read through their strides; other layouts of the correspondences go through
    the Python checks (contiguous copies) to the same minimum."""
    rng = np.random.default_rng(3124)
    v, f, M, R0, t0 = next(_offset_problems(rng, 1))
    reference = refine_pose(v, f, M, R0, t0)
    read_only = [a.copy() for a in (v, f, M, R0, t0)]
    for a in read_only:
        a.flags.writeable = False
    strided_t = np.repeat(t0, 2)[::2]
    for found in (refine_pose(v, f, M, np.asfortranarray(R0), strided_t), refine_pose(*read_only)):
        np.testing.assert_array_equal(found.R, reference.R)
        np.testing.assert_array_equal(found.t, reference.t)
        np.testing.assert_array_equal(found.covariance, reference.covariance)
    other = refine_pose(np.asfortranarray(v), np.hstack([f, f])[:, :3], M.tolist(), R0, t0)
    np.testing.assert_allclose(other.R, reference.R, rtol=0, atol=1e-9)
    np.testing.assert_allclose(other.t, reference.t, rtol=0, atol=1e-9 * np.abs(reference.t).max())
    assert _refine.refine(v.astype(np.float32), f, M, R0, t0, 5, STEP_TOLERANCE, COST_TOLERANCE, np.nan,
                          ZERO_DIRECTION) is None
    assert _refine.refine(v, f, M[:-1], R0, t0, 5, STEP_TOLERANCE, COST_TOLERANCE, np.nan, ZERO_DIRECTION) is None
    assert _refine.refine(v, f, M, R0[:2], t0, 5, STEP_TOLERANCE, COST_TOLERANCE, np.nan, ZERO_DIRECTION) is None
    assert _refine.refine(v, f, M, R0, t0.tolist(), 5, STEP_TOLERANCE, COST_TOLERANCE, np.nan, ZERO_DIRECTION) is None


def test_without_covariance_the_pose_is_the_same():
    rng = np.random.default_rng(3125)
    v, f, M, R0, t0 = next(_bench_problems(rng, counts=(20,), per_count=1))
    args = (v, f, M, R0, t0, MAX_ITERATIONS, STEP_TOLERANCE, COST_TOLERANCE, np.nan, ZERO_DIRECTION)
    with_covariance, without = _refine.refine(*args), _refine.refine(*args, False)
    assert without[2] is None
    for a, b in zip(with_covariance[:2] + with_covariance[3:], without[:2] + without[3:]):
        np.testing.assert_array_equal(a, b)


def test_threads_give_the_serial_answers():
    """The compiled work runs without the GIL on per-call buffers: two threads, the same answers."""
    rng = np.random.default_rng(3126)
    problems = list(_bench_problems(rng, counts=(10, 100), per_count=10))
    serial = [refine_pose(*p) for p in problems]
    with ThreadPoolExecutor(max_workers=2) as pool:
        threaded = list(pool.map(lambda p: refine_pose(*p), problems * 3))
    for k, found in enumerate(threaded):
        np.testing.assert_array_equal(found.R, serial[k % len(problems)].R)
        np.testing.assert_array_equal(found.covariance, serial[k % len(problems)].covariance)
