"""The paper's generalized pose solver (issue 3): template, accuracy, Cayley's blind spot, global
optimality against a slow multi-start variable-projection Levenberg-Marquardt."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dmais_pipe.geometry import rotation_error, rotation_from_cayley
from dmais_pipe.pose import PoseError, pose_statistics
from dmais_pipe.pose.equations import coefficients_of
from dmais_pipe.pose.solver import TEMPLATE_PATH, kernel, runtime, solve_generalized_pose
from dmais_pipe.pose.template import Template, check_template, template_entries

from pose_scenes import (centred_cost, dmais_scene, generalized_scene, multistart_minimum, narrow_camera_scene,
                         single_camera_scene)

SCENES = {
    "opengv": lambda rng, noise: generalized_scene(rng, n=10, noise=noise * 1e-3, max_angle=np.pi),
    "dmais": lambda rng, noise: dmais_scene(rng, 4, noise_px=4 * noise),
    "dmais_planar": lambda rng, noise: dmais_scene(rng, 4, noise_px=4 * noise, planar=True),
    "single": lambda rng, noise: single_camera_scene(rng, 10, noise_px=4 * noise),
    "single_planar": lambda rng, noise: single_camera_scene(rng, 10, noise_px=4 * noise, planar=True),
    "opengv_many": lambda rng, noise: generalized_scene(rng, n=100, noise=noise * 1e-3, max_angle=np.pi),
}


def test_template_is_the_stored_one_and_valid_on_fresh_instances():
    template = Template.from_json(TEMPLATE_PATH.read_text())
    assert template.shape == (118, 158)
    assert len(template.basis) == 40 and template.n_reducible == 21
    check_template(template, seeds=(101, 102))
    assert runtime().m == 118


def test_template_check_rejects_a_template_that_drops_a_needed_monomial():
    """Dropping a row with an E column keeps the block square and nonsingular, yet the reductions
    then carry a term in the dropped monomial: such a template is wrong, however well it polishes."""
    template = Template.from_json(TEMPLATE_PATH.read_text())
    smaller = Template(
        action_variable=template.action_variable,
        rows=tuple(row for row in template.rows if row != (4, (1, 3, 0))),
        columns=tuple(column for column in template.columns if column != (5, 3, 0)),
        n_reducible=template.n_reducible,
    )
    assert smaller.shape == (117, 157)
    with pytest.raises(RuntimeError, match="drops excessive monomials"):
        check_template(smaller, seeds=(101,))


@pytest.mark.parametrize("kind", sorted(SCENES))
def test_noise_free_rotation_accuracy(kind):
    rng = np.random.default_rng(7)
    errors = []
    for _ in range(120):
        origins, directions, points, R, t = SCENES[kind](rng, 0.0)
        pose = solve_generalized_pose(origins, directions, points)
        errors.append(rotation_error(pose.R, R))
        assert pose.candidates[0].cost <= pose.cost
    errors = np.array(errors)
    assert np.median(errors) < 1e-9, kind
    assert np.percentile(errors, 99.9) < 1e-6, kind


def test_noise_free_percentiles_over_all_kinds():
    """The issue's figures: median below 1e-10 rad, 99.9th percentile below 1e-6 rad."""
    rng = np.random.default_rng(11)
    errors = []
    for i in range(600):
        kind = sorted(SCENES)[i % len(SCENES)]
        origins, directions, points, R, _ = SCENES[kind](rng, 0.0)
        errors.append(rotation_error(solve_generalized_pose(origins, directions, points).R, R))
    assert np.median(errors) < 1e-10
    assert np.percentile(errors, 99.9) < 1e-6


@pytest.mark.parametrize("yaw_deg", range(0, 360, 15))
def test_nadir_rig_at_every_yaw(yaw_deg):
    """A down-looking rig over a z-up world is a 180-degree rotation: Cayley's blind spot."""
    rng = np.random.default_rng(yaw_deg)
    origins, directions, points, R, t = dmais_scene(rng, 3, yaw=np.deg2rad(yaw_deg))
    pose = solve_generalized_pose(origins, directions, points)
    assert rotation_error(pose.R, R) < 1e-8
    np.testing.assert_allclose(pose.t, t, atol=1e-3)


def test_minimal_sets_contain_the_truth():
    rng = np.random.default_rng(3)
    for _ in range(100):
        origins, directions, points, R, t = generalized_scene(rng, n=3, max_angle=np.pi)
        pose = solve_generalized_pose(origins, directions, points)
        assert min(rotation_error(c.R, R) for c in pose.candidates) < 1e-8
        assert pose.cost < 1e-12


def clustered_roots_scene():
    """Draw 10 of seed 3 in `test_minimal_sets_contain_the_truth`: three stationary points within
    0.041 rad, the truth (a minimum), a saddle 0.021 rad from it and a minimum 0.041 rad from it."""
    rng = np.random.default_rng(3)
    for _ in range(11):
        origins, directions, points, R, _ = generalized_scene(rng, n=3, max_angle=np.pi)
    return origins, directions, points, R


# The solving frame of `clustered_roots_scene` where dsyev runs OpenBLAS's SkylakeX kernels: the sphere
# relaxation of a minimal problem has a 6-dimensional hard case, and its minimiser (so the frame)
# moves by ~0.06 with the last bits of dsyev's eigenvectors.
CLUSTER_FRAME = np.array([[0.2859417778076454, -0.6735533533381766, -0.6815887175644124],
                          [0.11737989685532757, 0.7305505547143786, -0.6726944676602784],
                          [0.951030630168364, 0.11234663863868133, 0.28795654753478606]])


def test_clustered_roots_keep_the_truth():
    """The truth of `clustered_roots_scene` is among the candidates whatever the BLAS kernel (with
    OpenBLAS's SkylakeX or Cooperlake kernels, the default on AVX-512 machines, the whole cluster
    was lost: 23 candidates instead of 28)."""
    origins, directions, points, R = clustered_roots_scene()
    pose = solve_generalized_pose(origins, directions, points)
    assert min(rotation_error(c.R, R) for c in pose.candidates) < 1e-8
    assert pose.cost < 1e-12


def test_polishing_settles_a_cluster_of_nearly_repeated_roots():
    """In CLUSTER_FRAME the truth and the saddle 0.021 rad away come out of the template as a nearly
    real complex pair, whose real part lies 9e-3 rad from the truth where the Hessian is nearly
    singular (Newton's first step lands 0.25 rad away), and the minimum 0.041 rad away comes 3e-3
    rad off, more than two Newton steps from it: polishing alone dropped the whole cluster. The
    roots and their polishing are the compiled code's own arithmetic (no BLAS), so this fails or
    passes alike on every machine."""
    origins, directions, points, R = clustered_roots_scene()
    stats = pose_statistics(origins, directions, points)
    roots = kernel().rotations_of_roots(stats.H, stats.g, CLUSTER_FRAME)
    assert 1e-3 < rotation_error(roots, R[None]).min() < 2e-2  # the truth only as an inaccurate start
    polished = kernel().polish_rotations(stats.H, stats.g, stats.c, roots)
    errors = np.sort(rotation_error(polished, R[None]))
    assert errors[0] < 1e-8
    assert np.any(np.abs(errors - 0.0415) < 1e-3)  # the neighbouring minimum too


def reference_action_matrix(H, g, P):
    """The action matrix (40, 40) of eq. EF6 in the frame P from the dense template and numpy's
    solve, and the basis as {monomial: index}."""
    template = Template.from_json(TEMPLATE_PATH.read_text())
    K = np.kron(np.eye(3), P.T)  # r = K r' for R = R' P
    H, g = K.T @ H @ K, K.T @ g
    coeffs = coefficients_of(H / np.trace(H), g / np.trace(H))
    target, source = template_entries(template.rows, template.columns)
    C = np.zeros(template.shape[0] * template.shape[1])
    C[target] = coeffs.reshape(-1)[source]
    C = C.reshape(template.shape)
    m = template.shape[0]
    reducible = -np.linalg.solve(C[:, :m], C[:, m:])[m - template.n_reducible :]  # R = reducible @ B
    basis = {mono: i for i, mono in enumerate(template.basis)}
    reducible_row = {mono: i for i, mono in enumerate(template.reducible)}
    action = np.zeros((40, 40))
    for i, (a, b, c) in enumerate(template.basis):
        product = (a + 1, b, c)  # the action variable is qx
        if product in basis:
            action[i, basis[product]] = 1.0
        else:
            action[i] = reducible[reducible_row[product]]
    return action, basis


def reference_root_rotations(H, g, P):
    """Slow reference of the compiled root finder: the real roots of eq. EF6 in the frame P from the
    dense template, numpy's solve and numpy's eig, as rotations (k, 3, 3)."""
    action, basis = reference_action_matrix(H, g, P)
    _, vectors = np.linalg.eig(action)
    units = vectors[[basis[(0, 0, 0)], basis[(1, 0, 0)], basis[(0, 1, 0)], basis[(0, 0, 1)]]]
    q = (units[1:] / units[:1]).T
    real = np.abs(q.imag).max(axis=1) < 1e-9 * (1 + np.abs(q).max(axis=1))
    return rotation_from_cayley(q[real].real) @ P


@pytest.mark.parametrize("kind", ["opengv", "dmais", "single"])
def test_compiled_roots_equal_a_numpy_reference(kind):
    rng = np.random.default_rng(17)
    for trial in range(20):
        origins, directions, points, R, _ = SCENES[kind](rng, 0.0)
        stats = pose_statistics(origins, directions, points)
        P = Rotation.from_rotvec(rng.normal(scale=0.3, size=3)).as_matrix() @ R  # a frame near the truth
        compiled = kernel().rotations_of_roots(stats.H, stats.g, P)
        reference = reference_root_rotations(stats.H, stats.g, P)
        # The true root is as accurate as numpy's, to the rounding of two LAPACK builds (unpolished
        # roots of ill-conditioned instances differ by up to ~50x; polishing finishes the job).
        assert rotation_error(compiled, R[None]).min() <= max(1e-7, 100 * rotation_error(reference, R[None]).min())
        # Every real root is found (nearly real pairs may come in addition); those within 90 deg of
        # the frame (|q| < 1) agree to the unpolished template's accuracy (3e-4 at worst seen here).
        assert len(compiled) >= len(reference)
        near = reference[rotation_error(reference, P[None]) < np.pi / 2]
        assert max(np.abs(compiled - Rr).reshape(-1, 9).max(axis=1).min() for Rr in near) < 1e-2, (kind, trial)


def test_translation_in_survey_coordinates():
    rng = np.random.default_rng(5)
    origins, directions, points, R, t = dmais_scene(rng, 5)
    pose = solve_generalized_pose(origins, directions, points)
    centre, true_centre = -pose.R.T @ pose.t, -R.T @ t
    assert np.linalg.norm(centre - true_centre) < 1e-5


# ---------------------------------------------------------------- global optimality (slow LM)


def _direct_cost(origins, directions, points, R, t):
    return float(np.sum(np.cross(directions, points @ R.T + t - origins) ** 2))


def multistart_lm(origins, directions, points, n_random=16, iterations=60, seed=0):
    """The least cost of `pose_scenes.multistart_minimum` (see there)."""
    return multistart_minimum(origins, directions, points, n_random, iterations, seed)[0]


def test_returned_cost_is_the_global_minimum_in_999_of_2000_noisy_trials():
    rng = np.random.default_rng(2026)
    kinds = sorted(SCENES)
    misses = []
    for i in range(2000):
        kind = kinds[i % len(kinds)]
        origins, directions, points, _, _ = SCENES[kind](rng, 1.0)
        if kind == "opengv_many" and i % 4:  # fewer of the slow 100-point cases
            origins, directions, points, _, _ = SCENES["opengv"](rng, 1.0)
        pose = solve_generalized_pose(origins, directions, points)
        ours = _direct_cost(origins, directions, points, pose.R, pose.t)
        assert abs(ours - pose.cost) <= 1e-6 * ours + 1e-12
        reference = multistart_lm(origins, directions, points, seed=i)
        if ours > reference * (1 + 1e-6) + 1e-15:
            misses.append((i, kind, ours, reference))
    assert len(misses) <= 2, misses


def _narrow_misses(fovs, trials, seed):
    """Trials (index, field of view, cost ratio, angle to the reference in deg) where the solver's
    cost exceeds that of multi-start LM (also started at the true rotation) on a narrow camera
    over flat ground; costs on the centred points."""
    rng = np.random.default_rng(seed)
    misses = []
    for i in range(trials):
        fov = fovs[i % len(fovs)]
        origins, directions, points, R, _ = narrow_camera_scene(rng, fov)
        pose = solve_generalized_pose(origins, directions, points)
        ours = centred_cost(origins, directions, points, pose.R, pose.t)
        assert abs(ours - pose.cost) <= 1e-3 * ours  # the quadratic form rounds at ~1e-4 at 0.5 deg
        reference, R_reference, _ = multistart_minimum(origins, directions, points, n_random=8, iterations=40,
                                                       seed=i, starts=[R])
        if ours > reference * (1 + 1e-6):
            misses.append((i, fov, ours / reference, np.rad2deg(rotation_error(pose.R, R_reference))))
    return misses


def test_global_minimum_through_a_narrow_camera_over_flat_ground():
    """Issue 16 item 2: one camera of 0.5-2 deg over a plane (10 points, 0.3 px) has minima a few
    degrees apart (the plane and its flip) that the template's roots cannot tell apart. Before the
    flip descent and the exact tie costs, 2% of the 0.5 deg cases missed the minimum (4 here)."""
    misses = _narrow_misses([0.5], 150, seed=516) + _narrow_misses([1.0, 2.0], 50, seed=1602)
    assert len(misses) <= 1, misses


def test_global_minimum_through_the_5_4_deg_camera_over_flat_ground():
    """The paper's subset #0 (C0 alone) over a flat area: the minimum in every case."""
    misses = _narrow_misses([5.4], 60, seed=1654)
    assert not misses, misses


# ---------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda o, d, p: (o[:2], d[:2], p[:2]), "at least 3"),
        (lambda o, d, p: (o, d, p[:-1]), "mismatched lengths"),
        (lambda o, d, p: (o, d, np.outer(np.arange(len(p)), [1.0, 2.0, 3.0])), "collinear"),
        (lambda o, d, p: (o, np.where(np.arange(len(d))[:, None] == 1, np.nan, d), p), "directions row 1"),
        (lambda o, d, p: (o, np.where(np.arange(len(d))[:, None] == 2, 0.0, d), p), "directions row 2 is zero"),
    ],
)
def test_degenerate_input_raises(mutate, message):
    origins, directions, points, _, _ = generalized_scene(np.random.default_rng(1), n=8)
    with pytest.raises(PoseError, match=message):
        solve_generalized_pose(*mutate(origins, directions, points))


# ---------------------------------------------------------------- beyond the paper


def test_refine_returns_covariance_matching_the_scatter():
    rng = np.random.default_rng(21)
    origins, directions, points, R, t = dmais_scene(rng, 6, noise_px=4.0)
    pose = solve_generalized_pose(origins, directions, points, refine=True)
    assert pose.covariance.shape == (6, 6)
    assert np.all(np.linalg.eigvalsh(pose.covariance[:3, :3]) > 0)  # t couples to R through UTM offsets
    # the truth lies within a few standard deviations of the refined rotation
    err = Rotation.from_matrix(R @ pose.R.T).as_rotvec()
    assert err @ np.linalg.solve(pose.covariance[:3, :3], err) < 30


def test_robust_mode_recovers_the_pose_with_40_percent_wrong_correspondences():
    from dmais_pipe.pose.robust import solve_robust

    rng = np.random.default_rng(4)
    origins, directions, points, R, t = dmais_scene(rng, 10, noise_px=1.0)
    wrong = rng.permutation(len(points))[: int(0.4 * len(points))]
    points = points.copy()
    points[wrong] = points[rng.permutation(wrong)] + rng.uniform(-200, 200, size=(len(wrong), 3))
    result = solve_robust(origins, directions, points, threshold_rad=5 / 45000)
    assert not result.inliers[wrong].any()
    assert result.inliers.sum() == len(points) - len(wrong)
    right = np.setdiff1d(np.arange(len(points)), wrong)
    clean = solve_generalized_pose(origins[right], directions[right], points[right])
    assert rotation_error(result.R, clean.R) < 1e-9  # the paper's solver on the inliers
    assert rotation_error(result.R, R) < 3e-4  # 1 px at 45000 px is 2.2e-5 rad; 18 inliers


def test_batch_solves_every_frame_and_reports_bad_ones():
    from dmais_pipe.pose.solver import solve_batch

    rng = np.random.default_rng(8)
    frames = [dmais_scene(rng, 3) for _ in range(4)]
    problems = [(o, d, p) for o, d, p, _, _ in frames]
    problems.insert(2, (problems[0][0][:2], problems[0][1][:2], problems[0][2][:2]))
    results = solve_batch(problems)
    assert isinstance(results[2], PoseError)
    for result, (_, _, _, R, _) in zip(results[:2] + results[3:], frames):
        assert rotation_error(result.R, R) < 1e-8


def test_threaded_batch_equals_the_sequential_one():
    """The compiled core runs without the GIL: threads solve frames at once, with the same results."""
    from dmais_pipe.pose.solver import solve_batch

    rng = np.random.default_rng(9)
    problems = [dmais_scene(rng, 4, noise_px=4.0)[:3] for _ in range(40)]
    problems.insert(7, (problems[0][0][:2], problems[0][1][:2], problems[0][2][:2]))
    sequential = solve_batch(problems)
    threaded = solve_batch(problems, workers=3)
    assert isinstance(threaded[7], PoseError)
    for one, other in zip(sequential[:7] + sequential[8:], threaded[:7] + threaded[8:]):
        np.testing.assert_array_equal(one.R, other.R)
        assert one.cost == other.cost and len(one.candidates) == len(other.candidates)


# ---------------------------------------------------------------- certificate of global optimality


def test_certified_solutions_are_global_minima_and_generic_scenes_are_certified():
    """Soundness: a certified pose costs no more than any minimum multi-start LM finds; and the
    certificate holds on OpenGV-like scenes at ordinary noise (the dual is tight there)."""
    rng = np.random.default_rng(31)
    flags = []
    for i in range(30):
        origins, directions, points, _, _ = generalized_scene(rng, n=10, noise=1e-3, max_angle=np.pi)
        pose = solve_generalized_pose(origins, directions, points)
        flags.append(pose.certified)
        if pose.certified:
            assert pose.cost <= multistart_lm(origins, directions, points, seed=i) * (1 + 1e-6) + 1e-15
    assert np.mean(flags) >= 0.9


def test_certificate_refuses_costlier_stationary_points():
    """Every stationary candidate satisfies the KKT conditions, but only a global minimum can have
    a positive semidefinite Lagrangian Hessian: the costlier candidates must fail the check."""
    rng = np.random.default_rng(5)
    refused = 0
    for _ in range(40):
        origins, directions, points, _, _ = generalized_scene(rng, n=10, noise=1e-3, max_angle=np.pi)
        stats = pose_statistics(origins, directions, points)
        pose = solve_generalized_pose(origins, directions, points)
        assert kernel().certify(stats.H, stats.g, stats.c, pose.R) == pose.certified
        for candidate in pose.candidates[1:]:
            if candidate.cost > pose.candidates[0].cost * (1 + 1e-6) + 1e-12:
                assert not kernel().certify(stats.H, stats.g, stats.c, np.ascontiguousarray(candidate.R))
                refused += 1
    assert refused > 40


def test_candidates_read_as_a_list_of_stationary_points():
    """`Candidates` builds each Candidate on access from the core's arrays: every one must be a
    stationary point of the cost with its own optimal translation, in order of cost, with the
    solution among them, whichever way the sequence is read (index, negative index, slice, loop)."""
    rng = np.random.default_rng(11)
    origins, directions, points, R, t = dmais_scene(rng, 4, noise_px=4.0)
    pose = solve_generalized_pose(origins, directions, points)
    listed = list(pose.candidates)
    assert len(listed) == len(pose.candidates) >= 1
    assert [c.cost for c in listed] == sorted(c.cost for c in listed)
    assert all(isinstance(c.cost, float) and isinstance(c.in_front, float) for c in listed)
    assert pose.candidates[-1].cost == listed[-1].cost and len(pose.candidates[1:]) == len(listed) - 1
    assert any(np.array_equal(c.R, pose.R) and np.array_equal(c.t, pose.t) and c.cost == pose.cost for c in listed)
    with pytest.raises(IndexError):
        pose.candidates[len(listed)]
    unit = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    for c in listed:
        assert abs(np.linalg.det(c.R) - 1) < 1e-9
        residual = np.cross(unit, points @ c.R.T + c.t - origins)
        # the optimal translation zeroes the cost's gradient in t: sum_i [f_i]x^T [f_i]x (R M_i + t - v_i)
        gradient_t = -np.cross(unit, residual).sum(axis=0)
        assert np.linalg.norm(gradient_t) < 1e-6 * (1 + np.sqrt(np.sum(residual**2)) * len(points))
        assert c.cost == pytest.approx(np.sum(residual**2), rel=1e-6, abs=1e-9)
