"""The marker fit's compiled core (`markers/_xfit.pyx`) against the numpy expressions it replaces
(`xfit.model` and `xfit._normal_equations`), on seeded synthetic windows, and `xfit.fit` through it
against the fit of the same model in numpy."""

import numpy as np
import pytest
from scipy.special import erf

from dmais_pipe.markers import _xfit, xfit


def _windows(seed: int, radius: float = 12.0, n: int = 5):
    """Blurred X-corners with noise in windows of `radius` about centres near the corners: params
    (n, 7) a little off the truth, pixels x, y, values, weights (n, k)."""
    rng = np.random.default_rng(seed)
    centre = rng.uniform(30.0, 70.0, (n, 2))
    t1 = rng.uniform(0.0, np.pi, n)
    truth = np.column_stack([centre + rng.uniform(-0.5, 0.5, (n, 2)), t1, t1 + rng.uniform(0.6, 2.5, n),
                             rng.uniform(0.6, 2.0, n), rng.uniform(80.0, 160.0, n),
                             rng.choice([-1.0, 1.0], n) * rng.uniform(30.0, 70.0, n)])
    x, y, _, weights = xfit.window(np.zeros((100, 100), np.float32), centre, radius)
    values = xfit.model(truth, x, y, jacobian=False)[0] + rng.normal(0.0, 2.0, x.shape)
    weights[0, ::7] = 0.0  # zero weights count as in numpy
    start = truth + np.column_stack([rng.normal(0.0, 0.3, (n, 2)), rng.normal(0.0, 0.05, (n, 2)),
                                     rng.normal(0.0, 0.1, n), rng.normal(0.0, 5.0, (n, 2))])
    return start, x, y, values, weights


def _close(got: np.ndarray, want: np.ndarray, rtol: float = 1e-10) -> None:
    """got equals want to rtol of each array's largest magnitude (sums of terms of both signs)."""
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=0.0, atol=rtol * np.max(np.abs(want)))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_values_and_normal_equations_are_numpys(seed):
    params, x, y, values, weights = _windows(seed)
    model, jac = xfit.model(params, x, y)
    _close(_xfit.values(params, x, y), model)
    residual = model - values
    cost, hess, grad = xfit._normal_equations(residual, jac, weights)
    got = _xfit.normal_equations(params, x, y, values, weights)
    for compiled, numpy_value in zip(got, (cost, hess, grad)):
        _close(compiled, numpy_value)
    wj = (jac * weights[..., None]).transpose(0, 2, 1)
    meat = np.matmul(wj * weights[:, None, :], jac)
    with_meat = _xfit.normal_equations(params, x, y, values, weights, meat=True)
    _close(with_meat[3], meat)
    for a, b in zip(with_meat[:3], got):
        np.testing.assert_array_equal(a, b)


def test_far_from_both_edges_erf_is_scipys():
    # The core takes erf as +-1 beyond 6 (where scipy's rounds to it): a sharp corner in a wide
    # window, most pixels far from both edges.
    params, x, y, _, _ = _windows(4, radius=25.0, n=2)
    params[:, 4], params[:, 5] = 0.3, 0.0
    product = _erf_product(params, x, y)
    assert np.mean(np.abs(product) == 1.0) > 0.5
    np.testing.assert_allclose(_xfit.values(params, x, y), params[:, 6:7] * product, rtol=1e-13, atol=0.0)


def _erf_product(params, x, y):
    """erf(l1 / sqrt(2) s) erf(l2 / sqrt(2) s) of `xfit.model`, by scipy."""
    px, py, t1, t2, s = (params[:, i:i + 1] for i in range(5))
    dx, dy = x - px, y - py
    scale = np.sqrt(2.0) * s
    return erf((np.cos(t1) * dx + np.sin(t1) * dy) / scale) * erf((np.cos(t2) * dx + np.sin(t2) * dy) / scale)


def test_non_finite_params_give_non_finite_sums():
    params, x, y, values, weights = _windows(5, n=2)
    params[1, 6] = np.inf
    cost, hess, grad = _xfit.normal_equations(params, x, y, values, weights)
    assert np.isfinite(cost[0]) and not np.isfinite(cost[1]) and not np.all(np.isfinite(hess[1]))


@pytest.mark.parametrize("seed", [6, 7])
def test_fit_through_the_core_is_the_numpy_fit(seed):
    params, x, y, values, weights = _windows(seed)

    def numpy_model(p, px, py, jacobian=True):  # the same model, not `xfit.model`: the numpy path
        return xfit.model(p, px, py, jacobian)

    compiled = xfit.fit(params, x, y, values, weights)
    reference = xfit.fit(params, x, y, values, weights, model=numpy_model)
    assert np.all(compiled[3]) and np.array_equal(compiled[3], reference[3])
    np.testing.assert_allclose(compiled[0][:, :2], reference[0][:, :2], rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(compiled[1], reference[1], rtol=1e-8)
    np.testing.assert_allclose(compiled[2], reference[2], rtol=1e-10)


@pytest.mark.parametrize("seed", [8, 9])
def test_meat_of_some_rows_is_the_meat_pass(seed):
    # J^T W^2 J of the rows asked, made in the pass of the normal equations: the same numbers as a
    # pass with `meat` of its own, the other rows' zero, the rest of the pass unchanged.
    params, x, y, values, weights = _windows(seed, n=6)
    rows = np.array([True, False, True, True, False, False])
    plain = _xfit.normal_equations(params, x, y, values, weights)
    every = _xfit.normal_equations(params, x, y, values, weights, meat=True)
    some = _xfit.normal_equations(params, x, y, values, weights, meat_rows=rows)
    for a, b in zip(some[:3], plain):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(some[3][rows], every[3][rows])
    assert not some[3][~rows].any()


@pytest.mark.parametrize("seed", [10, 11])
def test_kept_erf_factors_are_the_ones_made_again(seed):
    # `values` keeps the two erf factors; the normal equations of params that differ in the levels
    # only, taking them from there, are those that make them again, to the last bit.
    params, x, y, values, weights = _windows(seed, radius=20.0)
    erfs = np.empty((2,) + x.shape)
    ab = _xfit.values(np.column_stack([params[:, :5], np.zeros(len(params)), np.ones(len(params))]), x, y, erfs)
    np.testing.assert_array_equal(ab, 0.0 + 1.0 * erfs[0] * erfs[1])
    _close(erfs[0] * erfs[1], _erf_product(params, x, y), rtol=1e-13)
    for meat in (False, True):
        made = _xfit.normal_equations(params, x, y, values, weights, meat=meat)
        kept = _xfit.normal_equations(params, x, y, values, weights, meat=meat, erfs=erfs)
        for a, b in zip(kept, made):
            np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError):
        _xfit.normal_equations(params, x, y, values, weights, erfs=erfs[:, :2])


@pytest.mark.parametrize("seed, iterations, shift", [(12, 40, 0.3), (13, 40, 2.0), (14, 2, 0.3), (15, 1, 1.0)])
def test_fit_with_its_covariance_in_the_last_pass_is_the_fit_with_a_pass_of_its_own(seed, iterations, shift,
                                                                                     monkeypatch):
    # The fit of the compiled model makes J^T W^2 J in the pass of a small step (the last where it is
    # taken), and for fits that end otherwise (too few iterations, the damping's limit) in a pass of
    # their own; with the start's erf factors kept by `linear_levels`: the same bits as the fit that
    # makes the whole covariance's parts again at its end and every erf again.
    params, x, y, values, weights = _windows(seed, radius=15.0, n=7)
    params[:, :2] += np.random.default_rng(seed).normal(0.0, shift, (len(params), 2))
    params[-1, 4] = np.nan  # a fit that never starts
    erfs = np.empty((2,) + x.shape)
    start = xfit.linear_levels(params, x, y, values, weights, erfs)
    folded = xfit.fit(start, x, y, values, weights, iterations, erfs=erfs)
    monkeypatch.setattr(xfit, "_is_compiled", lambda fitted: False)  # every pass of its own, as before
    own = xfit.fit(xfit.linear_levels(params, x, y, values, weights), x, y, values, weights, iterations)
    for a, b in zip(folded, own):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("radius", [3.0, 7.25, 25.0])
def test_window_is_numpys(radius):
    # `xfit.window`'s positions, pixels and taper weights in one compiled pass (`_xfit.window_pixels`):
    # numpy's to the last bit, at the image's borders, beyond them and about a NaN centre, on a float
    # image and on ImageParts.
    from dmais_pipe.markers.rings import ImageParts

    rng = np.random.default_rng(int(radius * 4))
    image = rng.uniform(0.0, 255.0, (120, 160)).astype(np.float32)
    centre = np.vstack([rng.uniform(-5.0, 165.0, (40, 2)), [[0.0, 0.0], [159.5, 119.5], [np.nan, 30.0],
                                                          [80.49999999, 60.5]]])
    parts = ImageParts([(0, 0, 64, 120), (128, 0, 160, 120)], image.shape)
    for pixels, top, left in zip(parts.pixels, parts.tops, parts.lefts):
        pixels[...] = image[top:top + pixels.shape[0], left:left + pixels.shape[1]]
    for img in (image, parts):
        for got, want in zip(xfit.window(img, centre, radius), xfit._window_numpy(img, centre, radius)):
            assert got.dtype == want.dtype
            np.testing.assert_array_equal(got, want)
