"""calib.survey_variance: the pixel and survey variance components of a calibration's residuals."""

import numpy as np

from dmais_pipe.calib.survey_variance import estimate, pixel_variance


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


def test_pixel_variance_leaves_out_the_survey_the_intrinsics_and_the_priors():
    """A fit of pixel rows (noise 0.1) and prior rows (unit variance): the survey errors (0.5 per
    unit) and a fixed error of parameters held constant (intrinsics, moving every image's residuals)
    put several times the pixel noise into the sum of squares; the estimate from outside their span
    is the pixel variance, without bias (mean over 200 draws), where r.r / dof is far above it."""
    rng = np.random.default_rng(8)
    J, S = linear_calibration(rng)
    priors = 40
    J = np.vstack([J, rng.normal(size=(priors, J.shape[1]))])
    S = np.vstack([S, np.zeros((priors, S.shape[1]))])
    held = np.vstack([rng.normal(size=(len(J) - priors, 5)), np.zeros((priors, 5))])
    pixel_rows = np.arange(len(J)) < len(J) - priors
    H = J @ np.linalg.pinv(J)
    found, naive = [], []
    for _ in range(200):
        e = np.where(pixel_rows, 0.1, 1.0) * rng.normal(size=len(J)) + S @ rng.normal(scale=0.5, size=S.shape[1]) \
            + held @ rng.normal(scale=0.3, size=5)
        r = e - H @ e
        found.append(pixel_variance(J, r, np.hstack([S, held]), pixel_rows))
        naive.append(r @ r / (len(J) - J.shape[1]))
    assert abs(np.mean(found) / 0.1**2 - 1) < 0.03
    assert np.mean(naive) > 10 * 0.1**2
    # without the nuisance the survey's share is counted as noise
    assert pixel_variance(J, r, np.zeros((len(J), 0)), pixel_rows) > 5 * 0.1**2
