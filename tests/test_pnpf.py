"""PnPf (pose + focal, known principal point, d = 0) against known truth and OpenCV."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dmais_pipe.calib.pnpf import solve_pnpf
from dmais_pipe.camera import Camera
from dmais_pipe.errors import DmaisError
from dmais_pipe.geometry import Rigid3, rotation_error

NARROW = Camera(fx=45000.0, fy=45000.0, cx=2063.0, cy=1489.0, d=0.0, width=4096, height=3000)  # 5.2 deg FoV
WIDE = Camera(fx=800.0, fy=800.0, cx=322.0, cy=236.0, d=0.0, width=640, height=480)  # 44 deg FoV
DEPTHS = {"narrow": (130.0, 280.0), "wide": (1.0, 5.0)}


def scene(camera: Camera, n: int, rng, depth, planar: bool = False, noise: float = 0.0):
    """World points (n, 3), pixels (n, 2) spread over the image, true cam_from_world."""
    u = rng.uniform(20, camera.width - 20, n)
    v = rng.uniform(20, camera.height - 20, n)
    rays = np.column_stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones(n)])
    if planar:  # a plane tilted by ~35 deg, through the middle depth
        normal = np.array([0.45, -0.4, 1.0]) / np.linalg.norm([0.45, -0.4, 1.0])
        z = np.mean(depth) / (rays @ normal)
    else:
        z = rng.uniform(*depth, n)
    points_cam = rays * z[:, None]
    cam_from_world = Rigid3(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3) * 50 * depth[0])
    points_world = cam_from_world.inverse().apply(points_cam)
    uv = camera.project(points_cam) + rng.normal(scale=noise, size=(n, 2))
    return points_world, uv, cam_from_world


@pytest.mark.parametrize("camera,kind", [(NARROW, "narrow"), (WIDE, "wide")], ids=["f45000", "f800"])
@pytest.mark.parametrize("planar", [False, True], ids=["3d", "planar"])
def test_exact_on_noise_free_data(camera, kind, planar):
    rng = np.random.default_rng(1 + planar)
    for n in (6, 20) if not planar else (4, 20):
        X, uv, truth = scene(camera, n, rng, DEPTHS[kind], planar=planar)
        pose, focal = solve_pnpf(X, uv, [camera.cx, camera.cy])
        assert focal == pytest.approx(camera.fx, rel=1e-8)
        assert rotation_error(pose.R, truth.R) < 1e-9
        np.testing.assert_allclose(pose.t, truth.t, atol=1e-7 * np.linalg.norm(truth.t))


@pytest.mark.parametrize("camera,kind", [(NARROW, "narrow"), (WIDE, "wide")], ids=["f45000", "f800"])
def test_noisy_3d_matches_opencv_calibration_of_the_same_view(camera, kind):
    """With 0.1 px noise, PnPf's focal equals OpenCV's single-view calibration with the same model
    (fx = fy, principal point fixed, no distortion): both minimise the same reprojection error."""
    rng = np.random.default_rng(7)
    X, uv, truth = scene(camera, 40, rng, DEPTHS[kind], noise=0.1)
    pose, focal = solve_pnpf(X, uv, [camera.cx, camera.cy])
    assert abs(focal / camera.fx - 1) < 0.01
    assert np.degrees(rotation_error(pose.R, truth.R)) < 0.05
    centre = X.mean(axis=0)  # float32 input: centre the world first
    flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_FIX_PRINCIPAL_POINT
             | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3)
    K0 = camera.K.copy()
    K0[0, 0] = K0[1, 1] = camera.fx * 1.002
    _, K, _, rvecs, tvecs = cv2.calibrateCamera(
        [(X - centre).astype(np.float32)], [uv.astype(np.float32)], (camera.width, camera.height), K0,
        np.zeros(5), flags=flags, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 500, 1e-14))
    assert focal == pytest.approx(K[0, 0], rel=2e-5)
    assert rotation_error(pose.R, cv2.Rodrigues(rvecs[0])[0]) < 1e-5


def test_noisy_planar_wide():
    rng = np.random.default_rng(3)
    X, uv, truth = scene(WIDE, 48, rng, DEPTHS["wide"], planar=True, noise=0.1)
    pose, focal = solve_pnpf(X, uv, [WIDE.cx, WIDE.cy])
    assert abs(focal / WIDE.fx - 1) < 0.01
    assert np.degrees(rotation_error(pose.R, truth.R)) < 0.2


def test_world_far_from_origin_and_large_translation():
    """UTM-like coordinates (1e6 m) must not hurt: the solver centres and scales the points."""
    rng = np.random.default_rng(5)
    X, uv, truth = scene(NARROW, 15, rng, DEPTHS["narrow"])
    offset = np.array([5.0e5, 4.2e6, 120.0])
    pose, focal = solve_pnpf(X + offset, uv, [NARROW.cx, NARROW.cy])
    assert focal == pytest.approx(NARROW.fx, rel=1e-7)
    np.testing.assert_allclose(pose.apply(X + offset), truth.apply(X), atol=1e-4)


def test_bad_input():
    rng = np.random.default_rng(0)
    X, uv, _ = scene(NARROW, 10, rng, DEPTHS["narrow"])
    with pytest.raises(DmaisError, match="at least 4"):
        solve_pnpf(X[:3], uv[:3], [NARROW.cx, NARROW.cy])
    with pytest.raises(DmaisError, match="non-coplanar points, needs at least 6"):
        solve_pnpf(X[:5], uv[:5], [NARROW.cx, NARROW.cy])
    line = X[:1] + np.linspace(0, 1, 8)[:, None] * np.array([1.0, 2.0, 3.0])
    with pytest.raises(DmaisError, match="collinear"):
        solve_pnpf(line, uv[:8], [NARROW.cx, NARROW.cy])
    bad = uv.copy()
    bad[4, 1] = np.nan
    with pytest.raises(DmaisError, match=r"non-finite.*\[4\]"):
        solve_pnpf(X, bad, [NARROW.cx, NARROW.cy])
    with pytest.raises(DmaisError, match="shape"):
        solve_pnpf(X, uv[:5], [NARROW.cx, NARROW.cy])
    # a plane parallel to the image plane: the focal length is not observable
    grid = np.array([[x, y, 200.0] for x in range(-3, 4) for y in range(-2, 3)], dtype=float)
    flat = NARROW.project(grid)
    with pytest.raises(DmaisError, match="degenerate coplanar"):
        solve_pnpf(grid, flat, [NARROW.cx, NARROW.cy])
