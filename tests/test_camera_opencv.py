"""The opencv camera model (k1, k2, p1, p2, k3) against OpenCV itself and against finite differences."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dmais_pipe.camera import UNDISTORT_TOLERANCE_PX, Camera, project_unmasked
from dmais_pipe.errors import DmaisError

# cv2.calibrateCamera's result on OpenCV's left*.jpg stereo sample (a wide-angle 640x480 lens),
# rounded: k3 > 0 keeps it one-to-one well beyond the image.
WIDE = Camera(532.8, 532.9, 342.5, 233.9, -0.281, 640, 480, "opencv", k2=0.0252, p1=0.0012, p2=-0.00018, k3=0.16)
# An 80 mm aerial lens: 14000 x 10000 px at f = 12000 px, small radial and tangential terms.
AERIAL = Camera(12004.0, 11996.5, 7003.2, 4995.1, -0.032, 14000, 10000, "opencv",
                k2=0.011, p1=2.1e-5, p2=-3.4e-5, k3=-0.004)
# A strong barrel lens whose model folds inside the image (k3 < 0 turns it back).
FOLDING = Camera(420.0, 420.0, 319.5, 239.5, -0.30, 640, 480, "opencv", k2=0.05, p1=0.001, p2=0.0, k3=-0.05)
CAMERAS = {"wide": WIDE, "aerial": AERIAL}


def grid(camera: Camera, n: int = 97) -> np.ndarray:
    """(n^2, 2) pixels covering the whole image, its borders included."""
    u, v = np.meshgrid(np.linspace(-0.5, camera.width - 0.5, n), np.linspace(-0.5, camera.height - 0.5, n))
    return np.column_stack([u.ravel(), v.ravel()])


def points_in_view(camera: Camera, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) camera-frame points whose undistorted normalized coordinates span the image."""
    half = camera._half_diagonal()
    xy = rng.uniform(-0.7 * half, 0.7 * half, (n, 2))
    z = rng.uniform(1.0, 500.0, n)
    return np.column_stack([xy * z[:, None], z])


@pytest.mark.parametrize("name", sorted(CAMERAS))
def test_project_equals_opencv_projectPoints(name):
    camera = CAMERAS[name]
    points = points_in_view(camera, 500, np.random.default_rng(3))
    theirs = cv2.projectPoints(points, np.zeros(3), np.zeros(3), camera.K, np.array(camera.distortion))[0]
    np.testing.assert_allclose(camera.project(points), theirs.reshape(-1, 2), rtol=0, atol=1e-9)


@pytest.mark.parametrize("name", sorted(CAMERAS))
def test_undistort_inverts_the_model_over_the_whole_image_to_a_thousandth_of_a_pixel(name):
    camera = CAMERAS[name]
    assert not camera.folds_in_image
    uv = grid(camera)
    xy = camera.undistort_normalized(uv)
    assert np.isfinite(xy).all()
    assert np.hypot(xy[:, 0], xy[:, 1]).max() <= camera.max_projectable_radius
    back = camera.project(np.column_stack([xy, np.ones(len(xy))]))
    assert np.abs(back - uv).max() <= 1e-3
    assert np.abs(back - uv).max() <= 10 * UNDISTORT_TOLERANCE_PX  # what the Newton iteration promises
    np.testing.assert_allclose(camera.distort(camera.undistort(uv)), uv, rtol=0, atol=1e-6)


def test_undistort_agrees_with_opencv_undistortPoints():
    uv = grid(WIDE, 41)
    theirs = cv2.undistortPoints(uv.reshape(-1, 1, 2), WIDE.K, np.array(WIDE.distortion),
                                 criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)).reshape(-1, 2)
    np.testing.assert_allclose(WIDE.undistort_normalized(uv) * WIDE.fx, theirs * WIDE.fx, rtol=0, atol=1e-6)


def test_the_invertible_region_is_where_the_jacobian_determinant_stays_positive():
    r = FOLDING.max_projectable_radius
    assert np.isfinite(r)
    # just inside the radius the map's Jacobian is positive in every direction, just outside it is not in some
    angle = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    for radius, positive in ((0.995 * r, True), (1.02 * r, False)):
        xy = radius * np.column_stack([np.cos(angle), np.sin(angle)])
        h = 1e-7
        dx = (FOLDING.distort(xy * [FOLDING.fx, FOLDING.fy] + [FOLDING.cx + h, FOLDING.cy]) -
              FOLDING.distort(xy * [FOLDING.fx, FOLDING.fy] + [FOLDING.cx - h, FOLDING.cy])) / (2 * h)
        dy = (FOLDING.distort(xy * [FOLDING.fx, FOLDING.fy] + [FOLDING.cx, FOLDING.cy + h]) -
              FOLDING.distort(xy * [FOLDING.fx, FOLDING.fy] + [FOLDING.cx, FOLDING.cy - h])) / (2 * h)
        det = dx[:, 0] * dy[:, 1] - dx[:, 1] * dy[:, 0]
        assert (det > 0).all() == positive


def test_a_model_that_folds_inside_the_image_says_so_and_returns_nan_beyond_the_fold():
    assert FOLDING.folds_in_image
    assert not WIDE.folds_in_image and not AERIAL.folds_in_image
    r = FOLDING.max_projectable_radius
    beyond = np.array([[1.05 * r, 0.0, 1.0], [0.0, 2.0 * r, 1.0]])
    assert np.isnan(FOLDING.project(beyond)).all()
    assert np.isfinite(project_unmasked(beyond, FOLDING)).all()  # the solvers' smooth extension
    corner = np.array([[-0.5, -0.5], [639.5, 479.5]])
    xy = FOLDING.undistort_normalized(corner)
    assert np.isnan(xy).all()  # the image corners have no undistorted point inside the fold
    inside = FOLDING.project(np.array([[0.5 * r, 0.2 * r, 1.0]]))
    np.testing.assert_allclose(FOLDING.undistort_normalized(inside), [[0.5 * r, 0.2 * r]], atol=1e-12)


@pytest.mark.parametrize("name", sorted(CAMERAS))
def test_jacobians_are_the_finite_differences(name):
    camera = CAMERAS[name]
    points = points_in_view(camera, 30, np.random.default_rng(5))
    uv, J_point, J_parameters = camera.project(points, jacobian=True)
    assert J_parameters.shape == (30, 2, 9)
    for k, value in enumerate(camera.parameters):
        h = 1e-6 * max(abs(value), 1e-3)
        plus, minus = camera.parameters.copy(), camera.parameters.copy()
        plus[k] += h
        minus[k] -= h
        numeric = (camera.with_parameters(plus).project(points) - camera.with_parameters(minus).project(points)) / (2 * h)
        np.testing.assert_allclose(J_parameters[:, :, k], numeric, rtol=1e-6, atol=1e-6 * np.abs(numeric).max())
    for axis in range(3):
        h = 1e-6 * points[:, 2:]
        step = np.zeros(3)
        step[axis] = 1.0
        numeric = (camera.project(points + h * step) - camera.project(points - h * step)) / (2 * h)
        np.testing.assert_allclose(J_point[:, :, axis], numeric, rtol=1e-6, atol=1e-6 * np.abs(numeric).max())


def test_opencv_with_only_k1_is_radial1():
    radial1 = Camera(45010.0, 44987.5, 2085.25, 1476.5, -3.0, 4096, 3000)
    opencv = Camera(45010.0, 44987.5, 2085.25, 1476.5, -3.0, 4096, 3000, "opencv")
    points = points_in_view(radial1, 200, np.random.default_rng(7))
    np.testing.assert_allclose(opencv.project(points), radial1.project(points), rtol=0, atol=1e-9)
    np.testing.assert_allclose(opencv.max_projectable_radius, radial1.max_projectable_radius, rtol=2e-3)
    uv = grid(radial1, 33)
    np.testing.assert_allclose(opencv.undistort_normalized(uv), radial1.undistort_normalized(uv), rtol=0, atol=1e-12)
    J9, J5 = opencv.project(points, jacobian=True)[2], radial1.project(points, jacobian=True)[2]
    np.testing.assert_allclose(J9[:, :, :5], J5, rtol=1e-12)


def test_parameters_and_dict_round_trip():
    assert AERIAL.parameter_names == ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    assert AERIAL.with_parameters(AERIAL.parameters) == AERIAL
    assert Camera.from_dict(AERIAL.to_dict()) == AERIAL
    assert AERIAL.to_dict()["model"] == "opencv" and AERIAL.to_dict()["k1"] == AERIAL.d
    radial1 = Camera(45010.0, 44987.5, 2085.25, 1476.5, 3.0, 4096, 3000)
    assert list(radial1.to_dict()) == ["fx", "fy", "cx", "cy", "d", "width", "height"]  # the paper's files unchanged


def test_bad_models_are_refused_by_name():
    with pytest.raises(DmaisError, match="'fisheye' is not one of radial1, opencv"):
        Camera(1.0, 1.0, 0.0, 0.0, 0.0, 1, 1, "fisheye")
    with pytest.raises(DmaisError, match="need model opencv"):
        Camera(1.0, 1.0, 0.0, 0.0, 0.0, 1, 1, k2=0.1)
    with pytest.raises(DmaisError, match="9 parameters, got 5"):
        AERIAL.with_parameters(AERIAL.parameters[:5])
    with pytest.raises(DmaisError, match="'fisheye'"):
        Camera.from_dict({**AERIAL.to_dict(), "model": "fisheye"})
