"""Tests of the synthetic image renderer: exact geometry, area coverage, effects, determinism."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dmais_pipe.camera import Camera
from dmais_pipe.geometry import Rigid3
from dmais_pipe.sim.render import (
    MarkerBoard,
    RenderSettings,
    board_pixel_bbox,
    coverage_image,
    render_image,
)
from dmais_pipe.sim.render import _linear_area_fraction

SMALL = Camera(2000.0, 2000.0, 159.5, 119.5, 0.0, 320, 240)
WIDE = Camera(500.0, 500.0, 320.3, 239.6, -0.3, 640, 480)
FULL = Camera(45000.0, 45000.0, 2051.2, 1497.6, 3.0, 4096, 3000)

QUIET = RenderSettings(read_noise_dn=0.0, shot_noise_gain=0.0, illumination_jitter=0.0)
FLAT = RenderSettings(read_noise_dn=0.0, shot_noise_gain=0.0, illumination_jitter=0.0,
                      background_contrast=0.0, vignetting=0.0, blur_sigma_px=0.0)

# A camera somewhere in the world, looking in some direction: exercises cam_from_world fully.
WORLD_FROM_CAM = Rigid3(Rotation.from_euler("zyx", [0.7, -0.4, 2.1]).as_matrix(), [12.0, -30.0, 250.0])
POSE = WORLD_FROM_CAM.inverse()


def board_at(camera: Camera, cam_from_world: Rigid3, pixel, distance: float, *, roll=0.0, tilt=0.0,
             tilt_axis=0.0, cols=2, rows=2, cell=1.0, polarity=1, margin=0.0) -> MarkerBoard:
    """A board whose centre projects to `pixel`, `distance` m along the ray, facing the camera and
    then rotated in-plane by `roll` and tilted by `tilt` about the in-plane axis at angle `tilt_axis`."""
    bearing = camera.unproject(np.asarray(pixel, dtype=float))[0]
    centre_cam = bearing * distance
    # Fronto-parallel to the ray: u, v orthogonal to the bearing, roughly image x and y.
    u = np.cross([0.0, 1.0, 0.0], bearing)
    u /= np.linalg.norm(u)
    v = np.cross(bearing, u)
    R = (Rotation.from_rotvec(tilt * (np.cos(tilt_axis) * u + np.sin(tilt_axis) * v))
         * Rotation.from_rotvec(roll * bearing)).as_matrix()
    world_from_cam = cam_from_world.inverse()
    return MarkerBoard(world_from_cam.apply(centre_cam), world_from_cam.R @ (R @ u), world_from_cam.R @ (R @ v),
                       cols, rows, cell, cell, polarity, margin)


def projected_corners(camera, cam_from_world, board) -> np.ndarray:
    return camera.project(cam_from_world.apply(board.corners()))


def refine(image, start) -> np.ndarray:
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 200, 1e-5)
    points = np.asarray(start, dtype=np.float32).reshape(-1, 1, 2).copy()
    return cv2.cornerSubPix(image, points, (5, 5), (-1, -1), criteria).reshape(-1, 2)


def start_offsets(n: int) -> np.ndarray:
    """1.5 px offsets in varying directions."""
    angles = 0.7 + 2.0 * np.pi * np.arange(n) / max(n, 1) * 0.618
    return 1.5 * np.column_stack([np.cos(angles), np.sin(angles)])


# ------------------------------------------------------------------------------ MarkerBoard


def test_corners_of_single_marker_is_origin():
    board = MarkerBoard(np.array([1.0, 2.0, 3.0]), np.array([1.0, 0, 0]), np.array([0, 0, -1.0]), 2, 2, 1.0, 1.0)
    np.testing.assert_allclose(board.corners(), [[1.0, 2.0, 3.0]])


def test_corners_of_board_are_row_major():
    board = MarkerBoard(np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), 4, 3, 0.5, 0.25)
    expected = [[a, b, 0.0] for b in (-0.125, 0.125) for a in (-0.5, 0.0, 0.5)]
    np.testing.assert_allclose(board.corners(), expected)


# ------------------------------------------------------------------------------ area coverage


def fronto_parallel_board(corner, z=10.0, angle=0.0) -> MarkerBoard:
    """A 2 m marker facing SMALL (identity pose) at depth z, its X-corner projecting to `corner`."""
    origin = np.array([(corner[0] - SMALL.cx) * z / SMALL.fx, (corner[1] - SMALL.cy) * z / SMALL.fy, z])
    u = np.array([np.cos(angle), np.sin(angle), 0.0])
    v = np.array([-np.sin(angle), np.cos(angle), 0.0])
    return MarkerBoard(origin, u, v, 2, 2, 1.0, 1.0)


@pytest.mark.parametrize("supersampling", [1, 4])
@pytest.mark.parametrize("fraction", [0.0, 0.0625, 0.3, 0.5, 0.77, 0.97])
def test_antialiasing_is_area_coverage(supersampling, fraction):
    """Fronto-parallel, no distortion: pixels across the vertical and the horizontal inner edge
    hold the analytic covered fraction (required: within 1 / s^2; single edges are exact)."""
    settings = RenderSettings(supersampling=supersampling, background_mean=0.5)
    corner = np.array([150.0 + fraction - 0.5, 100.0 + (1 - fraction) - 0.5])  # in pixel (row 100, col 150)
    image = coverage_image(SMALL, Rigid3.identity(), [fronto_parallel_board(corner)], settings, levels=(0.0, 1.0))
    tolerance = min(1.0 / supersampling**2, 1e-4)
    columns = np.arange(140, 161)
    # Row 60 crosses the vertical edge between cell (0, 0) (black, left) and (1, 0) (white, right).
    black = np.clip(corner[0] - (columns - 0.5), 0.0, 1.0)
    np.testing.assert_allclose(image[60, columns], 1.0 - black, atol=tolerance)
    # Column 190 crosses the horizontal edge between cell (1, 0) (white, above) and (1, 1) (black).
    rows = np.arange(90, 111)
    white = np.clip(corner[1] - (rows - 0.5), 0.0, 1.0)
    np.testing.assert_allclose(image[rows, 190], white, atol=tolerance)
    # Pixels away from edges are exactly the levels.
    assert image[60, 100] == 0.0 and image[60, 200] == 1.0 and image[150, 100] == 1.0 and image[150, 200] == 0.0


@pytest.mark.parametrize("sign_u, sign_v", [(1, 1), (1, -1), (-1, 1), (-1, -1)])
def test_edges_on_pixel_boundaries_are_crisp(sign_u, sign_v):
    """Edges running exactly along pixel boundaries (corners on the line) give no mixed pixels,
    whichever way the board axes point."""
    z = 10.0
    origin = np.array([(149.5 - SMALL.cx) * z / SMALL.fx, (99.5 - SMALL.cy) * z / SMALL.fy, z])
    board = MarkerBoard(origin, np.array([sign_u, 0.0, 0.0]), np.array([0.0, sign_v, 0.0]), 2, 2, 1.0, 1.0)
    image = coverage_image(SMALL, Rigid3.identity(), [board], levels=(0.0, 1.0))
    np.testing.assert_array_equal(np.unique(image[0:200, 50:250]), [0.0, 1.0])
    assert image[99, 149] != image[99, 150] and image[99, 149] != image[100, 149]


@pytest.mark.parametrize("supersampling", [1, 4])
def test_x_corner_pixel_is_area_coverage(supersampling):
    """The pixel holding the X-corner (crossed by two edges) holds its exact area."""
    settings = RenderSettings(supersampling=supersampling)
    for fx, fy in [(0.3, 0.7), (0.5, 0.5), (0.9, 0.15), (0.21, 0.33)]:
        corner = np.array([150.0 + fx - 0.5, 100.0 + fy - 0.5])
        image = coverage_image(SMALL, Rigid3.identity(), [fronto_parallel_board(corner)], settings, levels=(1.0, 0.0))
        black = fx * fy + (1 - fx) * (1 - fy)  # quadrants (0, 0) top-left and (1, 1) bottom-right
        assert image[100, 150] == pytest.approx(black, abs=1e-5)


@pytest.mark.parametrize("degrees", [3.0, 17.0, 45.0])
def test_slanted_edge_row_sums_are_exact_area(degrees):
    """An in-plane rotated edge: the black area in each pixel row equals the edge abscissa at the
    row centre (a straight edge is linear)."""
    corner = np.array([160.23, 120.71])
    board = fronto_parallel_board(corner, angle=np.radians(degrees))
    image = coverage_image(SMALL, Rigid3.identity(), [board], FLAT, levels=(1.0, 0.0))  # black = 1
    v = board.axis_v
    for row in range(60, 100):  # above the corner: black cell (0, 0) is left of the edge a = 0
        x_edge = corner[0] + (row - corner[1]) / v[1] * v[0]  # edge abscissa at the row centre
        left = int(x_edge) - 20  # inside the black cell on this row
        area = image[row, left: int(x_edge) + 5].astype(float).sum()
        assert area == pytest.approx(x_edge - (left - 0.5), abs=1e-4)


def test_coverage_converges_with_supersampling():
    """Tilted, rotated 4 x 3 board with margin and strong distortion: every mixed pixel is crossed
    by at most one line in each direction, so its area is exact and s does not matter."""
    board = board_at(WIDE, POSE, (400.0, 150.0), 8.0, roll=0.6, tilt=1.0, tilt_axis=0.3, cols=4, rows=3,
                     cell=0.5, margin=0.1)
    coarse = coverage_image(WIDE, POSE, [board], RenderSettings(supersampling=4, background_mean=0.5), (0.0, 1.0))
    fine = coverage_image(WIDE, POSE, [board], RenderSettings(supersampling=16, background_mean=0.5), (0.0, 1.0))
    difference = np.abs(coarse.astype(float) - fine)
    assert difference.max() < 1e-6


@pytest.mark.parametrize("supersampling", [2, 4])
def test_supersampled_pixels_approach_area(supersampling):
    """A white margin 0.4 px wide puts two parallel lines in one pixel: those pixels are
    supersampled; s x s samples reach the fine rendering within the sampling error."""
    board = board_at(SMALL, POSE, (160.0, 120.0), 20.0, roll=0.3, margin=0.004)
    coarse = coverage_image(SMALL, POSE, [board], RenderSettings(supersampling=supersampling, background_mean=0.0),
                            levels=(0.0, 1.0))
    fine = coverage_image(SMALL, POSE, [board], RenderSettings(supersampling=32, background_mean=0.0),
                          levels=(0.0, 1.0))
    difference = coarse.astype(float) - fine
    sampled = np.abs(difference) > 1e-6
    assert 100 < np.count_nonzero(sampled) < 1000  # the outline pixels along the black cells
    assert np.sqrt(np.mean(difference[sampled] ** 2)) < 2.4 / supersampling**2
    assert abs(difference.sum()) < 0.02 * np.count_nonzero(sampled)


def test_linear_area_fraction_matches_brute_force():
    rng = np.random.default_rng(1)
    c, p, q = rng.normal(size=(3, 200)) * np.array([[0.6], [1.0], [1.0]])
    q[:20] = 0.0  # axis-aligned lines
    grid = (np.arange(400) + 0.5) / 400 - 0.5
    x, y = np.meshgrid(grid, grid)
    brute = np.array([np.mean(ci + pi * x + qi * y < 0) for ci, pi, qi in zip(c, p, q)])
    np.testing.assert_allclose(_linear_area_fraction(c, p, q), brute, atol=2e-3)


# ------------------------------------------------------------------------------ X-corner positions


FULL_CASES = [  # pixel, roll, tilt, tilt axis, polarity
    ((3850.0, 2800.0), 0.0, 0.0, 0.0, 1),
    ((250.0, 200.0), 0.4, np.radians(60), 0.3, -1),
    ((3900.0, 230.0), 1.1, np.radians(45), 1.9, 1),
    ((300.0, 2760.0), -0.7, np.radians(60), -1.0, 1),
    ((2048.0, 300.0), 0.25, np.radians(30), 2.5, -1),
    ((1200.0, 2500.0), -0.2, np.radians(55), 0.8, -1),
]


@pytest.fixture(scope="module")
def full_scene():
    """One full-size 4096 x 3000 render, f = 45000, d = 3: ~200 px markers far off-centre and a
    4 x 3-cell board, with blur, texture and vignetting but no noise."""
    boards = [board_at(FULL, POSE, pixel, 450.0, roll=roll, tilt=tilt, tilt_axis=axis, polarity=pol)
              for pixel, roll, tilt, axis, pol in FULL_CASES]
    boards.append(board_at(FULL, POSE, (3300.0, 1900.0), 450.0, roll=0.3, tilt=np.radians(40), tilt_axis=0.5,
                           cols=4, rows=3, cell=0.5, margin=0.15))
    image = render_image(FULL, POSE, boards, np.random.default_rng(7), QUIET)
    return boards, image


def test_full_size_render_shape(full_scene):
    _, image = full_scene
    assert image.shape == (3000, 4096) and image.dtype == np.uint8


@pytest.mark.parametrize("case", range(len(FULL_CASES)))
def test_full_size_marker_centre_equals_projection(full_scene, case):
    boards, image = full_scene
    truth = projected_corners(FULL, POSE, boards[case])
    found = refine(image, truth + start_offsets(1))
    np.testing.assert_array_less(np.linalg.norm(found - truth, axis=1), 0.05)


def test_full_size_board_corners_equal_projection(full_scene):
    boards, image = full_scene
    truth = projected_corners(FULL, POSE, boards[-1])
    assert truth.shape == (6, 2)
    found = refine(image, truth + start_offsets(6))
    np.testing.assert_array_less(np.linalg.norm(found - truth, axis=1), 0.05)


WIDE_CASES = [  # pixel, roll, tilt, tilt axis, polarity
    ((540.0, 390.0), 0.0, 0.0, 0.0, 1),
    ((90.0, 80.0), 0.5, np.radians(60), 0.2, -1),
    ((560.0, 90.0), -0.9, np.radians(45), 2.0, 1),
    ((110.0, 400.0), 1.3, np.radians(60), -1.2, -1),
    ((330.0, 240.0), 0.7, np.radians(50), 1.0, 1),
]


@pytest.mark.parametrize("pixel, roll, tilt, axis, polarity", WIDE_CASES)
def test_wide_angle_marker_centre_equals_projection(pixel, roll, tilt, axis, polarity):
    """Strong barrel distortion (f = 500 px, d = -0.3; the model folds before the image corners)."""
    board = board_at(WIDE, POSE, pixel, 15.0, roll=roll, tilt=tilt, tilt_axis=axis, polarity=polarity)
    image = render_image(WIDE, POSE, [board], np.random.default_rng(3), QUIET)
    truth = projected_corners(WIDE, POSE, board)
    found = refine(image, truth + start_offsets(1))
    np.testing.assert_array_less(np.linalg.norm(found - truth, axis=1), 0.05)


def test_wide_angle_board_corners_equal_projection():
    board = board_at(WIDE, POSE, (420.0, 300.0), 12.0, roll=-0.4, tilt=np.radians(35), tilt_axis=2.2,
                     cols=4, rows=3, cell=0.5, margin=0.1, polarity=-1)
    image = render_image(WIDE, POSE, [board], np.random.default_rng(4), QUIET)
    truth = projected_corners(WIDE, POSE, board)
    found = refine(image, truth + start_offsets(6))
    np.testing.assert_array_less(np.linalg.norm(found - truth, axis=1), 0.05)


# ------------------------------------------------------------------------------ appearance


@pytest.mark.parametrize("polarity", [1, -1])
def test_polarity_of_cell_00(polarity):
    board = board_at(SMALL, POSE, (150.0, 110.0), 40.0, roll=0.3, tilt=0.5, polarity=polarity)
    image = coverage_image(SMALL, POSE, [board], FLAT)
    quarter = -0.25 * board.cell_u * board.axis_u - 0.25 * board.cell_v * board.axis_v
    u, v = SMALL.project(POSE.apply(board.origin + quarter))[0]
    value = image[int(round(v)), int(round(u))]
    assert value == pytest.approx(FLAT.black_level if polarity == 1 else FLAT.white_level)


def test_margin_is_white():
    board = board_at(SMALL, POSE, (160.0, 120.0), 40.0, margin=0.25)
    image = coverage_image(SMALL, POSE, [board], FLAT)
    inside_margin = board.origin - 1.12 * board.axis_u - 1.12 * board.axis_v
    u, v = SMALL.project(POSE.apply(inside_margin))[0]
    assert image[int(round(v)), int(round(u))] == pytest.approx(FLAT.white_level)


def test_determinism():
    board = board_at(SMALL, POSE, (150.0, 110.0), 40.0, roll=0.3, tilt=0.5)
    first = render_image(SMALL, POSE, [board], np.random.default_rng(11))
    again = render_image(SMALL, POSE, [board], np.random.default_rng(11))
    other = render_image(SMALL, POSE, [board], np.random.default_rng(12))
    np.testing.assert_array_equal(first, again)
    assert np.mean(first != other) > 0.5


def test_noise_level():
    """Flat grey, no texture, no vignetting: the std is that of shot + read noise."""
    settings = RenderSettings(background_contrast=0.0, vignetting=0.0, read_noise_dn=2.0, shot_noise_gain=0.1)
    image = render_image(SMALL, POSE, [], np.random.default_rng(5), settings).astype(float)
    expected = np.sqrt(0.1 * settings.background_mean + 2.0**2)
    assert image.mean() == pytest.approx(settings.background_mean, abs=0.1)
    assert image.std() == pytest.approx(np.sqrt(expected**2 + 1 / 12), rel=0.05)


def test_background_texture_statistics():
    settings = RenderSettings(read_noise_dn=0.0, shot_noise_gain=0.0, vignetting=0.0, blur_sigma_px=0.0)
    image = render_image(FULL, POSE, [], np.random.default_rng(9), settings).astype(float)
    assert image.mean() == pytest.approx(settings.background_mean, abs=1.0)
    assert image.std() == pytest.approx(settings.background_contrast, rel=0.1)


@pytest.mark.parametrize("vignetting", [0.15, 0.3])
def test_vignetting_falloff(vignetting):
    settings = RenderSettings(background_contrast=0.0, read_noise_dn=0.0, shot_noise_gain=0.0, vignetting=vignetting)
    image = render_image(SMALL, POSE, [], np.random.default_rng(0), settings).astype(float)
    centre = image[int(SMALL.cy), int(SMALL.cx)]
    assert centre == pytest.approx(settings.background_mean, abs=0.6)
    for corner in (image[0, 0], image[0, -1], image[-1, 0], image[-1, -1]):
        assert corner / centre == pytest.approx(1.0 - vignetting, abs=0.01)
    # Monotone along the diagonal from the centre.
    diagonal = image[np.arange(120, 240), np.arange(160, 280)]
    assert np.all(np.diff(diagonal) <= 0)


def test_illumination_jitter_scales_levels():
    settings = RenderSettings(read_noise_dn=0.0, shot_noise_gain=0.0, vignetting=0.0, illumination_jitter=0.3)
    board = board_at(SMALL, POSE, (160.0, 120.0), 20.0)
    whites = []
    for seed in range(6):
        image = render_image(SMALL, POSE, [board], np.random.default_rng(seed), settings)
        whites.append(float(image[60, 200]))  # inside white cell (1, 0)
    assert len(set(whites)) > 1
    assert all(0.7 * 205 - 1 <= w <= 1.3 * 205 + 1 or w == 255 for w in whites)


# ------------------------------------------------------------------------------ visibility


def test_board_behind_camera_leaves_image_empty():
    behind = board_at(SMALL, POSE, (160.0, 120.0), 20.0)
    centre_cam = POSE.apply(behind.origin)
    world_from_cam = POSE.inverse()
    mirrored = MarkerBoard(world_from_cam.apply(-centre_cam), behind.axis_u, behind.axis_v, 2, 2, 1.0, 1.0)
    assert board_pixel_bbox(SMALL, POSE, mirrored) is None
    empty = render_image(SMALL, POSE, [], np.random.default_rng(2))
    np.testing.assert_array_equal(render_image(SMALL, POSE, [mirrored], np.random.default_rng(2)), empty)


def test_board_outside_view_leaves_image_empty():
    aside = board_at(SMALL, POSE, (900.0, 120.0), 20.0)  # pixel far right of the 320-px image
    assert board_pixel_bbox(SMALL, POSE, aside) is None
    empty = render_image(SMALL, POSE, [], np.random.default_rng(2))
    np.testing.assert_array_equal(render_image(SMALL, POSE, [aside], np.random.default_rng(2)), empty)


def test_edge_on_board_is_skipped():
    board = board_at(SMALL, POSE, (160.0, 120.0), 20.0, tilt=np.radians(89))
    assert board_pixel_bbox(SMALL, POSE, board) is None
    flat = coverage_image(SMALL, POSE, [], FLAT)
    np.testing.assert_array_equal(coverage_image(SMALL, POSE, [board], FLAT), flat)


@pytest.mark.parametrize("camera, pixel, distance", [(SMALL, (315.0, 5.0), 40.0), (WIDE, (600.0, 440.0), 12.0),
                                                     (FULL, (4090.0, 2990.0), 450.0)])
def test_board_at_image_border(camera, pixel, distance):
    board = board_at(camera, POSE, pixel, distance, roll=0.2, tilt=0.4, margin=0.2)
    bbox = board_pixel_bbox(camera, POSE, board)
    assert bbox is not None
    x0, y0, x1, y1 = bbox
    assert 0 <= x0 < x1 <= camera.width and 0 <= y0 < y1 <= camera.height
    image = coverage_image(camera, POSE, [board], FLAT)
    changed = np.nonzero(image != FLAT.background_mean)
    assert len(changed[0]) > 0
    assert changed[0].min() >= y0 and changed[0].max() < y1 and changed[1].min() >= x0 and changed[1].max() < x1
    render_image(camera, POSE, [board], np.random.default_rng(0))


@pytest.mark.parametrize("camera", [SMALL, WIDE, FULL])
def test_bbox_contains_every_changed_pixel(camera):
    boards = [board_at(camera, POSE, (0.3 * camera.width, 0.6 * camera.height), 30.0 * camera.fx / 2000.0,
                       roll=0.5, tilt=1.0, tilt_axis=0.4, cols=4, rows=3, cell=0.5, margin=0.1)]
    for board in boards:
        x0, y0, x1, y1 = board_pixel_bbox(camera, POSE, board)
        image = coverage_image(camera, POSE, [board], FLAT)
        inside = np.zeros(image.shape, dtype=bool)
        inside[y0:y1, x0:x1] = True
        assert np.all(image[~inside] == FLAT.background_mean)
        # The box is tight: changed pixels reach within the padding of each side.
        ys, xs = np.nonzero(image != FLAT.background_mean)
        assert xs.min() - x0 <= 3 and x1 - 1 - xs.max() <= 3 and ys.min() - y0 <= 3 and y1 - 1 - ys.max() <= 3


def test_board_crossing_the_camera_plane():
    """A huge board extending behind the camera: only the part in front is drawn, no error."""
    world_from_cam = POSE.inverse()
    # The ground 1 m below the camera, centred under it, 200 m x 200 m: it is seen below the
    # horizon up to its far edge 100 m ahead, i.e. from normalized y = 0.01 (pixel row 139.5) down.
    origin_cam = np.array([0.0, 1.0, 0.0])
    u_cam = np.array([1.0, 0.0, 0.0])
    v_cam = np.array([0.0, 0.0, 1.0])
    board = MarkerBoard(world_from_cam.apply(origin_cam), world_from_cam.R @ u_cam, world_from_cam.R @ v_cam,
                        2, 2, 100.0, 100.0)
    assert board_pixel_bbox(SMALL, POSE, board) == (0, 138, 320, 240)
    image = coverage_image(SMALL, POSE, [board], FLAT)
    np.testing.assert_array_equal(image[:139], FLAT.background_mean)
    assert np.all(image[140:, :159] == FLAT.white_level) and np.all(image[140:, 160:] == FLAT.black_level)
    render_image(SMALL, POSE, [board], np.random.default_rng(0))


def test_nearer_board_occludes_farther():
    far = board_at(SMALL, POSE, (160.0, 120.0), 40.0, polarity=1)
    near = board_at(SMALL, POSE, (160.0, 120.0), 20.0, polarity=-1)
    image = coverage_image(SMALL, POSE, [near, far], FLAT)
    np.testing.assert_array_equal(image, coverage_image(SMALL, POSE, [near], FLAT))
