"""The control points' survey variance, estimated from a calibration's own residuals where the
survey's sigma is not given (issue 42, item 2).

A calibration adjustment (an intrinsics bundle adjustment, the rig adjustment) is fitted on the
control points as surveyed. Its residuals r (m,) hold two kinds of error: the pixel noise, of
variance s^2 on every residual and independent, and each control point's survey error, which is
the same in every image that sees the point: per point and axis a draw of variance sigma^2 (one
sigma for the field, all three axes), moving the residuals by its columns of S (m, 3P), the
residuals' change per unit survey error (px / m, or whitened). Points whose sigma the dataset gives
(`sigma_m`) add their known share S_g S_g^T (S_g scaled by their sigmas).

With H the fit's hat matrix J N^-1 J^T (N = J^T J), the residuals are r = (I - H) e. The survey
errors to be estimated move them only within the span of K = (I - H) S (k = rank K dimensions), the
given ones within that of K_g = (I - H) S_g; outside both (m - n - k_all dimensions, k_all the rank of
[K K_g], n the parameters) is pixel noise alone. With P the projector onto K's span and Q onto both
spans, the sums of squares have the expectations (method of moments, as Helmert's variance-component
estimation; pose.error_model does the same for the flight's ground points):

    T_in   = |P r|^2          E T_in   = s^2 k               + sigma^2 |K|^2 + |P K_g|^2
    T_rest = |r|^2 - |Q r|^2  E T_rest = s^2 (m - n - k_all)

(|.| the Frobenius norm): the noise from what lies outside the surveys' spans, the survey from what
its span holds beyond the noise and the given points' share. A negative sigma^2 (no survey error
shows beyond the noise) is 0, and s^2 then the whole sum of squares' less the given share, over m - n.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SurveyVariance:
    """pixel_variance: s^2 (the residuals' unit squared); survey_sigma: sigma (the unit of S's columns'
    inverse: m); survey_estimable: whether the residuals could tell the two apart (there are points to
    estimate and residual dimensions outside the surveys' spans), else survey_sigma is 0."""

    pixel_variance: float
    survey_sigma: float
    survey_estimable: bool


def estimate(J: np.ndarray, residuals: np.ndarray, unit: np.ndarray, given: np.ndarray | None = None,
             inverse: np.ndarray | None = None) -> SurveyVariance:
    """The pixel and survey variance components (module docstring) of a least-squares fit with Jacobian
    J (m, n) at its residuals (m,): unit (m, 3P) the residuals' change per unit survey error of the
    points whose sigma is to be estimated, given (m, 3Q) per one-sigma error of those whose sigma is
    known (None: none); inverse (n, n) (J^T J)^-1 if made already (`inverse_normal`)."""
    J, r, S = np.asarray(J, float), np.asarray(residuals, float), np.asarray(unit, float)
    m, n = J.shape
    inverse = inverse_normal(J) if inverse is None else inverse
    given = np.zeros((m, 0)) if given is None else np.asarray(given, float)
    K = S - J @ (inverse @ (J.T @ S))
    K_g = given - J @ (inverse @ (J.T @ given))
    basis, k = _span(K)
    both, k_all = _span(np.hstack([K, K_g])) if K_g.shape[1] else (basis, k)
    outside = m - n - k_all
    if k == 0 or outside < 1:
        return SurveyVariance(max(float(r @ r) - float(np.sum(K_g**2)), 0.0) / max(m - n, 1), 0.0, False)
    s2 = (float(r @ r) - float(np.sum((both.T @ r) ** 2))) / outside
    T_in = float(np.sum((basis.T @ r) ** 2))
    sigma2 = (T_in - s2 * k - float(np.sum((basis.T @ K_g) ** 2))) / float(np.sum(K**2))
    if sigma2 <= 0:
        return SurveyVariance(max(float(r @ r) - float(np.sum(K_g**2)), 0.0) / max(m - n, 1), 0.0, True)
    return SurveyVariance(s2, float(np.sqrt(sigma2)), True)


def pixel_variance(J: np.ndarray, residuals: np.ndarray, nuisance: np.ndarray, pixel_rows: np.ndarray) -> float:
    """The variance of the pixel rows (pixel_rows (m,) bool) of a least-squares fit with Jacobian J (m, n) at
    its residuals r (m,), the other rows (priors, whitened by their own sigma) of unit variance, from the
    pixel rows of what lies outside the span of J and of `nuisance` (m, q): the residuals' change with
    errors that are the same in every image (the control points' survey, the intrinsics held as
    calibrated), which leave residuals no pixel noise explains. With B an orthonormal basis of
    [J, nuisance], P = I - B B^T, D the pixel rows' indicator, B_D and B_O B's pixel and other rows:

        T = |D P r|^2,   E T = s^2 tr(D P D P) + tr(D P (I - D) P D)
                             = s^2 (|D| - 2 |B_D|^2 + |B_D^T B_D|^2) + tr(B_D^T B_D B_O^T B_O)

    (|.| Frobenius norms, |D| the pixel rows' count): the priors' own noise reaches the pixel rows only
    through the projection. NaN where no pixel dimension lies outside that span."""
    r, rows = np.asarray(residuals, float), np.asarray(pixel_rows, bool)
    columns = np.hstack([np.asarray(J, float), np.asarray(nuisance, float)])
    norms = np.linalg.norm(columns, axis=0)
    basis, _ = _span(columns[:, norms > 0] / norms[norms > 0])  # radians beside metres: each column at unit norm
    B_D, B_O = basis[rows], basis[~rows]
    outside = r[rows] - B_D @ (basis.T @ r)
    pixel_gram, other_gram = B_D.T @ B_D, B_O.T @ B_O
    dimensions = np.count_nonzero(rows) - 2.0 * np.trace(pixel_gram) + float(np.sum(pixel_gram**2))
    if dimensions < 1:
        return float("nan")
    return max(float(outside @ outside) - float(np.sum(pixel_gram * other_gram)), 0.0) / dimensions


def _span(K: np.ndarray) -> tuple[np.ndarray, int]:
    """An orthonormal basis (m, k) of K's columns' span and its dimension k (singular values above
    1e-10 of the largest)."""
    if K.shape[1] == 0:
        return np.zeros((K.shape[0], 0)), 0
    U, singular, _ = np.linalg.svd(K, full_matrices=False)
    k = int(np.sum(singular > 1e-10 * singular.max())) if singular.max() > 0 else 0
    return U[:, :k], k


def inverse_normal(J: np.ndarray) -> np.ndarray:
    """(J^T J)^-1 (pseudo-inverse) with J's columns scaled to unit norm first: a focal length in
    pixels and a rotation in radians differ by many orders."""
    scale = np.linalg.norm(J, axis=0)
    scale[scale == 0] = 1.0
    Js = J / scale
    return np.linalg.pinv(Js.T @ Js) / np.outer(scale, scale)
