"""The error model's compiled passes over the observations (pose/_error.pyx: linearised_rows,
calibration_columns, covariance_sums, block_outer_sums, curvature_sums, noise_rows, frame_points) and the
pose stage's shortcuts around them, against the numpy they replaced, to the bit: the same numbers, the
same NaN and the same sign of every zero (the pose stage's tables are written from them).

The references below are the numpy of error_model.py, nonlinear.py, refine.py and flight.py before the
passes were compiled.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from dmais_pipe.camera import Camera
from dmais_pipe.geometry import Rigid3, exp_so3
from dmais_pipe.pose import _error, flight, nonlinear, refine
from dmais_pipe.pose import error_model as em
from dmais_pipe.rig import Rig

from pose_scenes import dmais_scene
from test_pose_uncertainty import paper_rig

FRAMES, POINTS = 12, 6


def assert_bits(actual, expected) -> None:
    """actual is expected to the bit (NaN where NaN; zeros of the same sign)."""
    actual, expected = np.asarray(actual), np.asarray(expected)
    assert actual.shape == expected.shape and actual.dtype == expected.dtype
    np.testing.assert_array_equal(actual, expected)
    zero = actual == 0
    assert np.array_equal(np.signbit(actual[zero]), np.signbit(expected[zero]))


def distorted_rig(model: str = "radial1") -> Rig:
    """The paper's rig with radial distortion (and, for opencv, the further lens terms)."""
    paper = paper_rig()
    extra = {"k2": 50.0, "p1": 1e-3, "p2": -1e-3, "k3": 20.0} if model == "opencv" else {}
    cameras = {n: Camera(c.fx, c.fy, c.cx, c.cy, -8.0 + k, c.width, c.height, model, **extra)
               for k, (n, c) in enumerate(paper.cameras.items())}
    return Rig(cameras, paper.cam_from_rig, paper.reference_camera)


def flight_rows(seed: int, rig: Rig, cameras=range(5)) -> dict:
    """linearised_solve's arguments for FRAMES frames of `rig` over ground points, pixel noise 0.5 px, one
    camera missing from every third frame."""
    rng = np.random.default_rng(seed)
    names = [rig.camera_names[k] for k in cameras]
    rows = {k: [] for k in ("cameras", "uv", "points", "frame", "ids")}
    R_all, t_all = [], []
    for f in range(FRAMES):
        _, _, points, R, t = dmais_scene(rng, points_per_camera=POINTS, cameras=cameras)
        for c, name in enumerate(names):
            if f % 3 == 2 and c == len(names) - 1 and len(names) > 1:
                continue
            part = points[c * POINTS:(c + 1) * POINTS]
            rows["uv"].append(rig.project(name, Rigid3(R, t), part) + rng.normal(0.0, 0.5, (POINTS, 2)))
            rows["cameras"] += [name] * POINTS
            rows["points"].append(part)
            rows["ids"] += [f"P{rng.integers(0, 40)}" for _ in range(POINTS)]
            rows["frame"] += [f] * POINTS
        R_all.append(R), t_all.append(t)
    cameras_, uv = np.array(rows["cameras"]), np.vstack(rows["uv"])
    origins, directions = rig.rays_of(cameras_, uv)
    K = len(em.calibration_parameters(rig))
    sigma = np.tile(np.r_[5.0, 5.0, 8.0, 8.0, 0.03, 3e-5, 3e-5, 5e-5, 0.01, 0.01, 0.02, np.full(K - 11, 0.1)], 5)
    sigma[2 * K:3 * K] = 0.0  # a camera without calibration variance
    sigma[K + 2] = 0.0  # a parameter without
    return dict(rig=rig, cameras=cameras_, uv=uv, origins=origins, directions=directions,
                points=np.vstack(rows["points"]), frame_index=np.array(rows["frame"]), R=np.array(R_all),
                t=np.array(t_all), groups=np.array(["g1"] * (FRAMES // 2) + ["g2"] * (FRAMES - FRAMES // 2)),
                point_ids=np.array(rows["ids"]), object_space=True, calibration_covariance=np.diag(sigma**2))


def geometry_of(rows: dict, **changes) -> em.Geometry:
    return em.linearised_solve(**{**rows, **changes})


def model_of(**sigmas) -> em.ErrorModel:
    sigma = {"pixel": 0.3, "survey": 0.02, "survey_vertical": 0.035, "jitter": 0.3, "mounting": 0.2, "focal": 150.0,
             "calibration": 1.0, **sigmas}
    return em.ErrorModel(sigma, dict.fromkeys(em.COMPONENTS, "set"))


# ------------------------------------------------------------------------------ the numpy references

def numpy_rows(origins, directions, points, centroid, R, t, t_centred, frame, axes, camera):
    """linearised_solve's per-observation numpy (error_model.py before _error.linearised_rows)."""
    R_rows = R[frame]
    unit = directions / np.linalg.norm(directions, axis=1)[:, None]
    bases = refine.tangent_bases(unit)
    points_centred = points - centroid[frame]
    residual, J = refine._jacobian(origins, bases, points_centred, R_rows, t_centred[frame])
    p = np.einsum("nij,nj->ni", R_rows, points) + t[frame] - origins
    squares = np.sum(p * p, axis=1)
    residual = residual.reshape(-1, 2)
    norm = np.linalg.norm(p, axis=1)
    dr_dp = (bases - residual[:, :, None] * (p / norm[:, None])[:, None, :]) / norm[:, None, None]
    axis = axes[camera]
    focal_effect = -np.einsum("ni,ni->n", unit, axis)[:, None] * np.einsum("nki,ni->nk", bases, axis)
    rotation = np.cross(bases, unit[:, None, :])
    return unit, bases, residual, J.reshape(-1, 2, 6), squares, dr_dp, rotation, focal_effect, points_centred


def numpy_calibration_effects(rig, names, camera_of, uv, bases, rotation, dr_dp, variances):
    """error_model._calibration_effects before _error.calibration_columns."""
    parameters = em.calibration_parameters(rig)
    k_all = len(parameters)
    effects = np.zeros((len(uv), 2, k_all))
    for c, name in enumerate(names):
        rows = np.flatnonzero(camera_of == c)
        sigma = np.sqrt(np.clip(variances[k_all * c:k_all * (c + 1)], 0.0, None))
        if not len(rows) or not sigma.any():
            continue
        camera, block = rig.cameras[name], np.zeros((len(rows), 2, k_all))
        own = {k: k if k < 5 else camera.parameter_names.index(parameters[k]) for k in range(k_all)
               if (k < 5 or parameters[k] in em.LENS_PARAMETERS) and sigma[k] > 0}
        if own:
            change = em._ray_changes(camera, rig.cam_from_rig[name].R.T, uv[rows])
            block[:, :, list(own)] = -np.einsum("nki,nip->nkp", bases[rows], change[:, :, list(own.values())])
        block[:, :, 5:8] = rotation[rows]
        block[:, :, 8:11] = -dr_dp[rows]
        effects[rows] = block
    return effects


def numpy_frame_covariances(g: em.Geometry, model: em.ErrorModel) -> dict:
    """error_model.frame_covariances before _error.covariance_sums and block_outer_sums."""
    n_frames = g.n_frames
    weighted = g.J * g.weight[:, None, None]
    n_cameras = int(g.camera.max()) + 1
    frame_camera = np.unique(g.frame * n_cameras + g.camera, return_inverse=True)[1]
    block_frame = np.zeros(int(frame_camera.max()) + 1, int)
    block_frame[frame_camera] = g.frame
    block_camera = np.zeros_like(block_frame)
    block_camera[frame_camera] = g.camera
    k_all = g.calibration.shape[2]

    def per_observation(effect, variance):
        return _error.scaled_outer_sums(weighted, effect, variance, g.frame, n_frames)

    def calibration():
        blocks = _error.row_products(weighted, g.calibration, frame_camera, len(block_frame))
        L = np.zeros((n_frames, 6, g.calibration_covariance.shape[0]))
        for c in np.unique(block_camera):
            mine = block_camera == c
            L[:, :, k_all * c:k_all * (c + 1)] += em._sum_by(blocks[mine], block_frame[mine], n_frames)
        return L @ g.calibration_covariance @ np.swapaxes(L, 1, 2) * model.si("calibration") ** 2

    def per_block(effect, sigma):
        L = _error.row_products(weighted, effect, frame_camera, len(block_frame)) * sigma[:, None, :]
        return em._sum_by(np.einsum("bij,bkj->bik", L, L), block_frame, n_frames)

    pixel = per_observation(np.broadcast_to(np.eye(2), (len(g.frame), 2, 2)) / g.focal[:, None, None],
                            np.full(len(g.frame), model.si("pixel") ** 2))
    point_sigma = em.survey_sigma(g.point_sigma, model)
    rotation_sigma = np.hypot(model.si("jitter"), model.si("mounting"))
    moving = np.where(np.bincount(frame_camera, g.reference, minlength=len(block_frame)) > 0, 0.0, rotation_sigma)
    covariances = {
        "pixel": pixel,
        "survey": per_observation(g.survey[:, :, :2] * point_sigma[:, None, :2], np.ones(len(g.frame))),
        "survey_vertical": per_observation(g.survey[:, :, 2:] * point_sigma[:, None, 2:], np.ones(len(g.frame))),
        "rotation": per_block(g.rotation, np.repeat(moving[:, None], 3, axis=1)),
        "focal": per_block(g.focal_effect[:, :, None], np.full((len(block_frame), 1), model.si("focal"))),
        "calibration": calibration(),
    }
    rotation = covariances.pop("rotation")
    share = model.si("jitter") ** 2 / rotation_sigma**2 if rotation_sigma > 0 else 0.0
    covariances["jitter"], covariances["mounting"] = rotation * share, rotation * (1.0 - share)
    return {name: g.A_inverse @ covariances[name] @ g.A_inverse for name in em.COMPONENTS}


def numpy_curvature_index(g: em.Geometry, covariance: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """nonlinear.curvature_index before _error.curvature_sums."""
    finite = np.isfinite(covariance).all(axis=(1, 2))
    values, vectors = np.linalg.eigh(np.where(finite[:, None, None], covariance, np.eye(6)))
    bases = refine.tangent_bases(nonlinear._predicted_directions(g, g.R, g.t_centred))
    centre = nonlinear._residuals(g, bases, g.R, g.t_centred)
    index = np.zeros(g.n_frames)
    for k in range(6):
        step = vectors[:, :, k] * np.sqrt(np.clip(values[:, k], 0.0, None))[:, None]
        plus = nonlinear._residuals(g, bases, nonlinear._rotated(step[:, :3], g.R), g.t_centred + step[:, 3:])
        minus = nonlinear._residuals(g, bases, nonlinear._rotated(-step[:, :3], g.R), g.t_centred - step[:, 3:])
        second = np.divide(plus + minus - 2 * centre, 2 * noise[:, None], out=np.zeros_like(centre),
                           where=noise[:, None] > 0)
        index = np.maximum(index, np.sqrt(np.bincount(g.frame, np.sum(second**2, axis=1), minlength=g.n_frames)))
    return np.where(finite, index, np.inf)


def numpy_inverse_normal_matrices(normal) -> np.ndarray:
    """refine.inverse_normal_matrices before its Frobenius bound."""
    normal = np.asarray(normal, dtype=float)
    scale = np.sqrt(np.clip(np.diagonal(normal, axis1=-2, axis2=-1), 0.0, None))
    observable = (scale > 0).all(axis=-1)
    scale = np.where(observable[..., None], scale, 1.0)
    outer = scale[..., :, None] * scale[..., None, :]
    normalized = np.where(observable[..., None, None], normal / outer, np.eye(normal.shape[-1]))
    observable &= np.linalg.cond(normalized) <= 1e12
    normalized[~observable] = np.eye(normal.shape[-1])
    inverse = np.linalg.inv(normalized) / outer
    inverse = 0.5 * (inverse + np.swapaxes(inverse, -1, -2))
    inverse[~observable] = np.nan
    return inverse


# ------------------------------------------------------------------------------ the tests

def test_the_compiled_tangent_bases_are_refines():
    """Random directions, and those with zeros, equal or NaN components (argmin's first)."""
    rng = np.random.default_rng(0)
    f = rng.normal(size=(2000, 3))
    special = np.array([[0.0, 0.0, 1.0], [-0.0, 1.0, 0.0], [1.0, -0.0, -0.0], [0.6, -0.6, 0.5], [0.5, 0.5, 0.5],
                        [-0.5, 0.5, -0.5], [np.nan, 0.1, 1.0], [0.3, np.nan, 0.2], [0.0, 0.8, -0.6]])
    f = np.vstack([f / np.linalg.norm(f, axis=1)[:, None], special])
    assert_bits(_error.tangent_bases(f), refine.tangent_bases(f))


def row_arguments(rows: dict, camera: np.ndarray | None = None) -> tuple:
    """linearised_rows' arguments for flight_rows' scene (camera: the rows' rig cameras unless given)."""
    rig, frame, points, R, t = rows["rig"], rows["frame_index"], rows["points"], rows["R"], rows["t"]
    counts = np.bincount(frame)
    centroid = np.stack([np.bincount(frame, points[:, k]) for k in range(3)], axis=1) / np.maximum(counts, 1)[:, None]
    t_centred = t + np.einsum("fij,fj->fi", R, centroid)
    axes = np.array([rig.cam_from_rig[name].R[2] for name in rig.camera_names])
    if camera is None:
        camera = pd.Index(rig.camera_names).get_indexer(rows["cameras"])
    return rows["origins"], rows["directions"], points, centroid, R, t, t_centred, frame, axes, camera


@pytest.mark.parametrize("model", ["radial1", "opencv"])
def test_the_rows_of_the_linearised_solve_are_numpys(model):
    rows = flight_rows(1, distorted_rig(model))
    camera = np.random.default_rng(2).integers(-1, 5, len(rows["frame_index"]))  # -1: the last axis, as numpy
    args = row_arguments(rows, camera)
    for actual, expected in zip(_error.linearised_rows(*args), numpy_rows(*args)):
        assert_bits(actual, expected)


@pytest.mark.parametrize("model", ["radial1", "opencv"])
def test_the_linearised_solve_is_its_numpy(model):
    """The Geometry's arrays from the numpy rows, weights and calibration effects, and the calibration effects
    with the intrinsics' variances or without them (a camera without any: none)."""
    rows = flight_rows(3, distorted_rig(model))
    g = geometry_of(rows)
    args = row_arguments(rows)
    unit, bases, residual, J, squares, dr_dp, rotation, focal_effect, centred = numpy_rows(*args)
    frame, counts = rows["frame_index"], np.bincount(rows["frame_index"])
    for actual, expected in ((g.J, J), (g.residual, residual), (g.rotation, rotation), (g.focal_effect, focal_effect),
                             (g.points_centred, centred), (g.survey, dr_dp @ rows["R"][frame]),
                             (g.weight, squares / (np.bincount(frame, squares)[frame] / counts[frame]))):
        assert_bits(actual, expected)
    rig, names = rows["rig"], list(rows["rig"].cameras)
    variances = np.diag(rows["calibration_covariance"])
    assert_bits(g.calibration, numpy_calibration_effects(rig, names, g.camera, rows["uv"], bases, rotation, dr_dp,
                                                         variances))
    extrinsic = np.where(np.arange(len(variances)) % len(em.calibration_parameters(rig)) < 5, 0.0, variances)
    effects = em._calibration_effects(rig, names, g.camera, rows["uv"], bases, rotation, dr_dp, extrinsic)
    assert_bits(effects, numpy_calibration_effects(rig, names, g.camera, rows["uv"], bases, rotation, dr_dp,
                                                   extrinsic))
    assert np.abs(effects[g.camera == 2]).max() == 0 and np.abs(effects[g.camera == 1][:, :, :5]).max() == 0


@pytest.mark.parametrize("object_space", [True, False])
@pytest.mark.parametrize("sigmas", [{}, {"pixel": 0.0, "jitter": 0.0, "mounting": 0.0},
                                    {"survey": 0.0, "focal": 0.0, "calibration": 3.0}])
def test_the_compiled_covariance_sums_are_numpys(object_space, sigmas):
    rows = flight_rows(4, distorted_rig())
    g = geometry_of(rows, object_space=object_space)
    g.point_sigma[::7] = [0.01, 0.01, 0.03]  # some points' own survey sigmas
    model = model_of(**sigmas)
    expected = numpy_frame_covariances(g, model)
    actual = em.frame_covariances(g, model)
    assert list(actual) == list(expected)
    for name in expected:
        assert_bits(actual[name], expected[name])


def test_the_weighted_row_products_are_those_of_the_weighted_copy():
    rng = np.random.default_rng(10)
    J, weight = rng.normal(size=(3000, 2, 6)), rng.uniform(0.0, 3.0, 3000)
    key = np.sort(rng.integers(-1, 200, 3000))
    assert_bits(_error.row_products(J, J, key, 200, weight),
                _error.row_products(J * weight[:, None, None], J, key, 200))


def test_the_compiled_block_outer_sums_are_numpys():
    rng = np.random.default_rng(5)
    for width in (1, 3):
        blocks, sigma = rng.normal(size=(400, 6, width)), rng.uniform(0.0, 2.0, (400, width))
        sigma[::5] = 0.0
        block_frame = np.sort(rng.integers(0, 90, 400))
        L = blocks * sigma[:, None, :]
        assert_bits(_error.block_outer_sums(blocks, sigma, block_frame, 90),
                    em._sum_by(np.einsum("bij,bkj->bik", L, L), block_frame, 90))


@pytest.mark.parametrize("cameras", [range(5), [0]])
def test_the_compiled_curvature_index_and_noise_are_numpys(cameras):
    """The whole rig, and C0 alone (curved: the index above NONLINEAR_INDEX); a covariance not finite."""
    rows = flight_rows(6, distorted_rig(), cameras=cameras)
    g = geometry_of(rows)
    g.point_sigma[::5] = [0.01, 0.01, 0.03]
    model = model_of()
    covariance = sum(em.frame_covariances(g, model).values())
    covariance[3] = np.nan
    survey = em.survey_sigma(g.point_sigma, model)
    noise = np.sqrt((model.si("pixel") / g.focal) ** 2 + np.sum(survey**2 * np.sum(g.survey**2, axis=1), axis=1) / 2)
    assert_bits(nonlinear.observation_noise(g, model), noise)
    noise[::4] = 0.0  # rows without noise add nothing
    index = nonlinear.curvature_index(g, covariance, noise)
    assert_bits(index, numpy_curvature_index(g, covariance, noise))
    assert index[3] == np.inf and (np.isfinite(index) | (np.arange(FRAMES) == 3)).all()


def test_the_inverse_normal_matrices_take_the_conditioned_without_their_singular_values():
    """Well and badly conditioned, rank-deficient, unobservable (a zero diagonal) and NaN normal
    matrices: the inverses, and NaN where singular, as the singular values made them; one (6, 6) alone."""
    rng = np.random.default_rng(7)
    J = rng.normal(size=(60, 12, 6)) * 10.0 ** rng.uniform(-3, 3, (60, 1, 6))
    normal = np.einsum("fki,fkj->fij", J, J)
    for k, condition in enumerate(10.0 ** np.arange(8, 16)):  # about 1e12 and either side
        U = np.linalg.qr(rng.normal(size=(6, 6)))[0]
        normal[k] = U @ np.diag(np.geomspace(1.0, 1.0 / condition, 6)) @ U.T
    normal[10] = np.outer(J[10, 0], J[10, 0])  # rank 1
    normal[11, 2, :] = normal[11, :, 2] = 0.0  # unobservable
    normal[12, 0, 1] = normal[12, 1, 0] = np.nan
    assert_bits(refine.inverse_normal_matrices(normal[:12]), numpy_inverse_normal_matrices(normal[:12]))
    assert_bits(refine.inverse_normal_matrices(normal[13:]), numpy_inverse_normal_matrices(normal[13:]))
    assert_bits(refine.inverse_normal_matrices(normal[20]), numpy_inverse_normal_matrices(normal[20]))
    inverse = refine.inverse_normal_matrices(normal[:12])
    conditioned = np.isfinite(inverse[:8]).all(axis=(1, 2))
    assert conditioned.any() and not conditioned.all() and np.isnan(inverse[[10, 11]]).all()
    with pytest.raises(np.linalg.LinAlgError):  # as numpy's singular values of a NaN matrix
        numpy_inverse_normal_matrices(normal[12])
    with pytest.raises(np.linalg.LinAlgError):
        refine.inverse_normal_matrices(normal[12])


def test_dense_codes_are_numpys_unique_codes():
    rng = np.random.default_rng(8)
    for key in (rng.integers(-1, 50, 1000), rng.integers(-1, 10**9, 1000), np.full(5, -1), np.zeros(0, int)):
        expected = np.full(len(key), -1)
        expected[key >= 0] = np.unique(key[key >= 0], return_inverse=True)[1]
        assert_bits(em._dense(key), expected)


def test_the_stages_pixel_residuals_and_string_columns_are_numpys():
    """flight._frames_pixel_residuals against rows_pixel_residuals of each row's pose; the per-observation
    table's str columns taken from their distinct values as pandas makes them."""
    rows = flight_rows(9, distorted_rig("opencv"))
    rig, frame = rows["rig"], rows["frame_index"]
    R, t = rows["R"].copy(), rows["t"].copy()
    R[4] = np.nan  # a frame not solved
    expected = flight.rows_pixel_residuals(rig, R[frame], t[frame], rows["cameras"], rows["uv"], rows["points"])
    actual = flight._frames_pixel_residuals(rig, R, t, frame, rows["cameras"], rows["uv"], rows["points"])
    np.testing.assert_array_equal(actual, expected)
    assert_bits(actual[frame != 4], expected[frame != 4])
    keep = np.flatnonzero(frame % 2 == 0)
    frames = np.array([f"f{k:03d}" for k in range(FRAMES)])
    for values in (frames[frame[keep]], rows["cameras"][keep], rows["point_ids"], rows["cameras"][:0]):
        direct = pd.DataFrame({"column": values})
        taken = pd.DataFrame({"column": flight._str_column(values)})
        pd.testing.assert_frame_equal(taken, direct)
        assert taken.to_csv() == direct.to_csv()
    with pytest.raises(Exception, match="C9"):
        flight._frames_pixel_residuals(rig, R, t, frame, np.where(frame == 1, "C9", rows["cameras"]), rows["uv"],
                                       rows["points"])
