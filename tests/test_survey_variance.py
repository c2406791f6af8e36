"""calib.survey_variance: the pixel and survey variance components of a calibration's residuals."""

import numpy as np

from dmais_pipe.calib.survey_variance import estimate


def linear_calibration(rng, n_images=12, n_points=25, n_params=30):
    """A linear stand-in for a calibration: J (2N, n) and the unit survey Jacobian (2N, 3P) of every
    image seeing every point (a point's error moves its residuals in every image, differently)."""
    rows = 2 * n_images * n_points
    J = rng.normal(size=(rows, n_params))
    S = np.zeros((rows, 3 * n_points))
    for image in range(n_images):
        for point in range(n_points):
            row = 2 * (image * n_points + point)
            S[row:row + 2, 3 * point:3 * point + 3] = rng.normal(size=(2, 3))
    return J, S


def draws(rng, J, S, pixel, survey, given=None, n=300):
    """(n, 2) the estimated (pixel variance, survey sigma) of n draws of the errors and their fit."""
    H = J @ np.linalg.pinv(J)
    out = []
    for _ in range(n):
        e = pixel * rng.normal(size=len(J)) + S @ rng.normal(scale=survey, size=S.shape[1])
        if given is not None:
            e += given @ rng.normal(size=given.shape[1])
        found = estimate(J, e - H @ e, S, given)
        out.append((found.pixel_variance, found.survey_sigma))
    return np.array(out)


def test_both_components_are_found_without_bias():
    """Their means over 300 draws equal the variances drawn (pixel 0.3, survey 0.5 per unit), where
    the sum of squares alone, taken as pixel noise, is several times the pixel variance."""
    rng = np.random.default_rng(4)
    J, S = linear_calibration(rng)
    found = draws(rng, J, S, pixel=0.3, survey=0.5)
    assert abs(found[:, 0].mean() / 0.3**2 - 1) < 0.03
    assert abs(np.mean(found[:, 1] ** 2) / 0.5**2 - 1) < 0.05
    assert np.all(found[:, 1] > 0.35)


def test_no_survey_error_is_found_near_zero():
    rng = np.random.default_rng(5)
    J, S = linear_calibration(rng)
    found = draws(rng, J, S, pixel=0.3, survey=0.0, n=100)
    assert abs(found[:, 0].mean() / 0.3**2 - 1) < 0.03
    assert np.mean(found[:, 1] ** 2) < 0.02 * 0.3**2  # against a survey term the size of the noise


def test_given_points_share_is_taken_off():
    """Half the points with a known sigma (their share given) and half estimated: the estimate is of
    the second half's sigma, not inflated by the first's."""
    rng = np.random.default_rng(6)
    J, S = linear_calibration(rng, n_points=30)
    known, unknown = S[:, :45] * 0.8, S[:, 45:]
    found = draws(rng, J, unknown, pixel=0.3, survey=0.4, given=known)
    assert abs(np.mean(found[:, 1] ** 2) / 0.4**2 - 1) < 0.06
    assert abs(found[:, 0].mean() / 0.3**2 - 1) < 0.03


def test_without_unknown_points_nothing_is_estimated():
    rng = np.random.default_rng(7)
    J, S = linear_calibration(rng)
    found = estimate(J, rng.normal(size=len(J)), S[:, :0])
    assert not found.survey_estimable and found.survey_sigma == 0.0
    assert abs(found.pixel_variance - 1) < 0.1
