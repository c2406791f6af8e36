"""The error model behind poses.csv's sigmas (pose/error_model.py): its propagation against a slow
dense reference, its variance-component estimation on residuals drawn from known components, and
what it refuses to estimate.

The scenes: the paper's rig (test_pose_uncertainty.paper_rig) over 3 groups of 8 hovering frames,
each group seeing the same 8 ground points per camera in every frame (as a hovering flight does).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from dmais_pipe.camera import Camera
from dmais_pipe.geometry import Rigid3, exp_so3
from dmais_pipe.pose import error_model as em
from dmais_pipe.pose.uncertainty import pose_uncertainty
from dmais_pipe.rig import Rig

from pose_scenes import dmais_scene
from test_pose_uncertainty import paper_rig

GROUPS, FRAMES, POINTS = 3, 8, 8
TRUE = {"pixel": 0.3, "survey": 0.02, "survey_vertical": 0.035, "jitter": 0.3, "mounting": 0.2, "focal": 150.0}


def hover_geometry(seed: int, cameras=range(5), object_space: bool = True, relief: float = 10.0) -> em.Geometry:
    """The Geometry at the true poses of GROUPS x FRAMES frames (residuals zero), the ground points
    within +-relief m of the ground plane."""
    rng = np.random.default_rng(seed)
    rig = paper_rig()
    names = [rig.camera_names[k] for k in cameras]
    rows = {k: [] for k in ("cameras", "uv", "points", "frame", "ids")}
    R_all, t_all, groups = [], [], []
    for g in range(GROUPS):
        _, _, points, R0, t0 = dmais_scene(rng, points_per_camera=POINTS, cameras=cameras, relief=relief)
        for f in range(FRAMES):
            R = exp_so3(rng.normal(0, 1e-4, 3)) @ R0  # a few pixels: every point stays in its image
            t = -R @ (-R0.T @ t0 + rng.normal(0, 0.05, 3))
            pose = Rigid3(R, t)
            for c, name in enumerate(names):
                part = points[c * POINTS:(c + 1) * POINTS]
                rows["uv"].append(rig.project(name, pose, part))
                rows["cameras"] += [name] * POINTS
                rows["points"].append(part)
                rows["ids"] += [f"G{g}P{c}_{k}" for k in range(POINTS)]
            rows["frame"] += [len(R_all)] * (POINTS * len(names))
            R_all.append(R), t_all.append(t), groups.append(f"g{g}")
    cameras_, uv, points = np.array(rows["cameras"]), np.vstack(rows["uv"]), np.vstack(rows["points"])
    assert np.isfinite(uv).all()
    origins, directions = rig.rays_of(cameras_, uv)
    # the cameras' focal lengths share an error (as cameras calibrated on one field do)
    sigma = np.tile([5.0, 5.0, 8.0, 8.0, 0.03, 3e-5, 3e-5, 5e-5, 0.01, 0.01, 0.02], 5)
    common = np.zeros(55)
    common[0::11], common[1::11] = 4.0, 4.0
    covariance = np.diag(sigma**2) + np.outer(common, common)
    geometry = em.linearised_solve(rig, cameras_, uv, origins, directions, points, np.array(rows["frame"]),
                               np.array(R_all), np.array(t_all), np.array(groups), np.array(rows["ids"]),
                               object_space, calibration_covariance=covariance)
    assert np.isfinite(geometry.A_inverse).all()
    return geometry


def model_of(sigmas: dict, calibration: float = 1.0) -> em.ErrorModel:
    sigma = {**dict.fromkeys(em.COMPONENTS, 0.0), **sigmas, "calibration": calibration}
    return em.ErrorModel(sigma, dict.fromkeys(em.COMPONENTS, "set"))


def dense_covariance(g: em.Geometry, frame: int, model: em.ErrorModel) -> np.ndarray:
    """The slow reference: frame's 6x6 covariance from the explicit 2n x 2n covariance of its errors."""
    rows = np.flatnonzero(g.frame == frame)
    K = g.A_inverse[frame] @ (g.J[rows] * g.weight[rows, None, None]).reshape(-1, 6).T
    return K @ dense_error_covariance(g, frame, model) @ K.T


def dense_error_covariance(g: em.Geometry, frame: int, model: em.ErrorModel) -> np.ndarray:
    """The explicit 2n x 2n covariance of the errors of frame's n observations, element by element."""
    rows = np.flatnonzero(g.frame == frame)
    n = len(rows)
    cov = np.zeros((2 * n, 2 * n))
    for a, i in enumerate(rows):
        for b, j in enumerate(rows):
            block = np.zeros((2, 2))
            if i == j:
                block += np.eye(2) * (model.si("pixel") / g.focal[i]) ** 2
                survey = np.diag([model.si("survey"), model.si("survey"), model.si("survey_vertical")]) ** 2
                block += g.survey[i] @ survey @ g.survey[i].T
            if g.camera[i] == g.camera[j]:
                if not g.reference[i]:
                    rotation = model.si("jitter") ** 2 + model.si("mounting") ** 2
                    block += g.rotation[i] @ g.rotation[j].T * rotation
                block += np.outer(g.focal_effect[i], g.focal_effect[j]) * model.si("focal") ** 2
            ci, cj = slice(11 * g.camera[i], 11 * g.camera[i] + 11), slice(11 * g.camera[j], 11 * g.camera[j] + 11)
            block += g.calibration[i] @ g.calibration_covariance[ci, cj] @ g.calibration[j].T * \
                model.si("calibration") ** 2
            cov[2 * a:2 * a + 2, 2 * b:2 * b + 2] = block
    return cov


@pytest.mark.parametrize("object_space", [True, False])
def test_propagation_matches_the_dense_reference(object_space):
    g = hover_geometry(1, object_space=object_space)
    model = model_of({k: v for k, v in TRUE.items()})
    parts = em.frame_covariances(g, model)
    assert set(parts) == set(em.COMPONENTS)
    total = sum(parts.values())
    for frame in (0, 9, 23):
        reference = dense_covariance(g, frame, model)
        np.testing.assert_allclose(total[frame], reference, rtol=1e-9, atol=1e-12 * np.abs(reference).max())


def test_propagation_matches_the_spread_of_drawn_errors_through_the_solve():
    """Each random component, drawn many times and put through the frames' linearised solve,
    spreads the poses as its propagated covariance says (Rademacher draws: the same second moments)."""
    g = hover_geometry(2)
    rng = np.random.default_rng(3)
    for name in ("pixel", "survey", "survey_vertical", "jitter", "focal"):
        model = model_of({name: TRUE[name]})
        predicted = em.frame_covariances(g, model)[name][:, [0, 1, 3]][:, :, [0, 1, 3]]
        steps = []
        for _ in range(1500):
            errors = em.unit_draw(g, name, rng) * model.si(name)
            right = np.add.reduceat(np.einsum("nkj,nk->nj", g.J * g.weight[:, None, None], errors), g.starts)
            steps.append(np.einsum("fij,fj->fi", g.A_inverse, right)[:, [0, 1, 3]])
        steps = np.array(steps)
        empirical = np.einsum("dfi,dfj->fij", steps, steps) / len(steps)
        ratio = np.diagonal(empirical, axis1=1, axis2=2) / np.diagonal(predicted, axis1=1, axis2=2)
        assert np.all(np.abs(ratio - 1) < 0.15), (name, ratio.min(), ratio.max())


def test_estimation_recovers_known_components_from_drawn_residuals():
    """Residuals drawn from the model with known sigmas: the estimates average to them."""
    g = hover_geometry(4)
    rng = np.random.default_rng(5)
    estimates, mounting_found = [], 0
    for draw in range(12):
        errors = sum(em.unit_draw(g, name, rng) * TRUE[name] * em._TO_SI[name] for name in TRUE)
        drawn = dataclasses.replace(g, residual=em.solve_response(g, errors))
        model = em.estimate(drawn, {"calibration": 0.0, "survey_vertical": TRUE["survey_vertical"]}, seed=draw)
        assert model.source["pixel"] == model.source["survey"] == "estimated"
        assert {model.source[name] for name in ("jitter", "mounting", "focal")} <= {"estimated", "not significant"}
        mounting_found += model.source["mounting"] == "estimated"
        estimates.append([model.sigma[name] ** 2 for name in TRUE])
    rms = dict(zip(TRUE, np.sqrt(np.mean(estimates, axis=0))))
    for name in ("pixel", "survey"):
        assert abs(rms[name] / TRUE[name] - 1) < 0.1, (name, rms[name])
    # a 150 ppm focal change moves the image edge by 0.3 px, under the 2.6 px survey errors: it is
    # not significant, and must not come out inflated
    assert rms["focal"] < 3 * TRUE["focal"]
    # the per-frame rotation total, what the sigmas use, is well determined; its split into jitter
    # and mounting (12 draws per group, 3 groups) less so, yet tested against mounting's absence
    # (error_model._null_error) a 0.2' mounting is found in most draws (under the fit with it, never)
    names = list(TRUE)
    rotation = np.sqrt(np.array(estimates)[:, names.index("jitter")] + np.array(estimates)[:, names.index("mounting")])
    assert abs(np.mean(rotation) / np.hypot(TRUE["jitter"], TRUE["mounting"]) - 1) < 0.15
    assert mounting_found >= 8


def test_zero_residuals_give_zero_components_and_the_set_ones_are_kept():
    g = hover_geometry(6)
    model = em.estimate(g, {"survey": 0.015, "calibration": 0.0})
    assert model.source["survey"] == "set" and model.sigma["survey"] == 0.015
    # survey set alone is that of all three axes
    assert model.source["survey_vertical"] == "set" and model.sigma["survey_vertical"] == 0.015
    model = em.estimate(g, {"survey": 0.015, "survey_vertical": 0.025, "calibration": 0.0})
    assert model.sigma["survey_vertical"] == 0.025
    assert all(model.sigma[name] == pytest.approx(0.0, abs=1e-9) for name in ("pixel", "jitter", "mounting", "focal"))


def test_a_reference_camera_alone_has_no_rotation_terms_and_its_focal_change_is_not_estimable():
    g = hover_geometry(7, cameras=[0])
    assert g.reference.all()
    model = em.estimate(g, {"calibration": 0.0})
    assert model.source["jitter"] == model.source["mounting"] == "not estimable"
    assert model.source["focal"] == "not estimable"  # a scale of a narrow image is a change of range
    parts = em.frame_covariances(g, model_of({"jitter": 1.0, "mounting": 1.0}))
    assert np.all(parts["jitter"] == 0) and np.all(parts["mounting"] == 0)


def test_the_survey_is_one_sigma_for_all_axes_unless_its_vertical_is_given():
    """Residuals of a survey 2 cm horizontal, 4 cm vertical: with the vertical given (a setting or
    every point's sigma_z_m) the horizontal comes out; without, one sigma for the three axes
    between the two."""
    g = hover_geometry(11)
    rng = np.random.default_rng(12)
    horizontal, vertical = [], []
    for draw in range(6):
        errors = em.unit_draw(g, "pixel", rng) * 0.3 + em.unit_draw(g, "survey", rng) * 0.02 + \
            em.unit_draw(g, "survey_vertical", rng) * 0.04
        drawn = dataclasses.replace(g, residual=em.solve_response(g, errors))
        tied = em.estimate(drawn, {"calibration": 0.0}, seed=draw)
        assert tied.source["survey_vertical"] == tied.source["survey"] == "estimated"
        assert tied.sigma["survey_vertical"] == tied.sigma["survey"]
        vertical.append(tied.sigma["survey"])
        given = em.estimate(drawn, {"calibration": 0.0, "survey_vertical": 0.04}, seed=draw)
        assert given.source["survey"] == "estimated" and given.source["survey_vertical"] == "set"
        per_point = dataclasses.replace(drawn, point_sigma=np.where([False, False, True], 0.04, np.nan) *
                                        np.ones((len(g.frame), 1)))
        from_points = em.estimate(per_point, {"calibration": 0.0}, seed=draw)
        assert abs(from_points.sigma["survey"] / given.sigma["survey"] - 1) < 0.1
        horizontal.append(given.sigma["survey"])
    assert abs(np.sqrt(np.mean(np.square(horizontal))) / 0.02 - 1) < 0.1
    assert 0.022 < np.sqrt(np.mean(np.square(vertical))) < 0.04


def test_a_mounting_under_the_calibrations_own_rotation_errors_is_not_ruled_out():
    """A group's 0.15' mounting and one draw of the calibration (whose camera rotations, 0.1-0.17',
    look like a mounting) in the residuals: the mounting is not significant, and the data cannot
    bound it below its prior, since the calibration's draw counts in the estimate's spread (with
    its expectation alone subtracted, the bound came out 0.002-0.014')."""
    g = hover_geometry(13)
    axes = em.calibration_errors(g)
    rng = np.random.default_rng(2)
    for draw in range(8):
        errors = em.unit_draw(g, "pixel", rng, gaussian=True) * 0.3 + sum(a * rng.normal() for a in axes) + \
            em.unit_draw(g, "mounting", rng, gaussian=True) * 0.15 * em.ARCMIN
        model = em.estimate(dataclasses.replace(g, residual=em.solve_response(g, errors)), seed=draw,
                            priors={"mounting": 0.15})
        assert model.sigma["mounting"] >= 0.15, (draw, model.sigma["mounting"], model.source["mounting"])


def test_too_few_observations_fall_back_to_the_calibrated_pixel_noise():
    g = hover_geometry(8)
    first = g.frame == 0
    rows = np.flatnonzero(first)[:4]
    small = dataclasses.replace(g, **{name: getattr(g, name)[rows] for name in (
        "J", "weight", "residual", "focal", "frame", "camera", "reference", "group", "point", "survey", "rotation",
        "focal_effect", "calibration", "point_sigma")}, starts=np.array([0]), A_inverse=g.A_inverse[:1])
    assert small.dof < em.MIN_DEGREES_OF_FREEDOM
    model = em.estimate(small, {"calibration": 0.0}, fallback_pixel_px=0.4)
    assert model.sigma["pixel"] == 0.4 and model.source["pixel"] == "calibration"
    assert model.source["survey"] == "not estimable"


def test_the_calibrated_pixel_noise_is_the_floor_of_the_estimated_one():
    """Residuals of camera rotations alone: the pixel noise estimate would be 0; the calibration's
    pixel noise stands in for it, the rotations as estimated."""
    g = hover_geometry(10)
    rng = np.random.default_rng(3)
    rotation = em.unit_draw(g, "jitter", rng, gaussian=True) * 0.5 * em.ARCMIN
    g = dataclasses.replace(g, residual=em.solve_response(g, rotation))
    free = em.estimate(g, {"calibration": 0.0})
    assert free.sigma["pixel"] < 0.05
    model = em.estimate(g, {"calibration": 0.0}, fallback_pixel_px=0.2)
    assert model.sigma["pixel"] == 0.2 and model.source["pixel"] == "calibration"
    assert model.source["jitter"] == "estimated" and model.sigma["jitter"] == free.sigma["jitter"]
    noisy = dataclasses.replace(g, residual=em.solve_response(
        g, rotation + em.unit_draw(g, "pixel", rng, gaussian=True) * 0.3))
    kept = em.estimate(noisy, {"calibration": 0.0}, fallback_pixel_px=0.2)  # above its floor: as estimated
    assert kept.source["pixel"] == "estimated" and abs(kept.sigma["pixel"] - 0.3) < 0.03


def test_sigmas_are_the_root_sum_of_the_components_shares():
    g = hover_geometry(9)
    rng = np.random.default_rng(1)
    R = np.array([exp_so3(rng.normal(0, 0.5, 3)) for _ in range(g.n_frames)])
    t = rng.normal(0, 100, (g.n_frames, 3))
    result = pose_uncertainty(g, model_of(TRUE), R, t)
    np.testing.assert_allclose(result.sigma_position ** 2, sum(result.variance_position.values()), rtol=1e-12)
    np.testing.assert_allclose(result.sigma_attitude ** 2, sum(result.variance_attitude.values()), rtol=1e-12)
    assert all((v >= 0).all() for v in result.variance_position.values())


def test_the_pose_stage_takes_the_calibrations_joint_covariance_from_rig_json():
    from dmais_pipe.stages.pose import calibration_covariance

    labels = ["C0.fx", "C0.cx", "C1.fx", "C1.rx", "C1.vz", "C9.fx"]
    matrix = np.diag([4.0, 9.0, 16.0, 1e-8, 1e-4, 1.0])
    matrix[0, 3] = matrix[3, 0] = 1e-4  # C0's focal and C1's rotation, as the rig adjustment couples them
    K = calibration_covariance({"calibration_covariance": {"parameters": labels, "matrix": matrix.tolist()}},
                               ["C0", "C1"])
    at = {label: 11 * int(label[1]) + em.CALIBRATION_PARAMETERS.index(label[3:]) for label in labels[:5]}
    for a, la in enumerate(labels[:5]):
        for b, lb in enumerate(labels[:5]):
            assert K[at[la], at[lb]] == matrix[a, b]
    assert np.count_nonzero(K) == 7  # a camera not in the rig (C9) is left out, the rest is 0
    assert not calibration_covariance({}, ["C0"]).any()
    bad = {"calibration_covariance": {"parameters": ["C0.fx"], "matrix": [["x"]]}}
    assert not calibration_covariance(bad, ["C0"]).any()


def test_a_prior_stands_in_for_a_component_the_residuals_cannot_tell():
    g = hover_geometry(10)
    rng = np.random.default_rng(11)
    errors = em.unit_draw(g, "pixel", rng) * 0.3  # pixel noise alone
    drawn = dataclasses.replace(g, residual=em.solve_response(g, errors))
    model = em.estimate(drawn, {"calibration": 0.0}, priors={"mounting": 0.15, "focal": 50.0})
    assert model.source["pixel"] == "estimated" and abs(model.sigma["pixel"] / 0.3 - 1) < 0.05
    # not significant here: the prior, bounded by what the data allows (estimate + 2 standard errors)
    assert model.source["mounting"] == model.source["focal"] == "prior"
    assert 0 < model.sigma["mounting"] <= 0.15 and 0 < model.sigma["focal"] <= 50.0
    assert model.sigma["jitter"] == 0.0 and model.source["jitter"] == "not significant"
    # a component set by the user is not replaced by its prior
    assert em.estimate(drawn, {"calibration": 0.0, "mounting": 0.0}, priors={"mounting": 0.15}).sigma["mounting"] == 0
    # the mounting prior enters the frames' covariance: wider sigmas than without it
    with_prior = em.frame_covariances(g, model)["mounting"]
    assert np.all(np.trace(with_prior[:, 3:, 3:], axis1=1, axis2=2) > 0)
    # not estimable (a single camera's focal change is a change of range): the prior whole
    alone = em.estimate(hover_geometry(7, cameras=[0]), {"calibration": 0.0}, priors={"focal": 50.0})
    assert (alone.sigma["focal"], alone.source["focal"]) == (50.0, "prior")


def test_an_opencv_cameras_lens_parameters_enter_the_calibration_term_as_their_rays_move():
    """With an opencv camera in the rig, C_i has columns for k2, p1, p2, k3 after the eleven: each
    is the change of the residuals when that coefficient moves (the rig's rays recomputed)."""
    rng = np.random.default_rng(30)
    paper = paper_rig()
    rig = Rig({n: Camera(c.fx, c.fy, c.cx, c.cy, c.d, c.width, c.height, "opencv", k2=50.0, p1=1e-3, p2=-1e-3)
               for n, c in paper.cameras.items()}, paper.cam_from_rig, paper.reference_camera)
    assert em.calibration_parameters(rig) == em.CALIBRATION_PARAMETERS + ("k2", "p1", "p2", "k3")
    assert em.calibration_parameters(paper) == em.CALIBRATION_PARAMETERS
    _, _, points, R, t = dmais_scene(rng, points_per_camera=POINTS)
    cameras = np.repeat(rig.camera_names, POINTS)
    uv = np.vstack([rig.project(name, Rigid3(R, t), points[c * POINTS:(c + 1) * POINTS])
                    for c, name in enumerate(rig.camera_names)])
    uv += rng.normal(0.0, 0.5, uv.shape)  # residuals not zero
    K = len(em.calibration_parameters(rig))
    covariance = np.diag(np.tile(np.r_[5.0, 5.0, 5.0, 5.0, 0.01, np.zeros(6), 10.0, 1e-4, 1e-4, 1e5], 5) ** 2)

    def geometry(r: Rig) -> em.Geometry:
        origins, directions = r.rays_of(cameras, uv)
        return em.linearised_solve(r, cameras, uv, origins, directions, points, np.zeros(len(uv), int), R[None],
                                   t[None], np.array(["g"]), np.arange(len(uv)).astype(str), True,
                                   calibration_covariance=covariance)

    base = geometry(rig)
    assert base.calibration.shape == (len(uv), 2, K)
    mine = cameras == "C2"
    def moved(name: str, step: float) -> Rig:
        camera = rig.cameras["C2"]
        return Rig({**rig.cameras, "C2": dataclasses.replace(camera, **{name: getattr(camera, name) + step})},
                   rig.cam_from_rig, rig.reference_camera)

    for name, step in (("k2", 1.0), ("p1", 1e-5), ("p2", 1e-5), ("k3", 1e4), ("d", 1e-3)):
        change = (geometry(moved(name, step)).residual - geometry(moved(name, -step)).residual) / (2 * step)
        column = base.calibration[:, :, em.calibration_parameters(rig).index(name)]
        assert np.abs(change[mine]).max() > 0
        np.testing.assert_allclose(column[mine], change[mine], rtol=1e-4, atol=1e-4 * np.abs(change[mine]).max())


def test_the_compiled_frame_sums_are_the_numpy_expressions_they_replace():
    """pose._error's loops against the numpy of error_model before them (einsum stacks summed by _sum_by),
    to the bit: each sum adds its rows in their order, each product its terms in einsum's order."""
    from dmais_pipe.pose._error import row_products, scaled_outer_sums

    rng = np.random.default_rng(3)
    n, n_keys = 5000, 300
    left = rng.normal(size=(n, 2, 6)) * 10.0 ** rng.uniform(-4, 4, (n, 1, 1))
    scale = rng.uniform(0.1, 2.0, n)
    for key in (np.sort(rng.integers(0, n_keys, n)), rng.integers(-1, n_keys, n)):  # a frame's rows; any order
        for width in (1, 2, 3, 6, 11):
            effect = rng.normal(size=(n, 2, width))
            K = np.einsum("nki,nkj->nij", left, effect)
            scaled = K * scale[:, None, None]  # sum over j of (K_ij scale) K_mj, in order
            outer = scaled[:, :, None, 0] * K[:, None, :, 0]
            for j in range(1, width):
                outer += scaled[:, :, None, j] * K[:, None, :, j]
            np.testing.assert_array_equal(row_products(left, effect, key, n_keys), em._sum_by(K, key, n_keys))
            np.testing.assert_array_equal(scaled_outer_sums(left, effect, scale, key, n_keys),
                                          em._sum_by(outer, key, n_keys))


def test_the_compiled_predicted_directions_are_numpys():
    """pose._error.predicted_directions (nonlinear.py's rays and residuals of moved poses) against the numpy
    expressions it replaces: to the last bits (1e-15; on numpy 2.4 bit for bit)."""
    from dmais_pipe.pose._error import predicted_directions

    rng = np.random.default_rng(4)
    n, n_frames = 3000, 70
    R, t = np.array([exp_so3(w) for w in rng.normal(size=(n_frames, 3))]), rng.normal(0, 100, (n_frames, 3))
    frame, points = np.sort(rng.integers(0, n_frames, n)), rng.normal(0, 300, (n, 3))
    origins = rng.normal(0, 0.1, (n, 3))
    bases = rng.normal(size=(n, 2, 3))
    p = np.einsum("nij,nj->ni", R[frame], points) + t[frame] - origins
    unit = p / np.linalg.norm(p, axis=1)[:, None]
    np.testing.assert_allclose(predicted_directions(R, t, frame, points, origins), unit, rtol=1e-15, atol=1e-15)
    np.testing.assert_allclose(predicted_directions(R, t, frame, points, origins, bases),
                               np.einsum("nij,nj->ni", bases, unit), rtol=1e-15, atol=1e-14)
