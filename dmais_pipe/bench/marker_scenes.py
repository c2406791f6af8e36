"""Seeded synthetic marker scenes with known truth, for the marker benchmarks and tests.

A scene is a 640 x 480 image of a few single diagonal markers (2 x 2 cells, no margin, on the
renderer's textured ground), each of a given apparent size, foreshortened by a given tilt about a
random axis, randomly rolled, of random polarity; the truth is the projection of each marker's
centre. Image formation (blur, noise, and the aerial effects of `RenderSettings`) is the
simulator's own `render_image`.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial.transform import Rotation

from ..camera import Camera
from ..geometry import Rigid3
from ..sim.render import MarkerBoard, RenderSettings, render_image

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
