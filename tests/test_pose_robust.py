"""Minimal gP3P solver, angular pose refinement and RANSAC for the generalized absolute pose
(paper, eq. projEq: alpha f_i + v_i = R M_i + t), on seeded synthetic rigs."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from dmais_pipe.camera import Camera
from dmais_pipe.geometry import Rigid3, rotation_error, rotation_from_euler_zyx
from dmais_pipe.pose import PoseError
from dmais_pipe.pose.gp3p import absolute_orientation, gp3p
from dmais_pipe.pose.refine import angular_residuals, cramer_rao_bound, ray_errors, refine_pose, tangent_bases
from pose_scenes import dmais_scene as paper_rig_scene
from dmais_pipe.pose.robust import ransac_generalized_pose, required_iterations
from dmais_pipe.rig import Rig

# --------------------------------------------------------------------------- synthetic scenes

FOCAL_PX = 45000.0
# tab:extrinsics_R / tab:extrinsics_t ("known" columns): rig_from_cam ZYX Euler angles (deg) and
# camera centres (m) in the rig (C0) frame.
EULER_DEG = {
    "C0": (0.0, 0.0, 0.0),
    "C1": (-179.811, -0.152, 46.233),
    "C2": (-90.048, -1.170, 44.758),
    "C3": (0.150, -0.047, 44.038),
    "C4": (90.140, 1.180, 45.615),
}
CENTRES = {
    "C0": (0.0, 0.0, 0.0),
    "C1": (-0.002, 0.102, -0.086),
    "C2": (-0.113, -0.012, -0.100),
    "C3": (0.000, -0.143, -0.097),
    "C4": (0.122, -0.010, -0.100),
}


def random_rotation(rng) -> np.ndarray:
    return Rotation.random(random_state=int(rng.integers(2**31))).as_matrix()


def generalized_scene(rng, n=3, n_cameras=4, central=False, depth=(2.0, 10.0)):
    """Random generalized camera: ray origins in a 2 m box (one per camera), any directions.

    Returns origins, unit directions (n, 3), world points (n, 3), true R (3, 3), t (3,).
    """
    R, t = random_rotation(rng), rng.normal(size=3) * 2.0
    centres = np.zeros((n_cameras, 3)) if central else rng.uniform(-1.0, 1.0, (n_cameras, 3))
    origins = centres[rng.integers(0, n_cameras, n)]
    directions = rng.normal(size=(n, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    depths = rng.uniform(*depth, n)
    points = (origins + depths[:, None] * directions - t) @ R  # R^T (x_rig - t)
    return origins, directions, points, R, t


def perturb(rng, directions, sigma) -> np.ndarray:
    """Unit directions with isotropic angular noise sigma (rad) per tangent-plane component."""
    noisy = directions + sigma * np.einsum("ni,nij->nj", rng.normal(size=(len(directions), 2)),
                                           tangent_bases(directions))
    return noisy / np.linalg.norm(noisy, axis=1)[:, None]


def dmais_rig() -> Rig:
    """Five 4096 x 3000 px cameras, f = 45000 px: C0 nadir, C1..C4 tilted 45 deg, ~0.1 m apart."""
    cameras, cam_from_rig = {}, {}
    for name in EULER_DEG:
        cameras[name] = Camera(FOCAL_PX, FOCAL_PX, 2047.5, 1499.5, 0.0, 4096, 3000)
        rig_from_cam = Rigid3(rotation_from_euler_zyx(np.radians(EULER_DEG[name])), CENTRES[name])
        cam_from_rig[name] = rig_from_cam.inverse()
    return Rig(cameras, cam_from_rig, "C0")


def dmais_scene(rng, rig, per_camera=30, noise_px=1.0, outlier_ratio=0.4):
    """Rig 350 m above flat-ish ground (+-3 m), ground points seen at random pixels.

    Returns origins, directions (from noisy pixels), world points (outliers replaced by random
    ground points), the true rig_from_world (R, t) and the outlier mask (n,).
    """
    R = Rotation.from_euler("xyz", [np.pi + 0.02, -0.015, rng.uniform(0, 2 * np.pi)]).as_matrix()
    centre = np.array([rng.uniform(-1e3, 1e3), rng.uniform(-1e3, 1e3), 350.0])
    t = -R @ centre
    origins, directions, points = [], [], []
    for name, camera in rig.cameras.items():
        uv = rng.uniform([0, 0], [camera.width - 1, camera.height - 1], (per_camera, 2))
        v, f = rig.rays(name, uv)
        start, heading = (v - t) @ R, f @ R  # world frame
        alpha = (rng.uniform(-3.0, 3.0, per_camera) - start[:, 2]) / heading[:, 2]
        points.append(start + alpha[:, None] * heading)
        v_noisy, f_noisy = rig.rays(name, uv + rng.normal(0.0, noise_px, uv.shape))
        origins.append(v_noisy)
        directions.append(f_noisy)
    origins, directions, points = map(np.concatenate, (origins, directions, points))
    outliers = rng.random(len(points)) < outlier_ratio
    random_ground = np.column_stack([rng.uniform(-600, 600, (outliers.sum(), 2)) + centre[:2],
                                     rng.uniform(-3.0, 3.0, outliers.sum())])
    points[outliers] = random_ground
    return origins, directions, points, R, t, outliers


def pose_error(R, t, R_true, t_true) -> float:
    """max(rotation angle, translation error relative to max(1, |t|))."""
    scale = max(1.0, float(np.linalg.norm(t_true)))
    return max(float(rotation_error(R, R_true)), float(np.linalg.norm(t - t_true)) / scale)


def mahalanobis(refined, R_ref, t_ref) -> float:
    """Mahalanobis distance of (R_ref, t_ref) from a RefinedPose under its covariance of (omega, t)."""
    error = np.concatenate([Rotation.from_matrix(R_ref @ refined.R.T).as_rotvec(), t_ref - refined.t])
    return float(np.sqrt(error @ np.linalg.solve(refined.covariance, error)))


def colmap_rays(origins, directions):
    """pycolmap inputs modelling each ray as its own camera: SIMPLE_PINHOLE f = 1, c = 0, whose
    optical axis is the ray (rows b1, b2, f of cam_from_rig), so every point2D is (0, 0) and the
    normalized reprojection error is the tangent of the angular error, ~ our residual."""
    bases = tangent_bases(directions)
    camera = pycolmap.Camera(model="SIMPLE_PINHOLE", width=2, height=2, params=[1.0, 0.0, 0.0])
    cams_from_rig = []
    for v, f, B in zip(origins, directions, bases):
        R = np.vstack([B, f])
        cams_from_rig.append(pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ v))
    n = len(origins)
    return np.zeros((n, 2)), list(range(n)), cams_from_rig, [camera] * n


def refine_from_minimal_test_double(origins, directions, points):
    """TEST DOUBLE standing in for the lead's globally optimal `pose.solver` final solver.

    Best gp3p pose over a few seeded triples of the (inlier) correspondences it is given, refined
    by refine_pose. Returns an object with R and t, as the real final solver does.
    """
    rng = np.random.default_rng(123)
    best, best_cost = None, np.inf
    for _ in range(10):
        sample = rng.choice(len(points), 3, replace=False)
        for R, t in gp3p(origins[sample], directions[sample], points[sample]):
            errors = ray_errors(origins, directions, points, R, t)
            cost = float(np.sum(np.minimum(errors, 1.0) ** 2))
            if cost < best_cost:
                best, best_cost = (R, t), cost
    return refine_pose(origins, directions, points, *best)


# --------------------------------------------------------------------------- gp3p


@pytest.mark.parametrize("central", [False, True], ids=["generalized", "central"])
def test_gp3p_true_pose_among_solutions(central):
    rng = np.random.default_rng(7 if central else 8)
    hits = 0
    for _ in range(1000):
        v, f, M, R, t = generalized_scene(rng, central=central)
        solutions = gp3p(v, f, M)
        assert len(solutions) <= 8
        hits += any(pose_error(Rs, ts, R, t) < 1e-8 for Rs, ts in solutions)
    assert hits >= 995


def test_gp3p_near_central_narrow_rays():
    """DMAIS-like triples: origins within 0.1 m, rays within 10 deg of each other, 350-500 m deep."""
    rng = np.random.default_rng(9)
    hits = 0
    for _ in range(300):
        R, t = random_rotation(rng), rng.normal(size=3) * 100.0
        v = rng.uniform(-0.1, 0.1, (3, 3))
        f = np.column_stack([np.tan(np.radians(10.0)) * rng.uniform(-1, 1, (3, 2)), np.ones(3)])
        f /= np.linalg.norm(f, axis=1)[:, None]
        M = (v + rng.uniform(350, 500, 3)[:, None] * f - t) @ R
        hits += any(pose_error(Rs, ts, R, t) < 1e-8 for Rs, ts in gp3p(v, f, M))
    assert hits >= 299


def test_gp3p_solutions_satisfy_the_ray_constraints():
    rng = np.random.default_rng(10)
    for _ in range(50):
        v, f, M, _, _ = generalized_scene(rng)
        for R, t in gp3p(v, f, M):
            np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
            assert np.linalg.det(R) > 0
            p = M @ R.T + t - v
            depth = np.einsum("ij,ij->i", p, f)
            assert (depth > 0).all()
            np.testing.assert_allclose(p, depth[:, None] * f, atol=1e-8)


def test_gp3p_all_solutions_without_depth_filter():
    """Without the depth filter every real solution is kept: a superset, at most 8."""
    rng = np.random.default_rng(11)
    for _ in range(50):
        v, f, M, _, _ = generalized_scene(rng)
        front, every = gp3p(v, f, M), gp3p(v, f, M, positive_depth=False)
        assert len(front) <= len(every) <= 8
        for R, t in front:
            assert any(pose_error(R, t, Rs, ts) < 1e-12 for Rs, ts in every)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gp3p_contains_pycolmap_pose(seed):
    """pycolmap's generalized RANSAC on 12 exact correspondences finds a pose our gp3p also finds
    from the first three of them."""
    rng = np.random.default_rng(100 + seed)
    v, f, M, R, t = generalized_scene(rng, n=12)
    points2D, camera_idxs, cams_from_rig, cameras = colmap_rays(v, f)
    options = pycolmap.RANSACOptions()
    options.max_error = 1e-6
    options.random_seed = seed
    result = pycolmap.estimate_generalized_absolute_pose(points2D, M, camera_idxs, cams_from_rig, cameras,
                                                         options)
    R_colmap = result["rig_from_world"].rotation.matrix()
    t_colmap = np.asarray(result["rig_from_world"].translation)
    assert pose_error(R_colmap, t_colmap, R, t) < 1e-8
    assert any(pose_error(Rs, ts, R_colmap, t_colmap) < 1e-8 for Rs, ts in gp3p(v[:3], f[:3], M[:3]))


def test_gp3p_input_checks():
    rng = np.random.default_rng(12)
    v, f, M, _, _ = generalized_scene(rng, n=4)
    with pytest.raises(PoseError, match="exactly 3"):
        gp3p(v, f, M)
    with pytest.raises(PoseError, match="shape"):
        gp3p(v[:3, :2], f[:3], M[:3])
    collinear = np.array([[0.0, 0, 0], [1, 1, 1], [2, 2, 2]])
    assert gp3p(v[:3], f[:3], collinear) == []


def test_absolute_orientation_three_points():
    rng = np.random.default_rng(13)
    R, t = random_rotation(rng), rng.normal(size=3)
    M = rng.normal(size=(3, 3))
    R_est, t_est = absolute_orientation(M, M @ R.T + t)
    assert pose_error(R_est, t_est, R, t) < 1e-12


# --------------------------------------------------------------------------- refine_pose


def test_refine_jacobian_matches_finite_differences():
    from dmais_pipe.geometry import exp_so3
    from dmais_pipe.pose.refine import _jacobian

    rng = np.random.default_rng(20)
    v, f, M, R, t = generalized_scene(rng, n=8)
    R, t = exp_so3([0.1, -0.2, 0.05]) @ R, t + 0.1
    bases = tangent_bases(f)
    r, J = _jacobian(v, bases, M, R, t)
    numeric = np.empty_like(J)
    h = 1e-7
    for k in range(6):
        step = np.zeros(6)
        step[k] = h
        shifted = angular_residuals(v, bases, M, exp_so3(step[:3]) @ R, t + step[3:]).reshape(-1)
        numeric[:, k] = (shifted - r) / h
    np.testing.assert_allclose(J, numeric, atol=1e-6)


def _least_squares_reference(v, f, M, R0, t0):
    bases = tangent_bases(f)

    def residuals(x):
        R = Rotation.from_rotvec(x[:3]).as_matrix() @ R0
        return angular_residuals(v, bases, M, R, t0 + x[3:]).reshape(-1)

    x = least_squares(residuals, np.zeros(6), method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15).x
    return Rotation.from_rotvec(x[:3]).as_matrix() @ R0, t0 + x[3:]


def test_refine_converges_from_perturbed_pose():
    rng = np.random.default_rng(21)
    v, f, M, R, t = generalized_scene(rng, n=40, n_cameras=5)
    f_noisy = perturb(rng, f, 1e-3)
    R0 = Rotation.from_rotvec(np.radians([3.0, -2.0, 4.0])).as_matrix() @ R
    t0 = t + np.array([0.3, -0.2, 0.25])
    refined = refine_pose(v, f_noisy, M, R0, t0)
    assert refined.converged and refined.n_iterations < 20
    R_ref, t_ref = _least_squares_reference(v, f_noisy, M, R, t)
    assert pose_error(refined.R, refined.t, R_ref, t_ref) < 1e-8
    bases = tangent_bases(f_noisy)
    cost, cost_ref = (float(np.sum(angular_residuals(v, bases, M, *pose) ** 2))
                      for pose in [(refined.R, refined.t), (R_ref, t_ref)])
    assert cost <= cost_ref * (1 + 1e-12)  # at least as good as scipy's minimum
    assert pose_error(refined.R, refined.t, R, t) < 2e-3  # noise-limited
    assert 0.7e-3 < refined.residual_rms < 1.6e-3  # ~ sqrt(2) sigma per ray
    assert refined.covariance.shape == (6, 6)


def test_refine_matches_pycolmap_pose_and_covariance():
    """pycolmap minimises tan-of-angle errors (equal to ours to first order) and reports the
    covariance of (quaternion tangent = omega / 2, t) for unit residual variance."""
    rng = np.random.default_rng(22)
    sigma = 1e-4
    v, f, M, R, t = generalized_scene(rng, n=30, n_cameras=5)
    f_noisy = perturb(rng, f, sigma)
    R0 = Rotation.from_rotvec([0.01, -0.02, 0.005]).as_matrix() @ R
    ours = refine_pose(v, f_noisy, M, R0, t + 0.01, sigma=sigma)

    points2D, camera_idxs, cams_from_rig, cameras = colmap_rays(v, f_noisy)
    options = pycolmap.AbsolutePoseRefinementOptions()
    options.gradient_tolerance = 1e-20
    start = pycolmap.Rigid3d(pycolmap.Rotation3d(R0), t + 0.01)
    result = pycolmap.refine_generalized_absolute_pose(
        start, points2D, M, np.ones(len(M), bool), camera_idxs, cams_from_rig, cameras, options,
        return_covariance=True)
    R_colmap = result["rig_from_world"].rotation.matrix()
    t_colmap = np.asarray(result["rig_from_world"].translation)
    assert pose_error(ours.R, ours.t, R_colmap, t_colmap) < 1e-7
    assert mahalanobis(ours, R_colmap, t_colmap) < 1e-2  # same minimum, to 1/100 of a sigma
    half_angle = np.diag([2.0, 2.0, 2.0, 1.0, 1.0, 1.0])
    covariance_colmap = sigma**2 * half_angle @ result["covariance"] @ half_angle
    np.testing.assert_allclose(ours.covariance, covariance_colmap, rtol=1e-3,
                               atol=1e-3 * np.abs(covariance_colmap).max())


def test_refine_covariance_matches_scatter():
    rng = np.random.default_rng(23)
    sigma = 1e-3
    v, f, M, R, t = generalized_scene(rng, n=30, n_cameras=5)
    errors, predicted, aposteriori = [], [], []
    for _ in range(500):
        f_noisy = perturb(rng, f, sigma)
        result = refine_pose(v, f_noisy, M, R, t, sigma=sigma)
        omega = Rotation.from_matrix(R @ result.R.T).as_rotvec()  # R_true = exp(omega) R_est
        errors.append(np.concatenate([omega, t - result.t]))
        predicted.append(result.covariance)
        unit_weight = refine_pose(v, f_noisy, M, result.R, result.t)  # s^2 from the residuals
        aposteriori.append(unit_weight.covariance[0, 0] / result.covariance[0, 0])
    errors = np.array(errors)
    empirical = errors.T @ errors / len(errors)
    predicted = np.mean(predicted, axis=0)
    np.testing.assert_allclose(np.diag(empirical), np.diag(predicted), rtol=0.2)
    correlation = lambda C: C / np.sqrt(np.outer(np.diag(C), np.diag(C)))  # noqa: E731
    # a correlation from 500 samples has a standard error of about 0.045
    np.testing.assert_allclose(correlation(empirical), correlation(predicted), atol=0.2)
    assert abs(np.mean(aposteriori) - 1.0) < 0.05  # E[s^2] = sigma^2


def test_refine_input_checks():
    rng = np.random.default_rng(24)
    v, f, M, R, t = generalized_scene(rng, n=6)
    with pytest.raises(PoseError, match="rotation"):
        refine_pose(v, f, M, 2.0 * R, t)
    with pytest.raises(PoseError, match="sigma"):
        refine_pose(v, f, M, R, t, sigma=-1.0)
    with pytest.raises(PoseError, match="mismatched"):
        refine_pose(v[:5], f, M, R, t)
    assert np.isnan(refine_pose(v[:3], f[:3], M[:3], R, t).covariance).all()  # no redundancy


# --------------------------------------------------------------------------- RANSAC


def test_required_iterations():
    assert required_iterations(1.0, 0.999) == 1
    assert required_iterations(0.6, 0.999) == 29  # log(0.001) / log(1 - 0.216) = 28.3
    assert required_iterations(0.0, 0.999) == np.inf


@pytest.mark.parametrize("seed", [0, 1])
def test_ransac_dmais_rig_with_40_percent_outliers(seed):
    rng = np.random.default_rng(30 + seed)
    v, f, M, R, t, outliers = dmais_scene(rng, dmais_rig(), per_camera=30, noise_px=1.0, outlier_ratio=0.4)
    threshold = 5.0 / FOCAL_PX
    result = ransac_generalized_pose(v, f, M, threshold, final_solver=refine_from_minimal_test_double)
    np.testing.assert_array_equal(result.inliers, ~outliers)
    assert result.n_inliers == (~outliers).sum()
    assert mahalanobis(result.final, R, t) < 5.0  # chi2(6 dof) = 25 is far in the tail
    assert rotation_error(result.R, R) < 1e-4  # 20 arcsec; 1 px = 22 microrad = 4.6 arcsec
    centre, centre_true = -result.R.T @ result.t, -R.T @ t
    assert np.linalg.norm(centre - centre_true) < 0.05
    assert result.n_iterations < 200



def test_ransac_keeps_its_pose_when_a_later_round_has_none():
    """The final solver raising PoseError on a re-selected set (the global solver does when no pose
    puts most points in front) ends the re-selection with the set it had, instead of failing."""
    rng = np.random.default_rng(31)
    v, f, M, R, t, outliers = dmais_scene(rng, dmais_rig(), per_camera=30, noise_px=1.0, outlier_ratio=0.4)
    calls = []

    def fails_after_the_first(origins, directions, points):
        calls.append(len(points))
        if len(calls) > 1:
            raise PoseError("no pose puts most points in front")
        return refine_from_minimal_test_double(origins, directions, points)

    # a threshold of 2 noise sigmas leaves true points just outside it: the widened set differs
    result = ransac_generalized_pose(v, f, M, 2.0 / FOCAL_PX, final_solver=fails_after_the_first)
    assert len(calls) >= 2  # the test reached a second round
    assert rotation_error(result.R, R) < 1e-4
    assert result.final is not None and result.n_inliers == int(result.inliers.sum())

    def fails_at_once(origins, directions, points):
        raise PoseError("no pose puts most points in front")

    with pytest.raises(PoseError, match="most points in front"):
        ransac_generalized_pose(v, f, M, 5.0 / FOCAL_PX, final_solver=fails_at_once)

def test_ransac_generic_rig_with_40_percent_outliers():
    rng = np.random.default_rng(32)
    v, f, M, R, t = generalized_scene(rng, n=100, n_cameras=4, depth=(4.0, 20.0))
    f = perturb(rng, f, 1e-3)  # "1 px" at f = 1000 px
    outliers = rng.random(len(M)) < 0.4
    M[outliers] = rng.uniform(-15, 15, (outliers.sum(), 3))
    result = ransac_generalized_pose(v, f, M, 5e-3, final_solver=refine_from_minimal_test_double)
    np.testing.assert_array_equal(result.inliers, ~outliers)
    assert pose_error(result.R, result.t, R, t) < 2e-3
    assert isinstance(result.final.covariance, np.ndarray)  # the final solver's own result


def test_ransac_agrees_with_pycolmap():
    rng = np.random.default_rng(33)
    v, f, M, R, t, outliers = dmais_scene(rng, dmais_rig(), per_camera=20, noise_px=1.0, outlier_ratio=0.3)
    threshold = 5.0 / FOCAL_PX
    ours = ransac_generalized_pose(v, f, M, threshold, final_solver=refine_from_minimal_test_double)
    points2D, camera_idxs, cams_from_rig, cameras = colmap_rays(v, f)
    options = pycolmap.RANSACOptions()
    options.max_error = threshold
    options.random_seed = 0
    result = pycolmap.estimate_generalized_absolute_pose(points2D, M, camera_idxs, cams_from_rig, cameras,
                                                         options)
    np.testing.assert_array_equal(result["inlier_mask"], ours.inliers)
    # pycolmap's built-in refinement stops early (gradient_tolerance = 1); finish it tightly.
    refinement = pycolmap.AbsolutePoseRefinementOptions()
    refinement.gradient_tolerance = 1e-20
    refined = pycolmap.refine_generalized_absolute_pose(
        result["rig_from_world"], points2D, M, result["inlier_mask"], camera_idxs, cams_from_rig, cameras,
        refinement)
    R_colmap = refined["rig_from_world"].rotation.matrix()
    t_colmap = np.asarray(refined["rig_from_world"].translation)
    assert mahalanobis(ours.final, R_colmap, t_colmap) < 0.05  # ceres stops a little early here
    assert mahalanobis(ours.final, R, t) < 5.0


def test_ransac_rejects_points_behind_the_rays():
    """Points mirrored through their ray's origin lie on the ray's line (zero tangent residual)
    but at negative depth alpha: they are outliers."""
    rng = np.random.default_rng(34)
    v, f, M, R, t = generalized_scene(rng, n=40)
    behind = np.zeros(len(M), bool)
    behind[::4] = True
    p = M[behind] @ R.T + t - v[behind]
    M[behind] = (v[behind] - p - t) @ R
    assert np.all(np.isinf(ray_errors(v, f, M, R, t)[behind]))
    result = ransac_generalized_pose(v, f, M, 1e-6, final_solver=refine_from_minimal_test_double)
    np.testing.assert_array_equal(result.inliers, ~behind)


def test_ransac_errors():
    rng = np.random.default_rng(35)
    v, f, M, _, _ = generalized_scene(rng, n=60)
    M_random = rng.uniform(-10, 10, M.shape)
    with pytest.raises(PoseError, match="outliers only"):
        ransac_generalized_pose(v, f, M_random, 1e-4, final_solver=refine_from_minimal_test_double,
                                max_iterations=300)
    with pytest.raises(PoseError, match="at least min_inliers"):
        ransac_generalized_pose(v[:5], f[:5], M[:5], 1e-4, final_solver=refine_from_minimal_test_double)
    with pytest.raises(PoseError, match="threshold"):
        ransac_generalized_pose(v, f, M, 0.0, final_solver=refine_from_minimal_test_double)
    with pytest.raises(PoseError, match="without R and t"):
        ransac_generalized_pose(v, f, M, 1e-6, final_solver=lambda *args: object())


def test_cramer_rao_bound_matches_monte_carlo_errors():
    rng = np.random.default_rng(31)
    v, f, M, R, t = paper_rig_scene(rng, points_per_camera=8)
    sigma = 4.0 / 45000.0  # 4 px per component at f = 45000 px
    bound_pos, bound_ang = cramer_rao_bound(v, f, M, R, t, sigma)
    bases = tangent_bases(f)
    centre = -R.T @ t
    pos, ang = [], []
    for _ in range(400):
        noisy = f + sigma * np.einsum("nij,ni->nj", bases, rng.normal(size=(len(f), 2)))
        fit = refine_pose(v, noisy, M, R, t)
        pos.append(np.sum((-fit.R.T @ fit.t - centre) ** 2))
        ang.append(rotation_error(fit.R, R) ** 2)
    # the least-squares estimate is efficient here: its RMS errors sit on the bound (400 trials: +-7%)
    assert 0.85 < np.sqrt(np.mean(pos)) / bound_pos < 1.15
    assert 0.85 < np.sqrt(np.mean(ang)) / bound_ang < 1.15
    assert 0.01 < bound_pos < 1.0 and np.rad2deg(bound_ang) * 60 < 5  # DMAIS scale: cm and arc-minutes
    with pytest.raises(PoseError, match="sigma"):
        cramer_rao_bound(v, f, M, R, t, 0.0)
