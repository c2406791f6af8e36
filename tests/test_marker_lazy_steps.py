"""Work the marker job leaves out or makes in one compiled pass, against what it replaces, to the last bit:
the 16-bit scale's order statistics counted over the strided samples (`_rings.strided_ranks_u16`, no copy of
them) against np.percentile, and the refinement's start with the saddle's parameters made only where the
ring is no X (`refine._initial_params`) against the saddle's for every row."""

import importlib

import cv2
import numpy as np
import pytest

from dmais_pipe.markers import _rings
from dmais_pipe.markers.detect import _dn_scale, _percentile_u16
from dmais_pipe.markers.rings import ImageParts, ring_offsets, ring_params, sample

refine = importlib.import_module("dmais_pipe.markers.refine")  # the module (markers exports a function of its name)


def _uint16(rng, kind: int, n: int) -> np.ndarray:
    if kind == 0:
        return rng.integers(0, 65536, n).astype(np.uint16)
    if kind == 1:
        return (rng.integers(0, 3, n) * 30000).astype(np.uint16)
    if kind == 2:
        return np.full(n, rng.integers(0, 65536), dtype=np.uint16)
    return np.clip(rng.normal(40000, 9000, n), 0, 65535).astype(np.uint16)


@pytest.mark.parametrize("kind", range(4))
def test_strided_percentile_of_uint16_is_numpys(kind):
    rng = np.random.default_rng(120 + kind)
    for n in (1, 2, 3, 7, 100, 1001, 100722, *rng.integers(1, 5000, 30)):
        values = _uint16(rng, kind, int(n))
        for step in (1, 2, 3, 122, int(n) + 5):
            for q in (99.5, 50.0, 0.0, 100.0, 12.3, 99.99):
                want = float(np.percentile(values[::step], q))
                got = _percentile_u16(values, q, step)  # contiguous: counted over the strided samples
                assert type(got) is float and got == want, (n, step, q)
                assert _percentile_u16(values[::2], q, step) == float(np.percentile(values[::2][::step], q))


def test_strided_ranks_are_the_sorted_samples():
    rng = np.random.default_rng(125)
    values = _uint16(rng, 3, 5003)
    for step in (1, 4, 77):
        ordered = np.sort(values[::step])
        for low, high in ((0, 0), (0, 1), (10, 11), (len(ordered) - 1, len(ordered) - 1), (3, 40)):
            assert _rings.strided_ranks_u16(values, step, low, high) == (ordered[low], ordered[high])
    with pytest.raises(ValueError):
        _rings.strided_ranks_u16(values, 1, 0, len(values))


def test_dn_scale_of_16_bit_images_is_numpys():
    rng = np.random.default_rng(126)
    for shape in ((1000, 1234), (3000, 4096), (7, 9), (1, 1)):
        image = np.clip(rng.normal(30000, 12000, shape), 0, 65535).astype(np.uint16)
        step = max(1, image.size // 100000)
        assert _dn_scale(image) == max(float(np.percentile(image.reshape(-1)[::step], 99.5)) / 220.0, 1e-6)
    view = np.clip(rng.normal(30000, 12000, (900, 1300)), 0, 65535).astype(np.uint16)[:, 100:]
    assert _dn_scale(view) == max(float(np.percentile(view.reshape(-1)[::max(1, view.size // 100000)], 99.5))
                                  / 220.0, 1e-6)


def _initial_params_of_every_saddle(img, start, radius):
    """`refine._initial_params` as it was: the saddle's parameters for every row, the ring's where it is an X."""
    rho = np.clip(0.6 * np.nan_to_num(radius, nan=refine.MIN_RADIUS), 2.5, 12.0)
    values = sample(img, start[:, None, :] + rho[:, None, None] * ring_offsets(1.0)[None]).astype(float)
    params = refine._saddle_params(img, start, radius)
    ring = ring_params(start, values)
    ok = np.isfinite(ring[:, 0])
    params[ok] = ring[ok]
    return params


def test_initial_params_make_the_saddle_only_where_the_ring_is_no_x():
    rng = np.random.default_rng(127)
    yy, xx = np.mgrid[0:300, 0:400]
    sharp = 100 + 60 * np.sign((xx - 200.3) * (yy - 150.6))
    image = np.where(xx < 300, cv2.GaussianBlur(sharp.astype(np.float32), (0, 0), 1.0),
                     cv2.GaussianBlur(sharp.astype(np.float32), (0, 0), 9.0))  # too blurred for the ring beyond 300 px
    image = (image + rng.normal(0, 3, image.shape)).astype(np.float32)
    image[:, 330:] = cv2.GaussianBlur((100 + 60 * np.sign((xx - 350.2) * (yy - 80.4))).astype(np.float32),
                                      (0, 0), 6.0)[:, 330:]
    start = np.vstack([[[200.3, 150.6], [201.1, 149.2], [350.2, 80.4], [351.0, 81.0], [5, 5], [np.nan, 3]],
                       rng.uniform(0, 1, (60, 2)) * [400, 300], [200.3, 150.6] + rng.normal(0, 1.5, (30, 2)),
                       [350.2, 80.4] + rng.normal(0, 2.0, (30, 2))])
    radius = rng.choice([3.0, 4.0, 6.5, 8.0, 12.0, np.nan], len(start))
    parts = ImageParts([(0, 0, 256, 300), (320, 0, 400, 300)], image.shape)
    for pixels, top, left in zip(parts.pixels, parts.tops, parts.lefts):
        pixels[...] = image[top:top + pixels.shape[0], left:left + pixels.shape[1]]
    for img in (image, parts):
        want = _initial_params_of_every_saddle(img, start, radius)
        got = refine._initial_params(img, start, radius)
        assert got.tobytes() == want.tobytes()
        ring_only = np.isfinite(ring_params(start, sample(img, start[:, None, :] + np.clip(
            0.6 * np.nan_to_num(radius, nan=refine.MIN_RADIUS), 2.5, 12.0)[:, None, None] * ring_offsets(1.0)[None]
        ).astype(float))[:, 0])
        assert ring_only.sum() >= 20 and (~ring_only & np.isfinite(want[:, 0])).sum() >= 5  # both kinds of start


@pytest.mark.parametrize("seed", range(4))
def test_rings_inside_a_part_sample_as_every_position_alone(seed):
    """The ring sampler's rings whose extremes lie inside their part (read without clamps) and those at and
    beyond its edges, against `sample` at every position (cv2.remap's arithmetic, tests/test_marker_sampling.py)."""
    from dmais_pipe.markers.rings import ring_sample
    rng = np.random.default_rng(130 + seed)
    image = (rng.normal(0.0, 1.0, (300, 460)) * 10 ** rng.uniform(-2, 4)).astype(np.float32)
    parts = ImageParts([(0, 0, 192, 180), (256, 100, 460, 300)], image.shape)
    for pixels, top, left in zip(parts.pixels, parts.tops, parts.lefts):
        pixels[...] = image[top:top + pixels.shape[0], left:left + pixels.shape[1]]
    centres = np.vstack([rng.uniform(-0.1, 1.1, (200, 2)) * [470, 310], [[0.0, 0.0], [458.0, 298.0], [191.0, 179.0],
                                                                         [np.nan, 5.0], [96.5, 90.25], [350.0, 200.0]]])
    centres = np.vstack([centres, rng.uniform(0, 1, (300, 2)) * [460, 300]])
    for radius in (0.0, 1.0, 2.5, 4.0, 30.0, 148.5):
        for k in (24, 48):
            offsets = radius * np.column_stack([np.cos(2 * np.pi * (np.arange(k) + 0.5) / k),
                                                np.sin(2 * np.pi * (np.arange(k) + 0.5) / k)])
            for img in (image, parts):
                want = sample(img, centres[:, None, :] + offsets)
                assert ring_sample(img, centres, offsets).tobytes() == want.tobytes(), (radius, k)


@pytest.mark.parametrize("contrast", [1e-6, 1e-3, 0.05, 1.0, 3.0])
def test_symmetric_choice_skipping_rings_below_the_best_is_numpys(contrast):
    """`_shadow.most_symmetric` leaves out a ring whose sample range cannot reach the best score so far:
    the choice stays numpy's (the first of the largest quality x contrast of the rings' point-symmetric
    parts) on X's of every contrast down to a few float32 steps, among noise, flat rings and ties."""
    from dmais_pipe.markers import _shadow
    from dmais_pipe.markers.rings import ring_stats

    rng = np.random.default_rng(int(contrast * 1e6) % 1000 + 150)
    groups, k, n = 81, 24, 60
    angle = 2.0 * np.pi * (np.arange(k) + 0.5) / k
    edges = rng.uniform(0, np.pi, (n * groups, 1))
    x = np.sign(np.cos(angle[None] - edges) * np.cos(angle[None] - edges - rng.uniform(0.6, 1.4, (n * groups, 1))))
    level = rng.uniform(0.0, 11.0, (n * groups, 1))
    logs = level + contrast * rng.uniform(0.1, 1.0, (n * groups, 1)) * x + contrast * rng.normal(0, 0.3, (n * groups, k))
    logs[::7] = level[::7]  # flat
    logs[3::11] = logs[2::11][:len(logs[3::11])]  # ties with the ring before
    logs = logs.astype(np.float32)
    symmetric = 0.5 * (logs.astype(np.float64) + np.roll(logs.astype(np.float64), k // 2, axis=1))
    quality, high, low, _ = ring_stats(symmetric)
    want = np.argmax((quality * (high - low)).reshape(n, groups), axis=1)
    np.testing.assert_array_equal(_shadow.most_symmetric(logs, groups), want)
