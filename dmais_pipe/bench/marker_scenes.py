"""Seeded synthetic marker scenes with known truth, for the marker benchmarks and tests.

A scene is a 640 x 480 image of a few single diagonal markers (2 x 2 cells, no margin, on the
renderer's textured ground), each of a given apparent size, foreshortened by a given tilt about a
random axis, randomly rolled, of random polarity; the truth is the projection of each marker's
centre. Image formation (blur, noise, and the aerial effects of `RenderSettings`) is the
simulator's own `render_image`.

`textured_scene`: a 12 MP image (TEXTURE_CAMERA) of ten markers of 30-500 px on band-limited
random ground (white noise blurred, as grass or gravel in sun), the boards painted by the
renderer's `coverage_image`.
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ..camera import Camera
from ..geometry import Rigid3
from ..sim.render import MarkerBoard, RenderSettings, coverage_image, render_image

CAMERA = Camera(2000.0, 2000.0, 319.7, 239.4, 0.0, 640, 480)
POSE = Rigid3.identity()
SLOTS = np.array([[107.0, 120.0], [320.0, 120.0], [533.0, 120.0],
                  [107.0, 360.0], [320.0, 360.0], [533.0, 360.0]])  # marker centres, px
MARKER_M = 2.0  # side of a marker (2 x 2 cells), metres


def marker_board(pixel, size_px: float, tilt_deg: float, roll: float, tilt_axis: float, polarity: int,
                 camera: Camera = CAMERA) -> MarkerBoard:
    """A 2 x 2-cell marker whose centre projects to `pixel` (2,), `size_px` wide when seen face-on,
    turned by `tilt_deg` about an in-plane axis at angle `tilt_axis` and rolled by `roll` (radians)."""
    distance = camera.fx * MARKER_M / size_px
    bearing = camera.unproject(np.asarray(pixel, dtype=float))[0]
    u = np.cross([0.0, 1.0, 0.0], bearing)
    u /= np.linalg.norm(u)
    v = np.cross(bearing, u)
    tilt = np.radians(tilt_deg)
    R = (Rotation.from_rotvec(tilt * (np.cos(tilt_axis) * u + np.sin(tilt_axis) * v))
         * Rotation.from_rotvec(roll * bearing)).as_matrix()
    cell = 0.5 * MARKER_M
    return MarkerBoard(bearing * distance, R @ u, R @ v, 2, 2, cell, cell, polarity, 0.0)


def marker_scene(rng: np.random.Generator, size_px: float, tilt_deg: float, settings: RenderSettings,
                 slots: np.ndarray = SLOTS) -> tuple[np.ndarray, np.ndarray, list[MarkerBoard]]:
    """(image (480, 640) uint8 (uint16 when settings.bit_depth > 8), truth (n, 2), boards) of one
    marker per slot (n, 2), each jittered by up to 10 px, with random roll, tilt axis and polarity."""
    boards = []
    for slot in slots:
        pixel = slot + rng.uniform(-10, 10, 2)
        boards.append(marker_board(pixel, size_px, tilt_deg, rng.uniform(-np.pi, np.pi),
                                   rng.uniform(0, np.pi), int(rng.choice([-1, 1]))))
    image = render_image(CAMERA, POSE, boards, rng, settings)
    truth = np.concatenate([CAMERA.project(POSE.apply(b.corners())) for b in boards])
    return image, truth, boards


def regime_settings(blur_px: float, noise_dn: float, base: RenderSettings = RenderSettings()) -> RenderSettings:
    """The simulator's defaults with Gaussian blur `blur_px`, read noise `noise_dn` (no shot noise,
    so the noise is exactly the stated one) and no vignetting."""
    return replace(base, blur_sigma_px=blur_px, read_noise_dn=noise_dn, shot_noise_gain=0.0, vignetting=0.0)


def starts(truth: np.ndarray, rng: np.random.Generator, low: float = 0.3, high: float = 1.5) -> np.ndarray:
    """Starting points (n, 2): truth (n, 2) moved by low...high px in random directions."""
    angle = rng.uniform(0, 2 * np.pi, len(truth))
    radius = rng.uniform(low, high, len(truth))
    return truth + radius[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])


TEXTURE_CAMERA = Camera(8000.0, 8000.0, 1999.5, 1499.5, 0.0, 4000, 3000)
GROUND_DN = 110.0  # mean of the textured ground
MARKER_MEAN_DN = 120.0  # mean of a marker's two levels (those of 35 / 205 DN)
TEXTURE_SLOTS = np.array([[400.0 + 800.0 * i, 750.0 + 1500.0 * j] for j in range(2) for i in range(5)])


def ground_texture(shape: tuple[int, int], rng: np.random.Generator, std_dn: float, blur_px: float,
                   optical_blur_px: float) -> np.ndarray:
    """(h, w) float32 zero-mean ground texture to paint before the optical blur `optical_blur_px`:
    white noise blurred so that the image shows it blurred by `blur_px` in all (>= the optical
    blur) with standard deviation `std_dn`."""
    texture = rng.standard_normal(shape, dtype=np.float32)
    extra = np.sqrt(max(blur_px**2 - optical_blur_px**2, 0.0))
    if extra > 0:
        texture = cv2.GaussianBlur(texture, (0, 0), extra)
    seen = cv2.GaussianBlur(texture, (0, 0), optical_blur_px) if optical_blur_px > 0 else texture
    texture *= np.float32(std_dn / max(float(seen.std()), 1e-12))
    return texture


def textured_scene(rng: np.random.Generator, texture_dn: float, texture_blur_px: float, blur_px: float = 0.8,
                   noise_dn: float = 2.0, sizes_px: tuple[float, float] = (30.0, 500.0), max_tilt_deg: float = 45.0,
                   camera: Camera = TEXTURE_CAMERA, slots: np.ndarray = TEXTURE_SLOTS,
                   contrasts_dn: tuple[float, float] | None = None):
    """(image (h, w) uint8, truth (n, 2)) of one marker per slot (n, 2) (jittered by up to 100 px;
    size log-uniform in `sizes_px`, foreshortened by up to `max_tilt_deg`, random roll and
    polarity, levels 35 / 205 DN scaled by 1 +- 0.1, or with `contrasts_dn` (low, high) levels
    MARKER_MEAN_DN -+ half a contrast log-uniform in it) on ground of mean GROUND_DN and texture
    `texture_dn` std blurred by `texture_blur_px` (`ground_texture`), all under a Gaussian optical
    blur `blur_px` and read noise `noise_dn`."""
    boards = []
    for slot in slots:
        size = float(np.exp(rng.uniform(*np.log(sizes_px))))
        boards.append(marker_board(slot + rng.uniform(-100, 100, 2), size, rng.uniform(0, max_tilt_deg),
                                   rng.uniform(-np.pi, np.pi), rng.uniform(0, np.pi), int(rng.choice([-1, 1])),
                                   camera))
    levels = marker_levels(rng, len(boards), contrasts_dn)
    flat = RenderSettings(background_mean=0.0)
    painted = coverage_image(camera, POSE, boards, flat, levels)
    ground = coverage_image(camera, POSE, boards, replace(flat, background_mean=1.0), np.zeros((len(boards), 2)))
    image = ground * (GROUND_DN + ground_texture(ground.shape, rng, texture_dn, texture_blur_px, blur_px)) + painted
    if blur_px > 0:
        image = cv2.GaussianBlur(image, (0, 0), blur_px, borderType=cv2.BORDER_REFLECT)
    image += rng.normal(0.0, noise_dn, image.shape).astype(np.float32)
    truth = np.concatenate([camera.project(POSE.apply(b.corners())) for b in boards] or [np.zeros((0, 2))])
    return np.clip(image + 0.5, 0, 255).astype(np.uint8), truth


def marker_levels(rng: np.random.Generator, count: int, contrasts_dn: tuple[float, float] | None = None) -> np.ndarray:
    """(count, 2) dark and bright levels (DN) of `count` markers: 35 / 205 DN scaled by 1 +- 0.1
    (within 0.7-1.3), or MARKER_MEAN_DN -+ half a contrast log-uniform in `contrasts_dn` (low, high)."""
    if contrasts_dn is None:
        factors = np.clip(1.0 + 0.1 * rng.standard_normal(count), 0.7, 1.3)
        return np.column_stack([35.0 * factors, 205.0 * factors])
    contrast = np.exp(rng.uniform(*np.log(contrasts_dn), count))
    return MARKER_MEAN_DN + 0.5 * np.column_stack([-contrast, contrast])
