"""The compiled bilinear samples of the ring tests (`markers/_rings.pyx`) against cv2.remap, which
they replace, `rings.ImageParts` read through them against the whole image, and the compiled ring
statistics, clean radii and centring steps (`markers/_centring.pyx`) against numpy's, to the last bit."""

import math
import types

import cv2
import numpy as np
import pytest

from dmais_pipe.markers import _rings, centring
from dmais_pipe.markers.rings import (RADII, ImageParts, _clean_radius, _ring_stats, clean_radius, ring_sample,
                                     ring_stats, sample)


def _cv2_remap(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(n,) cv2.remap's INTER_LINEAR, BORDER_REPLICATE samples of float32 image at float32 xy (n, 2)."""
    out = np.empty(len(xy), dtype=np.float32)
    for s in range(0, len(xy), 30000):  # SHRT_MAX rows a call
        chunk = xy[s:s + 30000]
        out[s:s + 30000] = cv2.remap(image, chunk[:, :1].copy(), chunk[:, 1:].copy(), cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_REPLICATE).ravel()
    return out


def _positions(rng, shape, n: int = 40000) -> np.ndarray:
    """(n, 2) float32 positions over an image of shape (h, w) and 5 px beyond, some on whole and 1/32 px."""
    height, width = shape
    xy = np.column_stack([rng.uniform(-5, width + 5, n), rng.uniform(-5, height + 5, n)]).astype(np.float32)
    xy[::97] = np.round(xy[::97])
    xy[::89] = np.round(xy[::89] * 32) / 32
    return xy


@pytest.mark.parametrize("seed", range(6))
def test_samples_are_cv2_remaps(seed):
    rng = np.random.default_rng(seed)
    shape = tuple(rng.integers(2, 600, 2))
    image = (rng.normal(0.0, 1.0, shape) * 10 ** rng.uniform(-3, 5)).astype(np.float32)
    xy = _positions(rng, shape)
    np.testing.assert_array_equal(sample(image, xy), _cv2_remap(image, xy))
    view = image[1:, 2:-1]  # rows and columns of a larger buffer
    np.testing.assert_array_equal(_rings.sample(view, xy), _cv2_remap(np.ascontiguousarray(view), xy))


def test_positions_that_are_not_finite_sample_nan():
    image = np.arange(12, dtype=np.float32).reshape(3, 4)
    xy = np.array([[np.nan, 1.0], [1.0, np.nan], [np.inf, 1.0], [-np.inf, 1.0], [1e9, 1.0], [-1e9, 2.0]], np.float32)
    got = sample(image, xy)
    np.testing.assert_array_equal(got, _cv2_remap(image, xy))
    assert np.isnan(got[:4]).all() and got[4] == 7.0 and got[5] == 8.0


def test_parts_sample_as_the_whole_image():
    rng = np.random.default_rng(7)
    image = rng.normal(100.0, 30.0, (700, 900)).astype(np.float32)
    parts = ImageParts([(0, 0, 192, 180), (448, 300, 900, 700)], image.shape)
    for pixels, top, left in zip(parts.pixels, parts.tops, parts.lefts):
        pixels[...] = image[top:top + pixels.shape[0], left:left + pixels.shape[1]]
    inside = np.vstack([_positions(rng, (160, 170)), _positions(rng, (380, 430)) + [460, 310]]).astype(np.float32)
    np.testing.assert_array_equal(parts.sample(inside), _cv2_remap(image, inside))
    owner = parts.owners(inside[:, 0], inside[:, 1])
    np.testing.assert_array_equal(_rings.owners(inside[:, 0], inside[:, 1], parts._cells, parts.CELL_PX), owner)
    odd = np.array([[np.nan, 5.0], [5.0, np.inf], [-1e30, 1e30], [2e4, -3.0]], np.float32)
    with np.errstate(invalid="ignore"):  # numpy's conversion of NaN and inf
        want = parts.owners(odd[:, 0], odd[:, 1])
    np.testing.assert_array_equal(_rings.owners(odd[:, 0], odd[:, 1], parts._cells, parts.CELL_PX), want)


@pytest.mark.parametrize("k", [3, 8, 9, 24, 47, 48, 130])
def test_ring_stats_are_numpys_to_the_last_bit(k):
    rng = np.random.default_rng(k)
    rings = rng.normal(0.0, 1.0, (300, k)) * 10 ** rng.uniform(-3, 4, (300, 1))
    rings[::5] = np.round(rings[::5])  # samples equal to the ring's mean
    angle = 2.0 * np.pi * (np.arange(k) + 0.5) / k
    rings[1::7] = 40.0 * np.sign(np.cos(2.0 * angle + rng.uniform(0, np.pi)))[None] + rng.normal(0, 1, (1, k))  # X's
    rings[3, 1], rings[4] = np.nan, 5.0
    for compiled, numpy_value in zip(ring_stats(rings), _ring_stats(rings)):
        np.testing.assert_array_equal(compiled, numpy_value)
    assert k < 8 or (ring_stats(rings)[0][1::7] > 0.5).all()


def _numpy_with_libm_exp() -> types.SimpleNamespace:
    """numpy's namespace with exp libm's, element by element: the compiled centring calls libm's exp, and
    numpy's own SIMD exp (x86-64 with AVX-512) differs from it in the last bit."""
    names = {name: getattr(np, name) for name in dir(np) if not name.startswith("__")}
    return types.SimpleNamespace(**{**names, "exp": np.vectorize(math.exp, otypes=[float])})


@pytest.mark.parametrize("converge, steps, shift", [(False, 4, 3.0), (True, 40, 2.0), (False, 4, None)])
def test_compiled_centring_steps_are_numpys(converge, steps, shift, monkeypatch):
    monkeypatch.setattr(centring, "np", _numpy_with_libm_exp())
    rng = np.random.default_rng(11)
    yy, xx = np.mgrid[0:300, 0:400]
    image = cv2.GaussianBlur((rng.normal(100, 20, (300, 400)) + 60 * np.sign((xx - 200.3) * (yy - 150.6)))
                             .astype(np.float32), (0, 0), 1.2)
    starts = np.vstack([[[200, 150], [203.2, 148.1], [np.nan, 3], [2, 2], [399, 150], [198.6, 153.9]],
                        rng.uniform(0, 1, (100, 2)) * [400, 300]])
    limit = np.linspace(0.5, 5, len(starts)) if shift is None else np.full(len(starts), shift)
    parts = ImageParts([(0, 0, 192, 180), (256, 100, 400, 300)], image.shape)
    for pixels, top, left in zip(parts.pixels, parts.tops, parts.lefts):
        pixels[...] = image[top:top + pixels.shape[0], left:left + pixels.shape[1]]
    for img in (image, parts):
        want = centring._refine_fixed_numpy(img, starts, 5.0, steps, 0.01, limit, converge)
        np.testing.assert_array_equal(centring._refine_fixed(img, starts, 5.0, steps, 0.01, limit, converge), want)
        assert np.isfinite(want[:, 0]).sum() >= 5


def test_an_image_of_doubles_is_sampled_by_cv2_as_before():
    rng = np.random.default_rng(12)
    image = rng.normal(0.0, 50.0, (40, 60))
    xy = _positions(rng, image.shape, 2000)
    np.testing.assert_array_equal(sample(image, xy), _cv2_remap(image, xy).astype(np.float32))


def test_compiled_clean_radius_is_numpys():
    rng = np.random.default_rng(13)
    yy, xx = np.mgrid[0:300, 0:400]
    image = cv2.GaussianBlur((rng.normal(100, 5, (300, 400)) + 60 * np.sign((xx - 200.3) * (yy - 150.6)))
                             .astype(np.float32), (0, 0), 1.0)
    image[:, 300:] = 40 + rng.normal(0, 5, (300, 100))  # an outline at 300 px
    uv = np.vstack([[[200.3, 150.6], [201, 150], [np.nan, 5], [5, 5], [299, 150]],
                    rng.uniform(0, 1, (100, 2)) * [400, 300], [200.3, 100.9] + rng.normal(0, 1.5, (50, 2))])
    parts = ImageParts([(0, 0, 192, 180), (256, 100, 400, 300)], image.shape)
    for pixels, top, left in zip(parts.pixels, parts.tops, parts.lefts):
        pixels[...] = image[top:top + pixels.shape[0], left:left + pixels.shape[1]]
    for img in (image, parts):
        for min_quality, radii in ((0.6, RADII), (0.7, RADII[RADII < 8.0])):
            want = _clean_radius(img, uv, min_quality, radii, 8.0)
            np.testing.assert_array_equal(clean_radius(img, uv, min_quality, radii), want)
    assert _clean_radius(image, uv[:1], 0.6, RADII, 8.0)[0] > 50.0


@pytest.mark.parametrize("seed", range(3))
def test_ring_samples_are_the_samples_at_their_sums(seed):
    rng = np.random.default_rng(seed)
    image = rng.normal(100.0, 30.0, (700, 900)).astype(np.float32)
    parts = ImageParts([(0, 0, 192, 180), (448, 300, 900, 700)], image.shape)
    for pixels, top, left in zip(parts.pixels, parts.tops, parts.lefts):
        pixels[...] = image[top:top + pixels.shape[0], left:left + pixels.shape[1]]
    centres = np.vstack([rng.uniform(-5, 905, (300, 2)), rng.uniform([450, 300], [900, 700], (300, 2))])
    centres[::7] = np.round(centres[::7])
    centres[3] = np.nan
    circle = 3.5 * np.column_stack([np.cos(np.arange(8)), np.sin(np.arange(8))])
    offsets = np.vstack([5.0 * rng.normal(size=(40, 2)), circle])
    for img in (image, parts, image.astype(np.float64)):
        want = sample(img, centres[:, None, :] + offsets[None])
        np.testing.assert_array_equal(ring_sample(img, centres, offsets), want)
    grid = centres[:60].reshape(6, 10, 2)
    np.testing.assert_array_equal(ring_sample(parts, grid, offsets), sample(parts, grid[:, :, None, :] + offsets))


def test_parts_pixels_as_numpys_gather():
    rng = np.random.default_rng(11)
    image = rng.normal(100.0, 30.0, (700, 900)).astype(np.float32)
    parts = ImageParts([(0, 0, 192, 180), (448, 300, 900, 700), (256, 0, 320, 40)], image.shape)
    for pixels, top, left in zip(parts.pixels, parts.tops, parts.lefts):
        pixels[...] = image[top:top + pixels.shape[0], left:left + pixels.shape[1]]
    ys, xs = rng.integers(-70, 770, (50, 40)), rng.integers(-70, 970, (50, 40))
    np.testing.assert_array_equal(parts[ys, xs], parts._gathered(ys, xs))
    inside = (rng.integers(0, 180, 500), rng.integers(0, 192, 500))
    np.testing.assert_array_equal(parts[inside], image[inside])
    assert parts[ys.astype(np.int32), xs].dtype == np.float32
