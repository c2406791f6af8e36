"""What real aerial photographs do to markers, as optional steps of `render.render_image`.

Every effect is off by default (RenderSettings) and, when on, draws only from its own random
streams, so turning one on changes nothing else in the image:

- ground texture: band-limited noise (a difference of Gaussians of white noise) of a given
  contrast and grain, e.g. grass (~25 DN, 1 px), gravel (~20 DN, 2-3 px), asphalt (~8 DN, 0.5 px);
- cast shadows: a straight shadow edge (Gaussian penumbra) through a marker, the light on its far
  side reduced by `shadow_depth`, within a disc 1.5 marker sizes in radius (the shadow of a pole, a
  wire, a tree), before the optical blur; overlapping shadows darken as one (their union);
- occluders: a flat object of random grey hiding the outer third of one cell of a board;
- motion blur: a line PSF of a given length along the flight direction, centred (the corner stays
  at its mid-exposure position); defocus: a disc PSF;
- JPEG compression of the 8-bit output; 12-bit (or any 9-16-bit) data in a uint16 image.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.special import ndtr

SHADOW_EXTENT = 1.5  # radius of the shadowed disc, in marker sizes
_SUPERSAMPLE = 8
_SHADOW_SUPERSAMPLE = 4  # samples per pixel and axis of the shade map (the boards use 8: their edges are sharp)
_SHADOW_ROWS = 64  # pixel rows of the shade map made at once


def band_limited_noise(shape, rng: np.random.Generator, std: float, grain_px: float) -> np.ndarray:
    """(h, w) float32 zero-mean noise of standard deviation `std`, its energy at ~`grain_px` scales."""
    white = rng.standard_normal(shape, dtype=np.float32)
    fine = cv2.GaussianBlur(white, (0, 0), 0.5 * grain_px)
    coarse = cv2.GaussianBlur(white, (0, 0), grain_px)
    band = fine - coarse
    band *= np.float32(std / max(float(band.std()), 1e-12))
    return band


def occlude_and_shadow(image: np.ndarray, camera, cam_from_world, boards, rng: np.random.Generator,
                       settings) -> None:
    """Paint occluders and cast shadows over the boards chosen by settings (in place, float32).

    The same numbers are drawn for every board whatever the settings, so the choice of boards and
    the geometry depend only on the seed and the fractions. Overlapping shadows darken once (the
    union of the shaded areas): in either shadow the direct sunlight is gone, and the skylight left
    does not depend on how many objects block the sun.
    """
    shade = np.zeros_like(image) if settings.shadow_fraction > 0 else None
    for board in boards:
        draws = rng.uniform(size=9)
        centre, size = _board_in_image(camera, cam_from_world, board)
        if centre is None:
            continue
        if draws[0] < settings.occlusion_fraction:
            _occlude(image, camera, cam_from_world, board, draws[1:5])
        if draws[5] < settings.shadow_fraction:
            offset = (draws[6:8] - 0.5) * 0.5 * size
            _shadow(shade, centre + offset, np.pi * draws[8] * 2.0, size, settings)
    if shade is not None:
        image *= 1.0 - np.float32(settings.shadow_depth) * shade


def _board_in_image(camera, cam_from_world, board):
    """Pixel centre (2,) and size (largest extent of the outline, px) of a board, or (None, None)
    when it is behind the camera or outside the image."""
    points = cam_from_world.apply(board.to_world(np.vstack([[0.0, 0.0], board.outline_coordinates()])))
    if np.any(points[:, 2] <= 0):
        return None, None
    uv = camera.project(points)
    if not np.all(np.isfinite(uv)) or not camera.in_image(uv[:1], margin=0)[0]:
        return None, None
    return uv[0], float(np.max(uv[1:].max(axis=0) - uv[1:].min(axis=0)))


def _occlude(image, camera, cam_from_world, board, draws) -> None:
    """Hide the outer third of one cell (chosen by draws (4,)) behind a flat object of random grey."""
    i, j = int(draws[0] * board.cols), int(draws[1] * board.rows)
    half_u, half_v = board.half_size
    a0, b0 = -half_u + i * board.cell_u, -half_v + j * board.cell_v
    a1, b1 = a0 + board.cell_u, b0 + board.cell_v
    if draws[2] < 0.5:  # a strip along the cell's side farther from the board centre, in a
        a0, a1 = (a1 - board.cell_u / 3, a1) if a0 + a1 > 0 else (a0, a0 + board.cell_u / 3)
    else:
        b0, b1 = (b1 - board.cell_v / 3, b1) if b0 + b1 > 0 else (b0, b0 + board.cell_v / 3)
    corners = np.array([[a0, b0], [a1, b0], [a1, b1], [a0, b1]])
    uv = camera.project(cam_from_world.apply(board.to_world(corners)))
    if not np.all(np.isfinite(uv)):
        return
    level = 40.0 + 160.0 * draws[3]
    _fill_polygon(image, uv, level)


def _fill_polygon(image: np.ndarray, uv: np.ndarray, level: float) -> None:
    """Blend `level` into image (in place) by the area coverage of the polygon uv (k, 2) (px)."""
    height, width = image.shape
    x0, y0 = np.maximum(np.floor(uv.min(axis=0)).astype(int) - 1, 0)
    x1, y1 = np.minimum(np.ceil(uv.max(axis=0)).astype(int) + 2, [width, height])
    if x1 <= x0 or y1 <= y0:
        return
    s = _SUPERSAMPLE
    mask = np.zeros(((y1 - y0) * s, (x1 - x0) * s), np.uint8)
    # Pixel (i, j) covers [j - 0.5, j + 0.5]: sub-pixel k of it is at (j - 0.5) * s + k + 0.5.
    poly = np.rint(((uv - [x0, y0] + 0.5) * s - 0.5) * 16).astype(np.int32)
    cv2.fillPoly(mask, [poly], 1, lineType=cv2.LINE_8, shift=4)
    coverage = cv2.resize(mask.astype(np.float32), (x1 - x0, y1 - y0), interpolation=cv2.INTER_AREA)
    patch = image[y0:y1, x0:x1]
    patch *= 1.0 - coverage
    patch += np.float32(level) * coverage


def _shadow(shade: np.ndarray, point: np.ndarray, angle: float, size: float, settings) -> None:
    """Add to the shade map (h, w) in [0, 1] (in place, by maximum) the side of the line through
    `point` (2,) at `angle` beyond its normal, with a Gaussian penumbra, within a disc of
    SHADOW_EXTENT x size about it; each pixel the mean over its area, as a camera integrates it
    (sampled at the pixel centres, the default 0.3 px penumbra puts up to ~0.09 of a pixel's shade
    on the wrong side of the edge, varying with the edge's sub-pixel phase)."""
    height, width = shade.shape
    radius = SHADOW_EXTENT * max(size, 4.0)
    x0, y0 = np.maximum(np.floor(point - radius).astype(int), 0)
    x1, y1 = np.minimum(np.ceil(point + radius).astype(int) + 1, [width, height])
    if x1 <= x0 or y1 <= y0:
        return
    for top in range(y0, y1, _SHADOW_ROWS):  # in strips: a large board's shadow spans millions of samples
        bottom = min(top + _SHADOW_ROWS, y1)
        covered = _shade_coverage(point, angle, radius, settings.shadow_penumbra_px, top, bottom, x0, x1)
        np.maximum(shade[top:bottom, x0:x1], covered, out=shade[top:bottom, x0:x1])


def _shade_coverage(point, angle, radius, penumbra, y0, y1, x0, x1) -> np.ndarray:
    """(y1 - y0, x1 - x0) float32 mean shade over the area of each pixel of rows y0..y1, columns
    x0..x1 (`_shadow`'s edge and disc; _SHADOW_SUPERSAMPLE^2 samples a pixel)."""
    s = _SHADOW_SUPERSAMPLE
    # Pixel (i, j) covers [j - 0.5, j + 0.5]: sub-pixel k of it is at j - 0.5 + (k + 0.5) / s.
    ys, xs = ((np.mgrid[y0 * s:y1 * s, x0 * s:x1 * s] + 0.5) / s - 0.5).astype(np.float32)
    dx, dy = xs - np.float32(point[0]), ys - np.float32(point[1])
    distance = np.float32(np.cos(angle)) * dx + np.float32(np.sin(angle)) * dy
    edge = ndtr(distance / max(penumbra, 1e-3)).astype(np.float32)
    disc = np.clip(radius - np.hypot(dx, dy), 0.0, 1.0)  # the shadow's far outline: 1 px soft
    return (edge * disc).reshape(y1 - y0, s, x1 - x0, s).mean(axis=(1, 3))


def blur_motion_and_defocus(image: np.ndarray, settings) -> np.ndarray:
    """image (h, w) float32 convolved with the motion-blur line and the defocus disc, if any."""
    if settings.motion_blur_px > 0:
        image = cv2.filter2D(image, -1, motion_kernel(settings.motion_blur_px, settings.motion_direction_deg),
                             borderType=cv2.BORDER_REFLECT)
    if settings.defocus_px > 0:
        image = cv2.filter2D(image, -1, disc_kernel(settings.defocus_px), borderType=cv2.BORDER_REFLECT)
    return image


def motion_kernel(length: float, direction_deg: float) -> np.ndarray:
    """(k, k) float32 PSF of a uniform motion of `length` px along `direction_deg`, centred, sum 1."""
    half = int(np.ceil(0.5 * length)) + 1
    kernel = np.zeros((2 * half + 1, 2 * half + 1), np.float32)
    t = np.linspace(-0.5 * length, 0.5 * length, 64 * max(int(np.ceil(length)), 1) + 1)
    a = np.radians(direction_deg)
    x, y = half + t * np.cos(a), half + t * np.sin(a)
    ix, iy = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - ix).astype(np.float32), (y - iy).astype(np.float32)
    for ox, oy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(kernel, (iy + oy, ix + ox), w)
    return kernel / kernel.sum()


def disc_kernel(radius: float) -> np.ndarray:
    """(k, k) float32 PSF of a uniform disc of `radius` px (area coverage, supersampled), sum 1."""
    half = int(np.ceil(radius)) + 1
    s = _SUPERSAMPLE
    offs = (np.arange((2 * half + 1) * s) + 0.5) / s - half - 0.5
    yy, xx = np.meshgrid(offs, offs, indexing="ij")
    inside = (xx**2 + yy**2 <= radius**2).astype(np.float32)
    kernel = inside.reshape(2 * half + 1, s, 2 * half + 1, s).mean(axis=(1, 3))
    return kernel / kernel.sum()


def quantize(image: np.ndarray, settings) -> np.ndarray:
    """The output image: uint8 (JPEG-compressed when jpeg_quality > 0), or uint16 holding
    bit_depth-bit data (levels scaled from 8-bit DN to 2**bit_depth - 1; no JPEG)."""
    if settings.bit_depth > 8:
        top = float(2 ** int(settings.bit_depth) - 1)
        image *= np.float32(top / 255.0)
        np.clip(image, 0.0, top, out=image)
        image += np.float32(0.5)
        return image.astype(np.uint16)
    np.clip(image, 0.0, 255.0, out=image)
    image += np.float32(0.5)
    image = image.astype(np.uint8)
    if settings.jpeg_quality > 0:
        ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(settings.jpeg_quality)])
        image = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE)
    return image
