"""The compiled scoring of the shadow start (`markers/_shadow.pyx`): the best straight step of log rings,
the symmetric centre's choice among a grid of rings and the shadowed-X test's best line, against numpy's
(`shadow._best_step_numpy`, `shadow._most_symmetric_x_numpy`, `detect._best_shadow_line_numpy`), to the
last bit, on seeded rings and images: X's crossed by a shadow edge, outline corners, texture, flat rings
and ties."""

import importlib

import numpy as np
import pytest

from dmais_pipe.markers import shadow
from dmais_pipe.markers.rings import ImageParts

detect = importlib.import_module("dmais_pipe.markers.detect")  # the module, not the package's function


def _log_rings(rng, n: int, k: int) -> np.ndarray:
    """(n, k) log rings: X's (random edges and levels) with a step of log light beyond a random line,
    T-junctions, noise, and flat or rounded rings whose steps tie."""
    angle = 2.0 * np.pi * (np.arange(k) + 0.5) / k
    edges = rng.uniform(0, np.pi, (n, 1))
    spread = rng.uniform(0.4, 1.2, (n, 1)) * np.pi / 2
    sector = (np.mod(angle[None] - edges, np.pi) < spread)
    bright, dark = rng.uniform(4.5, 5.5, (n, 1)), rng.uniform(2.5, 3.8, (n, 1))
    logs = np.where(sector, bright, dark)
    phi, t = rng.uniform(0, 2 * np.pi, (n, 1)), rng.uniform(-0.7, 0.7, (n, 1))
    logs += np.where(np.cos(angle[None] - phi) > t, -rng.uniform(0.1, 1.5, (n, 1)), 0.0)
    logs += rng.normal(0.0, 1.0, (n, 1)) ** 2 * 0.02 * rng.normal(0.0, 1.0, (n, k))
    logs[::7] = np.where(np.cos(angle - rng.uniform(0, 2 * np.pi)) > 0.2, 5.0, 3.0)[None]  # outline-like step
    logs[1::11] = rng.normal(4.0, 0.3, (len(logs[1::11]), k))  # texture
    logs[2::13] = 3.0  # flat: every step ties
    logs[3::17] = np.round(logs[3::17])  # steps of equal size
    return logs


@pytest.mark.parametrize("seed, k", [(0, 48), (1, 48), (2, 48), (3, 24), (4, 47)])
def test_best_step_is_numpys_to_the_last_bit(seed, k):
    rng = np.random.default_rng(seed)
    logs = _log_rings(rng, 600, k)
    got, want = shadow._best_step(logs), shadow._best_step_numpy(logs)
    for compiled, numpy_value in zip(got[:3], want[:3]):
        np.testing.assert_array_equal(compiled, numpy_value)
    found = np.isfinite(want[0])
    np.testing.assert_array_equal(got[3][found], want[3][found])
    assert k != 48 or 100 < found.sum() < 550  # both outcomes are compared


@pytest.mark.parametrize("seed, k", [(5, 24), (6, 24), (7, 48), (8, 23)])
def test_shadow_line_is_numpys_to_the_last_bit(seed, k):
    rng = np.random.default_rng(seed)
    logs = _log_rings(rng, 500, k)
    for contrast in (20.0, 60.0, 150.0):
        for min_quality in (0.5, 0.7):
            got = detect._best_shadow_line(logs, contrast, min_quality)
            want = detect._best_shadow_line_numpy(logs, contrast, min_quality)
            for compiled, numpy_value in zip(got, want):
                np.testing.assert_array_equal(compiled, numpy_value)
    assert 50 < detect._best_shadow_line(logs, 60.0, 0.7)[0].sum() < 450  # both outcomes are compared


def test_best_step_of_no_rings():
    for compiled, numpy_value in zip(shadow._best_step(np.zeros((0, 48))), shadow._best_step_numpy(np.zeros((0, 48)))):
        assert compiled.shape == numpy_value.shape


def _shadowed_image(rng, shape=(300, 400)) -> np.ndarray:
    """(h, w) float32: X-corners on a grey ground with noise, half of it in a shadow."""
    height, width = shape
    y, x = np.mgrid[0:height, 0:width].astype(float)
    image = np.full(shape, 90.0)
    for cx, cy in rng.uniform([40, 40], [width - 40, height - 40], (12, 2)):
        a, b = rng.uniform(0, np.pi, 2)
        inside = np.maximum(np.abs(x - cx), np.abs(y - cy)) < 20
        dx, dy = x - cx, y - cy
        sign = np.sign(np.cos(a) * dx + np.sin(a) * dy) * np.sign(np.cos(b) * dx - np.sin(b) * dy)
        image = np.where(inside, np.where(sign > 0, 200.0, 30.0), image)
    image *= np.where(0.6 * x + 0.8 * y > 0.5 * (width + height) * 0.7, 0.4, 1.0)
    return (image + rng.normal(0, 2.0, shape)).astype(np.float32)


@pytest.mark.parametrize("seed", range(3))
def test_most_symmetric_x_is_numpys_to_the_last_bit(seed):
    rng = np.random.default_rng(seed)
    image = _shadowed_image(rng)
    grid = np.array([(x, y) for y in range(-4, 5) for x in range(-4, 5)], dtype=float)
    points = rng.uniform([-10, -10], [410, 310], (50, 1, 2)) + grid[None]
    points[::5] = np.round(points[::5])
    for k in (24, 48):
        np.testing.assert_array_equal(shadow._most_symmetric_x(image, points, k),
                                      shadow._most_symmetric_x_numpy(image, points, k))
    parts = ImageParts([(0, 0, 192, 300), (256, 0, 400, 300)], image.shape)
    for pixels, top, left in zip(parts.pixels, parts.tops, parts.lefts):
        pixels[...] = image[top:top + pixels.shape[0], left:left + pixels.shape[1]]
    np.testing.assert_array_equal(shadow._most_symmetric_x(parts, points, 24),
                                  shadow._most_symmetric_x_numpy(parts, points, 24))


def test_most_symmetric_of_rings_without_four_level_changes_is_numpys():
    # Rings whose point-symmetric part does not change level four times score 0 without their other
    # numbers (`_shadow.not_four`): the choice stays numpy's where such rings lie among X's, tie with
    # each other (0 and -0), or come with a NaN ring or an infinite one (their numbers made).
    from dmais_pipe.markers import _shadow
    from dmais_pipe.markers.rings import ring_stats

    rng = np.random.default_rng(21)
    groups, k = 9, 24
    logs = _log_rings(rng, 40 * groups, k).astype(np.float32)
    logs[::3] = rng.normal(4.0, 0.5, (len(logs[::3]), k))  # mostly other than four changes
    logs[5::groups * 2] = 3.0  # flat: no change, dark level the mean
    logs[7 * groups + 4, 3] = np.nan
    logs[11 * groups + 2, 5] = np.inf
    logs[13 * groups:14 * groups] = 2.0  # a group of ties
    wide = logs.astype(np.float64)
    symmetric = 0.5 * (wide + np.roll(wide, k // 2, axis=1))
    quality, high, low, _ = ring_stats(symmetric)
    with np.errstate(invalid="ignore"):
        want = np.argmax((quality * (high - low)).reshape(-1, groups), axis=1)
    np.testing.assert_array_equal(_shadow.most_symmetric(logs, groups), want)
    assert np.mean(quality == 0.0) > 0.3


def test_most_symmetric_x_takes_the_first_of_equals():
    flat = np.full((40, 40), 50.0, dtype=np.float32)  # every ring scores 0
    points = np.array([[[10.0, 10.0], [20.0, 20.0], [30.0, 30.0]]])
    np.testing.assert_array_equal(shadow._most_symmetric_x(flat, points, 24), [[10.0, 10.0]])
    np.testing.assert_array_equal(shadow._most_symmetric_x_numpy(flat, points, 24), [[10.0, 10.0]])


def test_shadowed_markers_in_windows_are_the_whole_image_s():
    """On scenes whose markers a shadow edge crosses (the effects benchmark's shadow row), the detections
    and rejections in windows about the markers (the compiled start on `ImageParts`) are the whole
    image's there, to the last bit."""
    from dmais_pipe.bench.marker_effects import EFFECTS, effect_scenes
    from dmais_pipe.markers.windows import detect_in_windows

    found = rejected = 0
    for image, truth, _, _ in effect_scenes(EFFECTS["shadow"], 5, 208):
        boxes = np.column_stack([truth - 60.0, truth + 60.0])
        whole = detect.detect(image, with_rejected=True)
        for frame, windowed in zip(whole, detect_in_windows(image, boxes, with_rejected=True)):
            uv = frame[["u", "v"]].to_numpy(dtype=float)
            inside = ((uv[:, None] >= boxes[None, :, :2]) & (uv[:, None] <= boxes[None, :, 2:])).all(axis=2).any(axis=1)
            want = frame[inside].sort_values(["v", "u"], ignore_index=True)
            assert windowed.sort_values(["v", "u"], ignore_index=True).equals(want)
        found, rejected = found + len(whole[0]), rejected + int((whole[1]["reason"] == shadow.SHADOW_REASON).sum())
    assert found >= 20 and rejected >= 1
