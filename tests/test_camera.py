"""Tests of the camera model (paper eq. 2-3): pinhole + one radial coefficient d == OpenCV's k1."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dmais_pipe.camera import Camera, project_unmasked
from dmais_pipe.errors import DmaisError
from dmais_pipe.geometry import exp_so3, pose_jacobian

# Long-focal DMAIS-like cameras: fx != fy slightly, principal point tens of px off centre.
LONG_FOCAL = {
    f"d={d}": Camera(fx=45010.0, fy=44987.5, cx=2048.0 + 37.25, cy=1500.0 - 23.5, d=d, width=4096, height=3000)
    for d in (3.0, -3.0, 0.0)
}
# Wide-angle cameras whose whole image lies within the invertible radius of d = -0.3.
WIDE_INSIDE = {
    "640x480": Camera(fx=601.0, fy=598.0, cx=322.5, cy=237.0, d=-0.3, width=640, height=480),
    "1280x960": Camera(fx=1202.0, fy=1196.0, cx=645.0, cy=474.0, d=-0.3, width=1280, height=960),
}
# Wide-angle cameras with f ~ 530 px: the image corners are *beyond* the radius where the model
# r_d = r (1 + d r^2) folds back (max r_d = 0.703 for d = -0.3, corners at r_d ~ 0.755).
WIDE_FOLDING = {
    "640x480": Camera(fx=531.0, fy=529.0, cx=322.0, cy=238.0, d=-0.3, width=640, height=480),
    "1280x960": Camera(fx=1062.0, fy=1058.0, cx=643.0, cy=477.0, d=-0.3, width=1280, height=960),
}
ALL_CAMERAS = {**LONG_FOCAL, **{f"wide {k}": c for k, c in WIDE_INSIDE.items()}}


def dist_coeffs(camera: Camera) -> np.ndarray:
    return np.array([camera.d, 0.0, 0.0, 0.0, 0.0])


def image_grid(camera: Camera, n_u: int = 129, n_v: int = 97, beyond: float = 0.5) -> np.ndarray:
    """(n, 2) dense grid over the whole image from -0.5 - beyond to size - 0.5 + beyond, corners included."""
    u = np.linspace(-0.5 - beyond, camera.width - 0.5 + beyond, n_u)
    v = np.linspace(-0.5 - beyond, camera.height - 0.5 + beyond, n_v)
    uu, vv = np.meshgrid(u, v)
    grid = np.column_stack([uu.ravel(), vv.ravel()])
    w, h = camera.width, camera.height
    corners = np.array(
        [[x, y] for x in (-0.5, -1.0, w - 0.5, w) for y in (-0.5, -1.0, h - 0.5, h)]
        + [[camera.cx, camera.cy], [0.0, 0.0], [w - 1.0, h - 1.0]]
    )
    return np.vstack([grid, corners])


def distorted_radius(camera: Camera, uv: np.ndarray) -> np.ndarray:
    return np.hypot((uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy)


def random_points_in_view(camera: Camera, n: int, rng: np.random.Generator, beyond: float = 0.1) -> np.ndarray:
    """(n, 3) camera-frame points whose undistorted pixels span the image (+ `beyond` of its size)."""
    u = rng.uniform(-beyond * camera.width, (1 + beyond) * camera.width, n)
    v = rng.uniform(-beyond * camera.height, (1 + beyond) * camera.height, n)
    z = rng.uniform(0.5, 5000.0, n)
    return np.column_stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z])


# ------------------------------------------------------------------------------------ basics


def test_K_matrix():
    camera = LONG_FOCAL["d=3.0"]
    np.testing.assert_array_equal(
        camera.K, [[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]]
    )


def test_to_dict_from_dict_round_trip():
    camera = LONG_FOCAL["d=-3.0"]
    data = camera.to_dict()
    assert data == {
        "fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy, "d": camera.d,
        "width": 4096, "height": 3000,
    }
    assert isinstance(data["width"], int) and isinstance(data["height"], int)
    assert all(isinstance(data[k], float) for k in ("fx", "fy", "cx", "cy", "d"))
    assert Camera.from_dict(data) == camera
    # extra keys (e.g. rig.json's name, cam_from_rig) are ignored
    assert Camera.from_dict({**data, "name": "C0", "cam_from_rig": {}}) == camera


def test_bad_shapes_raise_dmais_error():
    camera = LONG_FOCAL["d=3.0"]
    with pytest.raises(DmaisError, match=r"\(n, 3\)"):
        camera.project(np.zeros((4, 2)))
    with pytest.raises(DmaisError, match=r"\(n, 2\)"):
        camera.undistort(np.zeros((4, 3)))
    with pytest.raises(DmaisError):
        camera.distort(np.zeros((2, 2, 2)))


def test_single_point_inputs_are_promoted_to_one_row():
    camera = LONG_FOCAL["d=3.0"]
    assert camera.project([1.0, 2.0, 1000.0]).shape == (1, 2)
    assert camera.distort([100.0, 200.0]).shape == (1, 2)
    assert camera.undistort([100.0, 200.0]).shape == (1, 2)
    assert camera.unproject([100.0, 200.0]).shape == (1, 3)


# -------------------------------------------------------------- the model is OpenCV's k1 model


@pytest.mark.parametrize("name", sorted(ALL_CAMERAS))
def test_project_equals_opencv_projectPoints(name):
    camera = ALL_CAMERAS[name]
    rng = np.random.default_rng(1)
    points = random_points_in_view(camera, 500, rng)
    expected, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), camera.K, dist_coeffs(camera))
    expected = expected.reshape(-1, 2)
    uv = camera.project(points)
    np.testing.assert_allclose(uv, expected, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("name", sorted(ALL_CAMERAS))
def test_distort_is_paper_eq2_written_out(name):
    camera = ALL_CAMERAS[name]
    rng = np.random.default_rng(2)
    u = rng.uniform(-0.5, camera.width - 0.5, 300)
    v = rng.uniform(-0.5, camera.height - 0.5, 300)
    fx, fy, cx, cy, d = camera.fx, camera.fy, camera.cx, camera.cy, camera.d
    # paper eq. 3 then eq. 2, literally
    x = (u - cx) / fx
    y = (v - cy) / fy
    u_breve = u + d * (u - cx) * (x**2 + y**2)
    v_breve = v + d * (v - cy) * (x**2 + y**2)
    np.testing.assert_allclose(camera.distort(np.column_stack([u, v])), np.column_stack([u_breve, v_breve]),
                               rtol=1e-12, atol=1e-9)


def test_project_is_pinhole_then_eq2():
    camera = LONG_FOCAL["d=3.0"]
    points = random_points_in_view(camera, 200, np.random.default_rng(3))
    homogeneous = points @ camera.K.T
    undistorted = homogeneous[:, :2] / homogeneous[:, 2:]
    np.testing.assert_allclose(camera.project(points), camera.distort(undistorted), rtol=1e-12, atol=1e-9)


def test_zero_distortion_is_identity():
    camera = LONG_FOCAL["d=0.0"]
    grid = image_grid(camera, 17, 13)
    np.testing.assert_allclose(camera.distort(grid), grid, rtol=0, atol=1e-9)
    np.testing.assert_allclose(camera.undistort(grid), grid, rtol=0, atol=1e-9)


# ----------------------------------------------------------- undistort inverts distort everywhere


@pytest.mark.parametrize("name", sorted(ALL_CAMERAS))
def test_undistort_inverts_distort_over_whole_image(name):
    camera = ALL_CAMERAS[name]
    grid = image_grid(camera)
    # the whole (distorted) image lies within the one-to-one radius of the model
    assert distorted_radius(camera, grid).max() < camera.max_undistortable_radius
    undistorted = camera.undistort(grid)
    assert np.isfinite(undistorted).all()
    np.testing.assert_allclose(camera.distort(undistorted), grid, rtol=0, atol=1e-6)
    # the grid read as undistorted pixels: distort, then undistort back
    np.testing.assert_allclose(camera.undistort(camera.distort(grid)), grid, rtol=0, atol=1e-6)


@pytest.mark.parametrize("name", sorted(WIDE_FOLDING))
def test_undistort_beyond_the_invertible_radius(name):
    """f ~ 530 px, d = -0.3: the image corners lie beyond the fold of r_d = r (1 + d r^2).

    Inside the invertible radius the inverse is exact; beyond it there is no undistorted point
    (distort never reaches that radius) and undistort says so with NaN.
    """
    camera = WIDE_FOLDING[name]
    r_turn = 1.0 / np.sqrt(-3.0 * camera.d)
    assert camera.max_undistortable_radius == pytest.approx(r_turn * (1 + camera.d * r_turn**2), rel=1e-12)
    grid = image_grid(camera)
    r_d = distorted_radius(camera, grid)
    inside = r_d <= camera.max_undistortable_radius
    assert 0 < (~inside).sum() < 0.05 * len(grid)  # only the corners fold
    undistorted = camera.undistort(grid)
    assert np.isfinite(undistorted[inside]).all()
    assert np.isnan(undistorted[~inside]).all()
    np.testing.assert_allclose(camera.distort(undistorted[inside]), grid[inside], rtol=0, atol=1e-6)
    # read as undistorted pixels, the whole image is within r_turn, so distort is invertible
    assert distorted_radius(camera, grid).max() < r_turn
    np.testing.assert_allclose(camera.undistort(camera.distort(grid)), grid, rtol=0, atol=1e-6)
    # distort never goes beyond max_undistortable_radius (for r up to where r (1 + d r^2) turns negative)
    r = np.linspace(0, 1 / np.sqrt(-camera.d), 2001)
    far = camera.distort(np.column_stack([camera.cx + camera.fx * r, np.full_like(r, camera.cy)]))
    assert distorted_radius(camera, far).max() <= camera.max_undistortable_radius * (1 + 1e-12)


def test_max_undistortable_radius_is_infinite_for_non_negative_d():
    assert LONG_FOCAL["d=3.0"].max_undistortable_radius == np.inf
    assert LONG_FOCAL["d=0.0"].max_undistortable_radius == np.inf
    assert np.isfinite(LONG_FOCAL["d=-3.0"].max_undistortable_radius)


@pytest.mark.parametrize("name", sorted(ALL_CAMERAS))
def test_undistort_matches_opencv_undistortPoints(name):
    """cv2.undistortPoints is an independent (fixed-point, less accurate) reference."""
    camera = ALL_CAMERAS[name]
    grid = image_grid(camera, 65, 49)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    reference = cv2.undistortPoints(
        grid.reshape(-1, 1, 2), camera.K, dist_coeffs(camera), P=camera.K, criteria=criteria
    ).reshape(-1, 2)
    # OpenCV's fixed-point iteration crawls close to the fold of d < 0: compare where it converges
    converged = distorted_radius(camera, grid) <= 0.9 * camera.max_undistortable_radius
    assert converged.mean() > 0.9
    np.testing.assert_allclose(camera.undistort(grid)[converged], reference[converged], rtol=0, atol=1e-3)


@pytest.mark.parametrize("name", sorted(LONG_FOCAL))
def test_undistort_matches_opencv_default_criteria_long_focal(name):
    camera = LONG_FOCAL[name]
    grid = image_grid(camera, 65, 49)
    reference = cv2.undistortPoints(grid.reshape(-1, 1, 2), camera.K, dist_coeffs(camera), P=camera.K)
    np.testing.assert_allclose(camera.undistort(grid), reference.reshape(-1, 2), rtol=0, atol=1e-3)


def test_undistort_normalized_matches_opencv_normalized_output():
    camera = LONG_FOCAL["d=-3.0"]
    grid = image_grid(camera, 33, 25)
    reference = cv2.undistortPoints(grid.reshape(-1, 1, 2), camera.K, dist_coeffs(camera)).reshape(-1, 2)
    np.testing.assert_allclose(camera.undistort_normalized(grid), reference, rtol=0, atol=1e-3 / camera.fx)


# --------------------------------------------------------------------------------- unproject


@pytest.mark.parametrize("name", sorted(ALL_CAMERAS))
@pytest.mark.parametrize("depth", [0.01, 1.0, 523.7, 1e6])
def test_unproject_is_unit_and_reprojects(name, depth):
    camera = ALL_CAMERAS[name]
    grid = image_grid(camera, 33, 25)
    rays = camera.unproject(grid)
    assert rays.shape == (len(grid), 3)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, rtol=0, atol=1e-14)
    assert (rays[:, 2] > 0).all()
    np.testing.assert_allclose(camera.project(rays * depth), grid, rtol=0, atol=1e-6)


def test_unproject_direction_is_K_inverse_of_undistorted_pixel():
    camera = LONG_FOCAL["d=3.0"]
    grid = image_grid(camera, 17, 13)
    m = np.column_stack([camera.undistort(grid), np.ones(len(grid))])
    expected = np.linalg.solve(camera.K, m.T).T
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    np.testing.assert_allclose(camera.unproject(grid), expected, rtol=0, atol=1e-15)


def test_principal_point_unprojects_to_optical_axis():
    camera = LONG_FOCAL["d=-3.0"]
    np.testing.assert_allclose(camera.unproject([camera.cx, camera.cy]), [[0.0, 0.0, 1.0]], atol=1e-15)
    np.testing.assert_allclose(camera.project([0.0, 0.0, 7.0]), [[camera.cx, camera.cy]], atol=1e-12)


# ----------------------------------------------------------------- behind camera, image borders


def test_points_behind_or_on_camera_plane_project_to_nan():
    camera = LONG_FOCAL["d=3.0"]
    points = np.array([
        [1.0, 2.0, 1000.0],   # in front
        [1.0, 2.0, -1000.0],  # behind
        [0.0, 0.0, -1.0],     # behind, on the axis
        [1.0, 2.0, 0.0],      # on the camera plane
        [0.0, 0.0, 0.0],      # the centre itself
        [0.0, 0.0, 1e-300],   # just in front
    ])
    with np.errstate(all="raise"):
        uv = camera.project(points)
    assert np.isfinite(uv[0]).all() and np.isfinite(uv[5]).all()
    assert np.isnan(uv[1:5]).all()
    assert not camera.in_image(np.nan_to_num(uv, nan=-1e9))[1:5].any()


def test_in_image_borders():
    camera = Camera(fx=45000.0, fy=45000.0, cx=2047.5, cy=1499.5, d=0.0, width=4096, height=3000)
    w, h = camera.width, camera.height
    eps = 1e-9
    uv = np.array([
        [-0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5], [w - 0.5, -0.5],  # corners: inside
        [0.0, 0.0], [w - 1.0, h - 1.0], [camera.cx, camera.cy],               # pixel centres
        [-0.5 - eps, 10.0], [w - 0.5 + eps, 10.0],                          # just outside in u
        [10.0, -0.5 - eps], [10.0, h - 0.5 + eps],                          # just outside in v
        [w, h], [-1.0, -1.0],
    ])
    expected = [True] * 7 + [False] * 6
    np.testing.assert_array_equal(camera.in_image(uv), expected)
    # a margin shrinks the accepted area on every side
    margin = 10.0
    uv_margin = np.array([[-0.5 + margin, 9.5], [w - 0.5 - margin, h - 0.5 - margin], [9.4, 100.0],
                          [100.0, h - 10.4]])
    np.testing.assert_array_equal(camera.in_image(uv_margin, margin=margin), [True, True, False, False])
    assert not camera.in_image([np.nan, 10.0])[0]


# --------------------------------------------------------------------- property-based round trips

CAMERA_PARAMS = st.fixed_dictionaries({
    "f": st.floats(300.0, 60000.0),
    "aspect": st.floats(0.99, 1.01),
    "cx_off": st.floats(-0.05, 0.05),
    "cy_off": st.floats(-0.05, 0.05),
    "d": st.floats(-0.5, 5.0, allow_subnormal=False),
    "size": st.sampled_from([(640, 480), (1280, 960), (4096, 3000)]),
})


def make_camera(p) -> Camera:
    w, h = p["size"]
    return Camera(fx=p["f"], fy=p["f"] * p["aspect"], cx=(0.5 + p["cx_off"]) * w, cy=(0.5 + p["cy_off"]) * h,
                  d=p["d"], width=w, height=h)


@settings(deadline=None, max_examples=150)
@given(params=CAMERA_PARAMS, a=st.floats(-1, 1), b=st.floats(-1, 1))
def test_property_undistort_distort_round_trip(params, a, b):
    # undistorted normalized radius <= 0.4, where 1 + 3 d r^2 >= 0.76 (well inside the fold)
    camera = make_camera(params)
    r_max = min(0.4, 1.5 * np.hypot(camera.width, camera.height) / camera.fx)
    xy = np.array([a, b]) * r_max / np.sqrt(2)
    uv = np.array([[camera.cx + camera.fx * xy[0], camera.cy + camera.fy * xy[1]]])
    distorted = camera.distort(uv)
    np.testing.assert_allclose(camera.undistort(distorted), uv, rtol=0, atol=1e-6)
    if np.all(distorted_radius(camera, distorted) <= camera.max_undistortable_radius):
        np.testing.assert_allclose(camera.distort(camera.undistort(distorted)), distorted, rtol=0, atol=1e-6)


@settings(deadline=None, max_examples=150)
@given(params=CAMERA_PARAMS, s=st.floats(-0.01, 1.01), t=st.floats(-0.01, 1.01),
       depth=st.floats(1e-3, 1e6))
def test_property_project_unproject_round_trip(params, s, t, depth):
    camera = make_camera(params)
    uv = np.array([[s * camera.width - 0.5, t * camera.height - 0.5]])
    if distorted_radius(camera, uv)[0] > camera.max_undistortable_radius:
        assert np.isnan(camera.unproject(uv)).all()
        return
    ray = camera.unproject(uv)
    assert np.linalg.norm(ray) == pytest.approx(1.0, abs=1e-14)
    np.testing.assert_allclose(camera.project(ray * depth), uv, rtol=0, atol=1e-6)


@settings(deadline=None, max_examples=150)
@given(params=CAMERA_PARAMS, x=st.floats(-1, 1), y=st.floats(-1, 1), z=st.floats(1e-2, 1e5))
def test_property_unproject_project_round_trip_inside_fold(params, x, y, z):
    """A point in front whose normalized radius is below the fold maps back to its own direction."""
    camera = make_camera(params)
    r_limit = 0.4 if camera.d >= 0 else min(0.4, 0.9 / np.sqrt(-3 * camera.d))
    point = np.array([[x * r_limit / np.sqrt(2) * z, y * r_limit / np.sqrt(2) * z, z]])
    ray = camera.unproject(camera.project(point))
    np.testing.assert_allclose(ray, point / np.linalg.norm(point), rtol=0, atol=1e-9)


# --------------------------------------------------------------------------- d < 0: the fold of the model


def test_max_undistortable_radius_for_tiny_negative_d():
    """r_turn (1 + d r_turn^2) == 2/3 r_turn, but r_turn**2 overflows for |d| < ~6e-309."""
    camera = Camera(fx=300.0, fy=300.0, cx=320.0, cy=240.0, d=-5e-324, width=640, height=480)
    with np.errstate(over="ignore"):
        assert camera.max_undistortable_radius > 1e100
        ray = camera.unproject([camera.cx, camera.cy])
    np.testing.assert_allclose(ray, [[0.0, 0.0, 1.0]])


def test_project_flags_points_beyond_the_distortion_fold():
    """For d < 0 the model folds back at r_turn = 1 / sqrt(-3 d). A point in front of the camera
    further off-axis than that is not imaged by the model's one-to-one part, yet a naive projection returns
    a finite pixel, often inside the image. E.g. d = -0.3, f = 601 px: a point 60 deg off-axis
    lands ~104 px from the principal point; d = -3, 4096x3000 px, f = 45000 px: points 29-31 deg
    off-axis would land in the image (30 deg exactly on the principal point).
    project() must flag them as not imaged (NaN) rather than report such ghosts.
    """
    camera = WIDE_INSIDE["640x480"]
    r_turn = 1.0 / np.sqrt(-3.0 * camera.d)
    assert r_turn < np.tan(np.radians(60))
    point = np.array([[np.tan(np.radians(60)), 0.0, 1.0]])  # 60 degrees off-axis, in front
    assert np.isnan(camera.project(point)).all()
    inside = np.array([[0.99 * r_turn, 0.0, 1.0]])
    np.testing.assert_allclose(camera.unproject(camera.project(inside)), inside / np.linalg.norm(inside), atol=1e-9)


# ------------------------------------------------------------------------------- Jacobians

INTRINSICS = ("fx", "fy", "cx", "cy", "d")


def numeric_point_jacobian(camera: Camera, points: np.ndarray) -> np.ndarray:
    """(n, 2, 3) central differences of the pixels by each coordinate of the points, step 1e-6 of the depth."""
    h = 1e-6 * points[:, 2:]
    columns = [(camera.project(points + h * e) - camera.project(points - h * e)) / (2.0 * h) for e in np.eye(3)]
    return np.stack(columns, axis=2)


def numeric_intrinsics_jacobian(camera: Camera, points: np.ndarray) -> np.ndarray:
    """(n, 2, 5) central differences of the pixels by fx, fy, cx, cy, d (the pixels are linear in each)."""
    columns = []
    for name in INTRINSICS:
        h = 1e-3 * max(abs(getattr(camera, name)), 1.0)
        plus = replace(camera, **{name: getattr(camera, name) + h}).project(points)
        minus = replace(camera, **{name: getattr(camera, name) - h}).project(points)
        columns.append((plus - minus) / (2.0 * h))
    return np.stack(columns, axis=2)


@pytest.mark.parametrize("name", sorted(ALL_CAMERAS))
def test_project_jacobians_are_the_finite_differences(name):
    camera = ALL_CAMERAS[name]
    points = random_points_in_view(camera, 40, np.random.default_rng(11))
    uv, J_point, J_intrinsics = camera.project(points, jacobian=True)
    np.testing.assert_array_equal(uv, camera.project(points))
    assert J_point.shape == (40, 2, 3) and J_intrinsics.shape == (40, 2, 5)
    assert np.isfinite(J_point).all() and np.isfinite(J_intrinsics).all()
    scale = np.abs(J_point).max(axis=(1, 2))[:, None, None]  # ~ f / z
    np.testing.assert_allclose(J_point / scale, numeric_point_jacobian(camera, points) / scale, rtol=0, atol=1e-7)
    np.testing.assert_allclose(J_intrinsics, numeric_intrinsics_jacobian(camera, points), rtol=1e-8, atol=1e-9)


def test_project_jacobian_is_nan_where_points_are_not_imaged():
    camera = WIDE_INSIDE["640x480"]
    points = np.array([[0.1, 0.2, 1.0],                       # imaged
                       [0.1, 0.2, -1.0],                      # behind
                       [0.0, 0.0, 0.0],                       # the centre
                       [np.tan(np.radians(60)), 0.0, 1.0]])   # beyond the fold of d = -0.3
    with np.errstate(all="raise"):
        uv, J_point, J_intrinsics = camera.project(points, jacobian=True)
    assert np.isfinite(uv[0]).all() and np.isfinite(J_point[0]).all() and np.isfinite(J_intrinsics[0]).all()
    assert np.isnan(uv[1:]).all() and np.isnan(J_point[1:]).all() and np.isnan(J_intrinsics[1:]).all()


def test_project_unmasked_is_project_where_imaged_and_finite_elsewhere():
    """The solvers' model: the same pixels and Jacobians for imaged points; behind the camera the
    formula's value (the mirrored point's pixel), not NaN."""
    camera = LONG_FOCAL["d=-3.0"]
    points = random_points_in_view(camera, 30, np.random.default_rng(12))
    for masked, unmasked in zip(camera.project(points, jacobian=True), project_unmasked(points, camera, jacobian=True)):
        np.testing.assert_array_equal(unmasked, masked)
    np.testing.assert_array_equal(project_unmasked(points, camera), camera.project(points))
    behind = -points[:5]
    np.testing.assert_allclose(project_unmasked(behind, camera), camera.project(points[:5]), rtol=1e-15)
    assert np.isnan(camera.project(behind)).all()


# The removed calib/_projection.py's outputs (commit c2e85e5), captured before it went: four
# cameras (d = 3, -3, 0 long-focal, d = -0.3 wide), world points with one behind each camera.
PROJECTION_REFERENCE = Path(__file__).parent / "data" / "projection_reference.npz"


def test_project_unmasked_equals_the_removed_projection_module():
    ref = np.load(PROJECTION_REFERENCE)
    for k, intrinsics in enumerate(ref["intrinsics"]):
        points_cam = ref["points"][k] @ ref["R"][k].T + ref["t"][k]
        uv, J_point, J_intrinsics = project_unmasked(points_cam, Camera(*intrinsics, 0, 0), jacobian=True)
        np.testing.assert_allclose(uv, ref["uv"][k], rtol=1e-12, atol=0)
        np.testing.assert_allclose(J_point, ref["J_cam"][k], rtol=1e-12, atol=0)
        np.testing.assert_allclose(J_intrinsics, ref["J_intr"][k], rtol=1e-12, atol=0)


def test_pose_jacobian_of_pixels_equals_the_removed_projection_module():
    ref = np.load(PROJECTION_REFERENCE)
    for k, intrinsics in enumerate(ref["intrinsics"]):
        for phi, expected in zip(ref["phis"], ref["pose_jacobian"][k]):
            R = exp_so3(phi) @ ref["R"][k]
            _, J_point, _ = project_unmasked(ref["points"][k] @ R.T + ref["t"][k], Camera(*intrinsics, 0, 0),
                                              jacobian=True)
            np.testing.assert_allclose(pose_jacobian(ref["points"][k], R, phi, J_point), expected, rtol=1e-12, atol=0)


@pytest.mark.parametrize("angle", [0.0, 0.3])
def test_pose_jacobian_of_pixels_is_the_finite_differences(angle):
    """d pixels / d(phi, t) for cam_from_world = (exp(phi) R0, t), against central differences."""
    camera = LONG_FOCAL["d=3.0"]
    rng = np.random.default_rng(13)
    points_cam = random_points_in_view(camera, 20, rng) + [0.0, 0.0, 100.0]
    R0 = exp_so3([0.2, -0.1, 0.3])
    phi = angle * np.array([0.6, 0.0, -0.8])
    t = np.array([1.0, -2.0, 3.0])
    X = (points_cam - t) @ exp_so3(phi) @ R0  # world points with exp(phi) R0 X + t = points_cam

    def pixels(p):
        return project_unmasked(X @ (exp_so3(p[:3]) @ R0).T + p[3:], camera)

    p0, h = np.concatenate([phi, t]), np.array([1e-7] * 3 + [1e-4] * 3)
    numeric = np.stack([(pixels(p0 + h[i] * e) - pixels(p0 - h[i] * e)) / (2.0 * h[i])
                        for i, e in enumerate(np.eye(6))], axis=2)
    _, J_point, _ = project_unmasked(X @ (exp_so3(phi) @ R0).T + t, camera, jacobian=True)
    J = pose_jacobian(X, exp_so3(phi) @ R0, phi, J_point)
    np.testing.assert_allclose(J, numeric, rtol=1e-5, atol=1e-6 * np.abs(J).max())
