"""The image-wide numbers' order statistics without a partition (`detect._percentile_u16`: the 16-bit
scale's percentile from the values' counts; `detect._median_of_abs`: the clutter's median of |band| by
the float32 bits) against np.percentile and np.median, to the last bit."""

import numpy as np
import pytest

from dmais_pipe.markers.detect import _dn_scale, _median_of_abs, _percentile_u16


def _uint16(rng, kind: int, n: int) -> np.ndarray:
    if kind == 0:
        return rng.integers(0, 65536, n).astype(np.uint16)
    if kind == 1:
        return (rng.integers(0, 3, n) * 30000).astype(np.uint16)
    if kind == 2:
        return np.full(n, rng.integers(0, 65536), dtype=np.uint16)
    if kind == 3:
        return np.clip(rng.normal(40000, 9000, n), 0, 65535).astype(np.uint16)
    return rng.integers(65530, 65536, n).astype(np.uint16)


@pytest.mark.parametrize("kind", range(5))
def test_percentile_of_uint16_is_numpys(kind):
    rng = np.random.default_rng(40 + kind)
    for n in (1, 2, 3, 7, 100, 1001, 100722, *rng.integers(1, 5000, 40)):
        values = _uint16(rng, kind, int(n))
        for step in (1, 3):
            for q in (99.5, 50.0, 0.0, 100.0, 12.3, 99.99):
                got = _percentile_u16(values[::step], q)
                assert type(got) is float and got == float(np.percentile(values[::step], q)), (n, step, q)


def test_dn_scale_of_a_16_bit_image_is_numpys():
    rng = np.random.default_rng(3)
    image = np.clip(rng.normal(30000, 12000, (1000, 1234)), 0, 65535).astype(np.uint16)
    want = max(float(np.percentile(image.reshape(-1)[::12], 99.5)) / 220.0, 1e-6)
    assert _dn_scale(image) == want


@pytest.mark.parametrize("kind", range(5))
def test_median_of_abs_is_numpys(kind):
    rng = np.random.default_rng(80 + kind)
    for n in (1, 2, 3, 8, 101, 6400, 102400, *rng.integers(1, 3000, 30)):
        values = rng.normal(0.0, 10.0 ** rng.integers(-3, 4), int(n)).astype(np.float32)
        if kind == 1:
            values = np.round(values)  # ties, zeros of both signs
        elif kind == 2:
            values[:] = values[0]
        elif kind == 3:
            values *= np.float32(1e-38)  # subnormals
        elif kind == 4 and n > 3:
            values[::3] = np.nan
        got, want = _median_of_abs(values), np.median(np.abs(values))
        assert type(got) is type(want) and np.float32(got).tobytes() == np.float32(want).tobytes(), n
        assert float(1.4826 * got) == float(1.4826 * want) or (np.isnan(got) and np.isnan(want))
