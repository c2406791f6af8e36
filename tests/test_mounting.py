"""pose.mounting: the group rig adjustment on seeded groups built with the simulator's rig, site and
markers, and a known mounting change per camera (drawn here, so that the truth is exact)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
import pandas as pd
import pytest
from scipy.optimize import least_squares

from dmais_pipe import cli
from dmais_pipe.errors import DmaisError
from dmais_pipe.geometry import Rigid3, exp_so3, rotation_error
from dmais_pipe.camera import Camera
from dmais_pipe.pose.error_model import calibration_parameters
from dmais_pipe.pose.mounting import RAD_PER_ARCMIN, TABLE_COLUMNS, adjust_group_rig, mounting_table
from dmais_pipe.pose.solver import solve_generalized_pose
from dmais_pipe.rig import Rig
from dmais_pipe.sim.config import DEFAULTS, merge
from dmais_pipe.sim.scene import build_rig, ground_markers_for, line_poses, nominal_rig_pose, visible_points

SITE = np.array([1500.0, -800.0, 45.0])


@dataclass(frozen=True)
class Group:
    """Observations of one simulated group (arguments of adjust_group_rig) and its truth."""

    rig: Rig
    cameras: np.ndarray
    uv: np.ndarray
    point_ids: np.ndarray
    points: np.ndarray
    frame_index: np.ndarray
    R: np.ndarray
    t: np.ndarray
    mount_arcmin: dict  # camera -> true delta (3,), arc-min
    true_R: np.ndarray
    true_t: np.ndarray

    def adjust(self, **noise):
        return adjust_group_rig(self.rig, self.cameras, self.uv, self.point_ids, self.points, self.frame_index, self.R,
                                self.t, **noise)


def make_group(seed: int, frames: int = 30, mount_arcmin: float = 0.0, vibration_arcmin: float = 0.3,
               survey_m: float = 0.025, pixel_px: float = 0.5, markers_per_camera: int = 8,
               pattern: str = "hover") -> Group:
    """A group over the simulator's site A (scene helpers), hovering or along a line (the
    simulator's flight patterns, markers placed for every frame), every non-reference camera turned
    by mount_arcmin per axis with seeded signs, each frame's cameras by N(0, vibration^2); the
    frames' poses from the project's solver with the calibrated rig."""
    config = merge(DEFAULTS, {"seed": seed, "flight": {"markers_per_camera": markers_per_camera,
                                                       "frames_per_group": frames}})
    rng = np.random.default_rng(seed)
    rig = build_rig(config["rig"])
    nominal = nominal_rig_pose(config, SITE, rng)
    nominals = [nominal] * frames if pattern == "hover" else line_poses(config, nominal)
    markers = []
    for pose in nominals[:1] if pattern == "hover" else nominals:
        markers += ground_markers_for(config, rig, pose, "A", SITE, rng, markers)
    true_points = {pid: xyz for m in markers for pid, xyz in zip(m.point_ids, m.board.corners())}
    surveyed = {pid: xyz + rng.normal(0.0, survey_m, 3) for pid, xyz in true_points.items()}
    tilted = [c for c in rig.camera_names if c != rig.reference_camera]
    mount = {c: mount_arcmin * rng.choice([-1.0, 1.0], 3) for c in tilted}
    rows, true_R, true_t, R, t = [], [], [], [], []
    for f in range(frames):
        world_from_nominal = nominals[f].inverse()
        rig_from_world = Rigid3(exp_so3(rng.normal(0.0, np.radians(0.2), 3)) @ world_from_nominal.R,
                                world_from_nominal.t + rng.normal(0.0, 1.0, 3)).inverse()
        frame_rows = []
        for name in rig.camera_names:
            turn = np.zeros(3) if name == rig.reference_camera else (
                mount[name] + rng.normal(0.0, vibration_arcmin, 3)) * RAD_PER_ARCMIN
            cam_from_world = Rigid3(exp_so3(turn), np.zeros(3)) * rig.cam_from_rig[name] * rig_from_world
            for pid, uv, _ in visible_points(rig.cameras[name], cam_from_world, markers, 20.0):
                frame_rows.append((name, uv + rng.normal(0.0, pixel_px, 2), pid, surveyed[pid], f))
        cameras = np.array([r[0] for r in frame_rows])
        uv, points = np.array([r[1] for r in frame_rows]), np.array([r[3] for r in frame_rows])
        origins, directions = rig.rays_of(cameras, uv)
        pose = solve_generalized_pose(origins, directions, points)
        rows += frame_rows
        true_R.append(rig_from_world.R), true_t.append(rig_from_world.t), R.append(pose.R), t.append(pose.t)
    return Group(rig, np.array([r[0] for r in rows]), np.array([r[1] for r in rows]), np.array([r[2] for r in rows]),
                 np.array([r[3] for r in rows]), np.array([r[4] for r in rows]), np.array(R), np.array(t),
                 {c: np.asarray(v) for c, v in mount.items()}, np.array(true_R), np.array(true_t))


def noise(survey_m=0.025, pixel_px=0.5, vibration_arcmin=0.3) -> dict:
    return {"pixel_sigma_px": pixel_px, "jitter_sigma_arcmin": vibration_arcmin, "survey_sigma_m": survey_m}


def centres(R, t) -> np.ndarray:
    """(F, 3) rig centres in the world of rig_from_world R (F, 3, 3), t (F, 3)."""
    return -np.einsum("fji,fj->fi", R, t)


def others(group: Group, result) -> list[int]:
    """Rows of result's non-reference cameras."""
    return [k for k, c in enumerate(result.cameras) if c != group.rig.reference_camera]


def errors_in_sigmas(group: Group, result) -> np.ndarray:
    """(K, 3) (estimate - truth) / sigma of the non-reference cameras."""
    names = list(result.cameras)
    return np.array([(result.delta_arcmin[names.index(c)] - truth) / result.sigma_arcmin[names.index(c)]
                     for c, truth in group.mount_arcmin.items()])


@pytest.fixture(scope="module")
def changed():
    group = make_group(11, mount_arcmin=2.0)
    return group, group.adjust(**noise())


@pytest.fixture(scope="module")
def unchanged():
    group = make_group(12, mount_arcmin=0.0)
    return group, group.adjust(**noise())


def test_a_mount_change_of_2_arcmin_is_found_within_3_sigma(changed):
    group, result = changed
    assert np.all(np.abs(errors_in_sigmas(group, result)) < 3.0)


def test_no_change_gives_deltas_within_3_sigma_of_zero(unchanged):
    group, result = unchanged
    assert np.all(np.abs(errors_in_sigmas(group, result)) < 3.0)
    assert not result.significant.any()


def test_sigma_with_a_2_5_cm_survey_is_the_bound_of_the_geometry(changed, unchanged):
    """30 frames, 0.5 px, 0.3' jitter, 2.5 cm survey: the Fisher bound of the module docstring,
    ~1.6', 2.1', 3.3' about x, y, z, is what is reported (not the issue's hoped-for 0.5'): the 8
    points per camera and their survey errors are common to every frame, and the reference camera's
    narrow view pins the cameras' common turns only weakly. A 2' change is then not flagged."""
    for group, result in (changed, unchanged):
        sigma = result.sigma_arcmin[others(group, result)]
        assert np.all((sigma > [1.2, 1.7, 2.7]) & (sigma < [2.0, 2.6, 4.0]))


def test_a_precise_survey_gives_sigma_under_half_an_arcmin_and_flags_2_arcmin():
    group = make_group(13, mount_arcmin=2.0, survey_m=0.002)
    result = group.adjust(**noise(survey_m=0.002))
    assert np.all(result.sigma_arcmin[others(group, result)] <= 0.5)
    assert np.all(np.abs(errors_in_sigmas(group, result)) < 3.0)
    assert result.significant[others(group, result)].all()


def test_a_rig_centre_prior_pins_the_outward_tilt_and_flags_2_arcmin(changed):
    """A POS-like prior (2 cm) on the rig centres: rx (the tilt, traded against the rig's height)
    drops to ~0.13'; the frames' positions come to the prior's level."""
    group, without = changed
    true = centres(group.true_R, group.true_t)
    prior = true + np.random.default_rng(0).normal(0.0, 0.02, true.shape)
    result = group.adjust(**noise(), center_prior_m=prior, center_sigma_m=0.02)
    chosen = others(group, result)
    assert np.all(result.sigma_arcmin[chosen, 0] < 0.2)
    assert np.all(result.sigma_arcmin[chosen, 1:] <= without.sigma_arcmin[chosen, 1:] + 1e-9)
    assert np.all(np.abs(errors_in_sigmas(group, result)) < 3.0)
    assert result.significant[chosen].all()
    error = np.linalg.norm(centres(result.R, result.t) - true, axis=1)
    assert np.sqrt(np.mean(error**2)) < 0.05


def test_reference_row_is_zero_and_the_rig_applies_the_deltas(changed):
    group, result = changed
    reference = result.cameras.index(group.rig.reference_camera)
    assert np.all(result.delta_arcmin[reference] == 0) and np.all(result.sigma_arcmin[reference] == 0)
    assert not result.significant[reference]
    for c, name in enumerate(result.cameras):
        turn = exp_so3(result.delta_arcmin[c] * RAD_PER_ARCMIN)
        np.testing.assert_allclose(result.rig.cam_from_rig[name].R, turn @ group.rig.cam_from_rig[name].R, atol=1e-12)
        np.testing.assert_allclose(result.rig.camera_center(name), group.rig.camera_center(name), atol=1e-12)
    table = mounting_table({"g1": result})
    assert list(table.columns) == TABLE_COLUMNS and len(table) == len(result.cameras)
    row = table[table["camera"] == group.rig.reference_camera].iloc[0]
    assert (row[TABLE_COLUMNS[2:8]] == 0).all() and not row["significant"]


def test_refined_poses_are_closer_to_the_truth_than_the_per_frame_solves(changed):
    group, result = changed
    true = centres(group.true_R, group.true_t)
    before = np.linalg.norm(centres(group.R, group.t) - true, axis=1)
    after = np.linalg.norm(centres(result.R, result.t) - true, axis=1)
    assert np.sqrt(np.mean(after**2)) < np.sqrt(np.mean(before**2))
    assert np.median(rotation_error(result.R, group.true_R)) < np.median(rotation_error(group.R, group.true_R))


def test_without_change_about_1_percent_is_flagged_and_chi2_is_honest():
    """Pooled over groups: the share flagged at SIGNIFICANCE and the mean chi2 (3 for honest sigmas)."""
    chi2 = []
    for seed in range(20, 26):
        group = make_group(seed, frames=6, mount_arcmin=0.0)
        result = group.adjust(**noise())
        chi2 += list(result.chi2[others(group, result)])
    assert 1.5 < np.mean(chi2) < 4.5
    assert np.mean(np.array(chi2) > 11.34) <= 2 / len(chi2)


@pytest.mark.parametrize("with_centres, frames", [(False, 3), (True, 3), (False, 4)])
def test_agrees_with_scipy_least_squares_on_the_same_whitened_residuals(with_centres, frames):
    """An independent dense reference: every unknown in one vector (poses as rotation vectors and
    centre moves from the starting ones), scipy's least_squares with central differences,
    covariance (J^T J)^-1; with and without the rig-centre prior. 20 points: with 3 frames (54
    frame unknowns) the adjustment eliminates the points, with 4 (72) the frames."""
    group = make_group(5, frames=frames, mount_arcmin=1.0, markers_per_camera=4)
    assert len(np.unique(group.point_ids)) == 20
    sigmas = {"pixel_sigma_px": 0.5, "jitter_sigma_arcmin": 0.3, "survey_sigma_m": 0.025, "prior_sigma_arcmin": 30.0}
    if with_centres:
        true = centres(group.true_R, group.true_t)
        sigmas |= {"center_prior_m": true + np.random.default_rng(1).normal(0.0, 0.02, true.shape),
                   "center_sigma_m": [0.02, 0.02, 0.03]}
    result = group.adjust(**sigmas)
    delta, sigma = reference_solution(group, **sigmas)
    chosen = others(group, result)
    np.testing.assert_allclose(result.delta_arcmin[chosen], delta, atol=1e-5 * np.max(sigma))
    np.testing.assert_allclose(result.sigma_arcmin[chosen], sigma, rtol=1e-4)


def reference_solution(group: Group, pixel_sigma_px, jitter_sigma_arcmin, survey_sigma_m, prior_sigma_arcmin,
                       center_prior_m=None, center_sigma_m=None, focal_sigma=()):
    """delta (K, 3) and sigma (K, 3) in arc-min of the model, written from its definition: every
    unknown an offset from its start (poses as a rotation vector and the rig centre's move); with
    focal_sigma (C,), each camera's relative focal change an unknown too (fx and fy scaled by 1 + it)
    with that prior sigma, and also its estimate and sigma (C,) in ppm."""
    rig = group.rig
    moving = [c for c in rig.camera_names if c != rig.reference_camera]
    ids, point = np.unique(group.point_ids, return_inverse=True)
    surveyed = np.array([group.points[np.flatnonzero(point == p)[0]] for p in range(len(ids))])
    F, K, P, C = len(group.R), len(moving), len(ids), len(focal_sigma)
    n = 6 * F + 3 * K + 3 * F * K + 3 * P
    jitter_rad, prior_rad = jitter_sigma_arcmin * RAD_PER_ARCMIN, prior_sigma_arcmin * RAD_PER_ARCMIN

    def unpack(x):
        omega, dc = x[:3 * F].reshape(F, 3), x[3 * F:6 * F].reshape(F, 3)
        delta = x[6 * F:6 * F + 3 * K].reshape(K, 3)
        jitter = x[6 * F + 3 * K:6 * F + 3 * K + 3 * F * K].reshape(F, K, 3)
        return omega, dc, delta, jitter, surveyed + x[6 * F + 3 * K + 3 * F * K:n].reshape(P, 3)

    def residuals(x):
        omega, dc, delta, jitter, points = unpack(x)
        focal = x[n:]
        R, centers = exp_so3(omega) @ group.R, start_centers + dc
        x_rig = np.einsum("nij,nj->ni", R[group.frame_index], points[point] - centers[group.frame_index])
        pixels = np.empty_like(group.uv)
        for name in rig.camera_names:
            rows = np.flatnonzero(group.cameras == name)
            turn = np.broadcast_to(np.eye(3), (len(rows), 3, 3))
            if name != rig.reference_camera:
                k = moving.index(name)
                turn = exp_so3(jitter[group.frame_index[rows], k]) @ exp_so3(delta[k])
            x_cam = np.einsum("nij,nj->ni", turn, rig.cam_from_rig[name].apply(x_rig[rows]))
            camera = rig.cameras[name]
            if C:
                scale = 1.0 + focal[rig.camera_names.index(name)]
                camera = replace(camera, fx=camera.fx * scale, fy=camera.fy * scale)
            pixels[rows] = camera.project(x_cam)
        centre_prior = [] if center_prior_m is None else [((centers - center_prior_m) / center_sigma_m).ravel()]
        return np.concatenate([((pixels - group.uv) / pixel_sigma_px).ravel(),
                               ((points - surveyed) / survey_sigma_m).ravel(), delta.ravel() / prior_rad,
                               jitter.ravel() / jitter_rad, *centre_prior, focal / np.asarray(focal_sigma)])

    start_centers = centres(group.R, group.t)
    x0 = np.zeros(n + C)
    solution = least_squares(residuals, x0, jac="3-point", x_scale="jac", method="lm", xtol=1e-15, ftol=1e-15,
                             gtol=1e-15)
    J = solution.jac  # at solution.x
    covariance = np.linalg.inv(J.T @ J)
    delta = unpack(solution.x)[2] / RAD_PER_ARCMIN
    sigma = np.sqrt(np.diag(covariance)[6 * F:6 * F + 3 * K]).reshape(K, 3) / RAD_PER_ARCMIN
    if not C:
        return delta, sigma
    return delta, sigma, solution.x[n:] * 1e6, np.sqrt(np.diag(covariance)[n:]) * 1e6


def focal_covariance(rig: Rig, sigma) -> np.ndarray:
    """(K C, K C) a calibration covariance of fx and fy alone, each camera's off together by its
    relative sigma (C,) (its focal change's prior in the adjustment); K = len(calibration_parameters)."""
    K = len(calibration_parameters(rig))
    covariance = np.zeros((K * len(rig.camera_names),) * 2)
    for c, name in enumerate(rig.camera_names):
        f = sigma[c] * np.array([rig.cameras[name].fx, rig.cameras[name].fy])
        covariance[K * c:K * c + 2, K * c:K * c + 2] = np.outer(f, f)
    return covariance


def with_opencv_lenses(group: Group) -> Group:
    """The group with every camera's model opencv (k1 = its d, the other coefficients 0): the same
    projection, with the opencv model's further parameters."""
    cameras = {name: Camera(c.fx, c.fy, c.cx, c.cy, c.d, c.width, c.height, "opencv")
               for name, c in group.rig.cameras.items()}
    return replace(group, rig=Rig(cameras, group.rig.cam_from_rig, group.rig.reference_camera))


def test_focal_changes_agree_with_scipy_least_squares():
    """Given a calibration covariance, each camera's focal change is an unknown with the
    calibration's relative sigma as its prior: the same solution and sigmas as the dense reference
    with that unknown written in (one camera's focal length held: its sigma 0)."""
    group = make_group(5, frames=3, mount_arcmin=1.0, markers_per_camera=4)
    focal_sigma = np.array([3e-4, 2e-4, 0.0, 4e-4, 2.5e-4])
    sigmas = {"pixel_sigma_px": 0.5, "jitter_sigma_arcmin": 0.3, "survey_sigma_m": 0.025, "prior_sigma_arcmin": 30.0}
    result = group.adjust(**sigmas, calibration_covariance=focal_covariance(group.rig, focal_sigma))
    held = focal_sigma == 0
    delta, sigma, focal, focal_sigma_ppm = reference_solution(group, **sigmas, focal_sigma=np.where(held, 1e-12,
                                                                                                     focal_sigma))
    chosen = others(group, result)
    np.testing.assert_allclose(result.delta_arcmin[chosen], delta, atol=1e-5 * np.max(sigma))
    np.testing.assert_allclose(result.sigma_arcmin[chosen], sigma, rtol=1e-4)
    np.testing.assert_allclose(result.focal_ppm[~held], focal[~held], atol=1e-4 * np.max(focal_sigma_ppm))
    np.testing.assert_allclose(result.sigma_focal_ppm[~held], focal_sigma_ppm[~held], rtol=1e-4)
    assert np.isnan(result.focal_ppm[held]).all() and np.isnan(result.sigma_focal_ppm[held]).all()
    for c, name in enumerate(result.cameras):
        scale = 1.0 + np.nan_to_num(result.focal_ppm[c]) * 1e-6
        assert result.rig.cameras[name].fx == pytest.approx(group.rig.cameras[name].fx * scale, rel=1e-12)
        assert result.rig.cameras[name].cx == group.rig.cameras[name].cx


def test_a_calibrated_focal_error_is_found_in_flight():
    """The calibrated rig's focal lengths off by 300-500 ppm (ten times its 0.5 px of 45,000 px) on a
    line of 30 frames (every frame new markers): each camera's focal change is found within 3
    sigma, its sigma below the calibration's, and the deltas stay within 3 sigma of the truth."""
    truth = make_group(31, frames=30, mount_arcmin=1.0, pattern="line")
    error = np.array([4e-4, -3e-4, 5e-4, 3e-4, -4e-4])
    cameras = {name: replace(camera, fx=camera.fx * (1 + e), fy=camera.fy * (1 + e))
               for e, (name, camera) in zip(error, truth.rig.cameras.items())}
    group = replace(truth, rig=Rig(cameras, dict(truth.rig.cam_from_rig), truth.rig.reference_camera))
    prior = np.full(5, 4e-4)
    result = group.adjust(**noise(), calibration_covariance=focal_covariance(group.rig, prior))
    true_change = (1.0 / (1.0 + error) - 1.0) * 1e6
    assert np.all(np.abs(result.focal_ppm - true_change) < 3 * result.sigma_focal_ppm)
    assert np.all(result.sigma_focal_ppm < prior * 1e6)
    assert np.all(np.abs(errors_in_sigmas(group, result)) < 3.0)


@pytest.mark.parametrize("changes, focal_held", [
    ([("C2", "cx", 2.0)], False), ([("C0", "cy", 2.0)], False), ([("C3", "fy", 20.0), ("C3", "fx", -20.0)], False),
    ([("C3", "fy", 20.0), ("C3", "fx", -20.0)], True), ([("C1", "d", 0.05)], False), ([("C2", "ry", 2e-4)], False),
    ([("C4", "vz", 0.05)], False), ([("C1", "vx", 0.03), ("C1", "vy", -0.03)], False),
    ([("C2", "cx", 2.0), ("C2", "ry", 2e-4), ("C0", "cx", -3.0), ("C1", "fx", 10.0), ("C1", "fy", -10.0)], False),
    ([("C1", "k2", 400.0)], "opencv"), ([("C2", "p1", 0.006), ("C2", "p2", -0.006)], "opencv"),
    ([("C3", "k3", 2e5), ("C3", "d", 0.05), ("C0", "p2", 0.006)], "opencv")])
def test_the_calibrations_share_is_what_re_adjusting_with_its_error_gives(changes, focal_held):
    """Calibration parameters off by their steps together: the deltas' change from adjusting again
    with the rig so changed (brute force) is the sigma the calibration's share gives with the
    covariance of that one joint error (v v^T, its signs included). A rotation error w (rad, about
    the rig's axes) of a calibrated camera turns its rig_from_cam by exp(w). Every focal length is an
    unknown with a 200 ppm prior (as the pose stage has it), so fx and fy move by opposite relative
    steps (the aspect, which stays in the share); with focal_held, the focal lengths are held (no
    prior) and the aspect's share is fx's and fy's. A camera centre's error (m, in the rig) moves
    its rays' origin. With "opencv", every camera has the opencv model (focal lengths free) and its
    further lens parameters (k2, p1, p2, k3) are in the share too."""
    group = make_group(7, frames=6, mount_arcmin=1.0)
    if focal_held == "opencv":
        group, focal_held = with_opencv_lenses(group), False
    rig = group.rig
    parameters = calibration_parameters(rig)
    K = len(parameters)
    focal = (lambda rig: np.zeros((K * 5, K * 5))) if focal_held else \
        (lambda rig: focal_covariance(rig, np.full(5, 2e-4)))
    base = group.adjust(**noise(), calibration_covariance=focal(rig))
    cameras, cam_from_rig, v = dict(rig.cameras), dict(rig.cam_from_rig), np.zeros(K * 5)
    for camera, parameter, step in changes:
        if parameter in ("fx", "fy"):  # relative steps: fx / fx0 - 1 = step / 45,000
            step *= getattr(rig.cameras[camera], parameter) / 45_000.0
        v[K * rig.camera_names.index(camera) + parameters.index(parameter)] = step
        if parameter in ("rx", "ry", "rz"):
            w = np.zeros(3)
            w["xyz".index(parameter[1])] = step
            cam_from_rig[camera] = (Rigid3(exp_so3(w), np.zeros(3)) * cam_from_rig[camera].inverse()).inverse()
        elif parameter in ("vx", "vy", "vz"):
            move = np.zeros(3)
            move["xyz".index(parameter[1])] = step
            R = cam_from_rig[camera].R
            cam_from_rig[camera] = Rigid3(R, cam_from_rig[camera].t - R @ move)
        else:
            cameras[camera] = replace(cameras[camera], **{parameter: getattr(cameras[camera], parameter) + step})
    changed = Rig(cameras, cam_from_rig, rig.reference_camera)
    moved = adjust_group_rig(changed, group.cameras, group.uv, group.point_ids, group.points, group.frame_index,
                             group.R, group.t, **noise(), calibration_covariance=focal(changed))
    shared = group.adjust(**noise(), calibration_covariance=focal(rig) + np.outer(v, v))
    assert np.isnan(shared.focal_ppm).all() == focal_held
    chosen = others(group, base)
    predicted = np.sqrt(np.diagonal(shared.covariance_arcmin2 - base.covariance_arcmin2, axis1=1, axis2=2))[chosen]
    brute = np.abs(moved.delta_arcmin - base.delta_arcmin)[chosen]
    assert brute.max() > 0.05  # the parameters matter
    np.testing.assert_allclose(predicted, brute, rtol=0.02, atol=5e-3 * brute.max())  # steps of ~0.5': second order


def test_a_camera_without_observations_gets_a_nan_row_with_a_warning(caplog):
    group = make_group(7, frames=4, mount_arcmin=2.0)
    kept = group.cameras != "C2"
    with caplog.at_level(logging.WARNING, logger="dmais_pipe.pose.mounting"):
        result = adjust_group_rig(group.rig, group.cameras[kept], group.uv[kept], group.point_ids[kept],
                                  group.points[kept], group.frame_index[kept], group.R, group.t, **noise())
    assert "C2" in caplog.text
    c2 = result.cameras.index("C2")
    assert np.isnan(result.delta_arcmin[c2]).all() and np.isnan(result.sigma_arcmin[c2]).all()
    assert not result.significant[c2]
    np.testing.assert_array_equal(result.rig.cam_from_rig["C2"].R, group.rig.cam_from_rig["C2"].R)
    assert np.isfinite(result.delta_arcmin[result.cameras.index("C1")]).all()


def test_one_frame_and_no_jitter_work_less_precisely():
    group = make_group(8, frames=30, mount_arcmin=2.0)
    one = group.frame_index == 0
    single = adjust_group_rig(group.rig, group.cameras[one], group.uv[one], group.point_ids[one], group.points[one],
                              group.frame_index[one], group.R[:1], group.t[:1], **noise())
    full = group.adjust(**noise())
    assert single.n_frames == 1 and full.n_frames == 30
    chosen = others(group, full)
    assert np.all(single.sigma_arcmin[chosen] > full.sigma_arcmin[chosen])
    assert np.all(np.abs(errors_in_sigmas(group, single)) < 3.0)
    still = make_group(9, frames=10, mount_arcmin=2.0, vibration_arcmin=0.0)
    assert np.all(np.abs(errors_in_sigmas(still, still.adjust(**noise(vibration_arcmin=0.0)))) < 3.0)


def test_pixel_sigma_per_camera_is_used():
    group = make_group(10, frames=5)
    same = group.adjust(**noise())
    per_camera = group.adjust(**{**noise(), "pixel_sigma_px": dict.fromkeys(group.rig.camera_names, 0.5)})
    np.testing.assert_allclose(per_camera.delta_arcmin, same.delta_arcmin, atol=1e-9)
    worse = group.adjust(**{**noise(), "pixel_sigma_px": {**dict.fromkeys(group.rig.camera_names, 0.5), "C3": 5.0}})
    c3 = worse.cameras.index("C3")
    assert np.all(worse.sigma_arcmin[c3] > same.sigma_arcmin[c3])


@pytest.mark.parametrize("change, message", [
    (lambda g: {"frame_index": g.frame_index + 100}, "frame indices"),
    (lambda g: {"cameras": np.where(g.cameras == "C1", "C9", g.cameras)}, "C9"),
    (lambda g: {"uv": g.uv[:-1]}, "one of each per observation"),
    (lambda g: {"pixel_sigma_px": {"C0": 0.5}}, "no pixel sigma"),
    (lambda g: {"survey_sigma_m": 0.0}, "survey sigma"),
    (lambda g: {"jitter_sigma_arcmin": -1.0}, "jitter_sigma_arcmin"),
    (lambda g: {"R": np.full_like(g.R, np.nan)}, "not finite"),
    (lambda g: {"cameras": g.cameras[:0], "uv": g.uv[:0], "point_ids": g.point_ids[:0], "points": g.points[:0],
                "frame_index": g.frame_index[:0]}, "without observations"),
])
def test_degenerate_input_is_refused(change, message):
    group = make_group(3, frames=2)
    arguments = {"rig": group.rig, "cameras": group.cameras, "uv": group.uv, "point_ids": group.point_ids,
                 "points": group.points, "frame_index": group.frame_index, "R": group.R, "t": group.t, **noise()}
    with pytest.raises(DmaisError, match=message):
        adjust_group_rig(**{**arguments, **change(group)})


def test_a_frame_with_fewer_than_3_observations_is_refused():
    group = make_group(4, frames=2)
    rows = np.flatnonzero(group.frame_index == 0)[:2].tolist() + np.flatnonzero(group.frame_index == 1).tolist()
    with pytest.raises(DmaisError, match="fewer than 3"):
        adjust_group_rig(group.rig, group.cameras[rows], group.uv[rows], group.point_ids[rows], group.points[rows],
                         group.frame_index[rows], group.R, group.t, **noise())


def test_bench_runs_one_small_simulation_and_writes_its_tables(tmp_path):
    from dmais_pipe.bench.mounting import TABLE_COLUMNS as BENCH_COLUMNS, bench_mounting, simulations

    csv = tmp_path / "mounting.csv"
    table = bench_mounting(csv, simulations(seeds=[3], mounts=[2.0], groups=1, frames_per_group=4), pos=True)
    assert list(table.columns) == BENCH_COLUMNS
    assert set(table["variant"]) == {"survey", "survey+pos"} and set(table["seed"]) == {"3", "pooled"}
    assert (table["n"] == 4).all() and (table["within_3sigma"] > 0.5).all()
    assert (table["pos_true_m"] < table["pos_calibrated_m"]).all()
    cameras = pd.read_csv(tmp_path / "mounting_cameras.csv")
    assert set(TABLE_COLUMNS) <= set(cameras.columns) and len(cameras) == 2 * 5
    assert len(pd.read_csv(tmp_path / "mounting_frames.csv")) == 2 * 4


def test_bench_simulations_take_the_flight_pattern():
    """--pattern: a line simulation asks the simulator for it and is named so; a hover one is the
    simulation it was before patterns existed (same name, no pattern setting)."""
    from dmais_pipe.bench.mounting import simulations

    hover, line = simulations(seeds=[3], mounts=[2.0], patterns=["hover", "line"])
    assert (hover.pattern, line.pattern) == ("hover", "line")
    assert hover.name == "vib0.3-mount2-survey0.025-px0.5-4x30-seed3-truthrig"
    assert "pattern" not in hover.config()["flight"]
    assert line.name == "vib0.3-mount2-survey0.025-px0.5-4x30-line-seed3-truthrig"
    assert line.config()["flight"]["pattern"] == "line"
    parser = cli._parser()
    assert parser.parse_args(["bench", "mounting", "--pattern", "hover,line"]).pattern == ["hover", "line"]
    assert parser.parse_args(["bench", "mounting"]).pattern == ["hover"]
    with pytest.raises(SystemExit):
        parser.parse_args(["bench", "mounting", "--pattern", "zigzag"])


def test_bench_runs_a_line_flight(tmp_path):
    from dmais_pipe.bench.mounting import bench_mounting, simulations

    chosen = simulations(seeds=[3], mounts=[2.0], groups=1, frames_per_group=4, patterns=["line"])
    table = bench_mounting(tmp_path / "mounting.csv", chosen, work=tmp_path / "work")
    assert set(table["pattern"]) == {"line"} and (table["n"] == 4).all()
    truth = pd.read_csv(tmp_path / "work" / chosen[0].name / "dataset" / "truth" / "frames.csv")
    steps = np.linalg.norm(np.diff(truth[["x", "y"]].to_numpy(), axis=0), axis=1)
    assert np.all(np.abs(steps - DEFAULTS["flight"]["line_spacing_m"]) < 5.0)


def test_the_compiled_model_and_jacobians_equal_numpys():
    """mounting's compiled loops (_group: the points in the cameras, the radial1 projection, the compact
    Jacobians, the normal equations with them formed in the loop) against the numpy formulas they replace,
    away from zero (turned cameras, jitters, focal changes)."""
    from dmais_pipe.pose import group_normal, mounting

    group = make_group(5, frames=3, mount_arcmin=1.0, markers_per_camera=4)
    problem = mounting._problem(group.rig, group.cameras, group.uv, group.point_ids, group.points, group.frame_index,
                                group.R, 0.5, 0.3, 0.025, 30.0, None, None,
                                focal_covariance(group.rig, np.array([3e-4, 2e-4, 0.0, 4e-4, 2.5e-4])))
    rng = np.random.default_rng(1)
    K, F = len(problem.free), problem.n_frames
    state = mounting._State(group.R.copy(), group.t + group.R @ problem.origin, rng.normal(0, 1e-3, (K, 3)),
                            rng.normal(0, 1e-4, (F, K, 3)), rng.normal(0, 1e-4, len(problem.focal_prior)),
                            problem.surveyed + rng.normal(0, 0.01, problem.surveyed.shape))
    forward = mounting._forward(problem, state)
    x_rig = np.einsum("nij,nj->ni", state.R[problem.frame], state.points[problem.point]) + state.t[problem.frame]
    for n, (f, c, slot) in enumerate(zip(problem.frame, problem.camera, problem.slot)):
        name = problem.names[c]
        turn = exp_so3(state.jitter[f, slot]) @ exp_so3(state.delta[slot]) if slot >= 0 else np.eye(3)
        calibrated = group.rig.cam_from_rig[name]
        np.testing.assert_allclose(forward.x[n], turn @ (calibrated.R @ x_rig[n] + calibrated.t), rtol=1e-12)
    centre = np.einsum("fij,fj->fi", state.R, problem.centroid) + state.t
    np.testing.assert_allclose(forward.q, x_rig - centre[problem.frame], rtol=1e-12, atol=1e-9)
    for compiled, reference in zip(mounting._jacobians(problem, state, forward),
                                   mounting._jacobians_numpy(problem, state, forward)):
        np.testing.assert_allclose(compiled, reference, rtol=1e-12, atol=1e-12 * np.abs(reference).max())
    assert {camera.model for camera in group.rig.cameras.values()} == {"radial1"}
    for compiled, reference in zip(mounting._radial1_residuals(problem, state, forward.x, True),
                                   mounting._projected_residuals(problem, state, forward.x, True)):
        np.testing.assert_allclose(compiled, reference, rtol=1e-12, atol=1e-12 * np.abs(reference).max())
    np.testing.assert_array_equal(mounting._forward(problem, state, jacobians=False).e, forward.e)
    fused = mounting._normal_equations(problem, state, forward)  # the Jacobians formed and added in one loop
    for jacobians, exact in ((mounting._jacobians(problem, state, forward), True),
                             (mounting._jacobians_numpy(problem, state, forward), False)):
        local_J, _, global_J, _ = jacobians
        normal = group_normal.assemble(problem.structure, local_J, global_J[:, :, :-3], global_J[:, :, -3:], forward.e)
        mounting._add_priors(problem, state, normal)
        for block, reference in zip(fused.blocks(), normal.blocks()):
            if exact:
                np.testing.assert_array_equal(block, reference)
            else:
                np.testing.assert_allclose(block, reference, rtol=1e-12, atol=1e-12 * np.abs(reference).max())
