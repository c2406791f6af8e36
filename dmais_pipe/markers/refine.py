"""Sub-pixel refinement of X-corners (diagonal markers, inner chessboard corners).

Each corner is centred coarsely by the gradient condition (`centring.seed`), then fitted with the
blurred X-corner model (`xfit`) in a window adapted to its size: the largest ring around the
corner that still shows a clean four-sector pattern (`rings.clean_radius`), so large markers use
many edge pixels (less noise) and small chessboard squares never let a neighbour into the window.
Windows are cut to the point-symmetric part about the fitted centre, and a shadow edge near a
clean X is fitted with the X (`shadow`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import xfit
from .centring import seed
from .rings import RADII, as_float_image, clean_radius, ring_offsets, ring_params, ring_sample, sample
from .shadow import shadowed_corners
from .xfit import rejection_reasons

MIN_RADIUS = 3.0  # px, smallest window radius
MAX_RADIUS = 25.0  # px, largest window half-size
NO_CLEAN_X = "no clean X at the fit"
SHADOW_MIN_QUALITY = 0.7  # `_refit_shadowed`: ring quality of the X with the shade divided out
SHADOW_MIN_RADIUS = 4.0  # and the radius (px) beyond which it must stay clean
REASONS = ("no X pattern", "no convergence", "moved too far", "degenerate edges", "blur exceeds window", "poor fit",
           "uncertain", NO_CLEAN_X, "asymmetric at the corner (a shadow edge or an occluder)")


@dataclass
class Corners:
    """Refined X-corners: uv (n, 2) (NaN rows where rejected), sigma_px (n,) standard deviation per
    axis of uv from the fit's residual (usable as a weight 1 / sigma^2), fit_residual (n,) RMS
    residual of the fit / contrast, blur_px (n,) fitted edge blur, contrast (n,) DN between the
    levels, window_px (n,) window radius, reason (n,) '' or why the corner was rejected."""

    uv: np.ndarray
    sigma_px: np.ndarray
    fit_residual: np.ndarray
    blur_px: np.ndarray
    contrast: np.ndarray
    window_px: np.ndarray
    reason: np.ndarray

    @classmethod
    def empty(cls, n: int) -> "Corners":
        nan = np.full(n, np.nan)
        return cls(np.full((n, 2), np.nan), nan.copy(), nan.copy(), nan.copy(), nan.copy(), nan.copy(),
                   np.full(n, REASONS[0], dtype=object))


def refine(image, uv, radius=None, max_shift: float | None = None) -> np.ndarray:
    """Sub-pixel X-corner positions (n, 2) from approximate ones uv (n, 2) (within ~2 px); NaN rows
    where `refine_corners` rejects the corner."""
    return refine_corners(image, uv, radius, max_shift).uv


def refine_corners(image, uv, radius=None, max_shift: float | None = None) -> Corners:
    """Fit of the blurred X-corner model (`xfit`) to every corner near uv (n, 2).

    image: (h, w) 8/16-bit or float grayscale. The start is centred first by the gradient condition
    with a small window (`seed`); the window radius (a scalar or (n,) `radius`, default per corner)
    is the largest clean X ring around it (`clean_radius`, the marker's scale: no outline, no
    neighbouring cell), at least 2.5 x the fitted blur + 1 px where the marker allows, within [3, 40]
    px and inside the image. The fit runs twice, the second window centred on the first result.
    A corner is rejected (NaN, with a reason) when no X is found, the fit does not converge, moves
    more than `max_shift` (default 3 px) from uv, its edges are nearly parallel, its fitted blur
    exceeds the window radius (no edge in the window, only a smooth saddle), its residual exceeds
    xfit.REJECT_RESIDUAL of the contrast (e.g. a shadow edge or an occluder through it), its
    uncertainty exceeds xfit.MAX_SIGMA_PX, or no ring about the fitted centre is a clean X (NO_CLEAN_X:
    a shadow edge through the corner itself). Where the rings about a returned corner show a
    shadow edge near it, the fit with the edge in the model replaces the plain one if confirmed
    (`_refit_shadowed`).
    """
    img = as_float_image(image)
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    n = len(uv)
    out = Corners.empty(n)
    if n == 0:
        return out
    limit = 3.0 if max_shift is None else float(max_shift)
    fixed = radius is not None
    # Start from the seed or from uv, whichever is the centre of the larger clean X (under strong
    # blur and foreshortening the small-window seed can drift away).
    first = seed(img, uv, np.full(n, limit))
    first = np.where(np.isfinite(first), first, uv)
    clean_uv, clean_first = np.split(clean_radius(img, np.vstack([uv, first])), 2)  # one call: rows are independent
    start = np.where((clean_first >= clean_uv)[:, None], first, uv)
    if not fixed:
        radius = np.maximum(clean_uv, clean_first)
    radius = _window_radius(img, start, radius)
    params = _initial_params(img, start, radius)
    params, cov, rms, converged = _fit_round(img, start, params, radius)
    # Second round centred on the first fit, with the window of the clean X about it; windows whose
    # fit is poor shrink (an outline, a shadow edge or an occluder at their rim) down to ~2 blurs.
    centre = np.where(np.isfinite(params[:, :2]), params[:, :2], start)
    if not fixed:
        again = clean_radius(img, centre)
        radius = _window_radius(img, centre, np.where(again > 0, again, radius))
    for attempt in range(3):
        todo = np.ones(n, dtype=bool) if attempt == 0 else (rejection_reasons(params, cov, rms, converged, uv, limit, radius)
                                                            == "poor fit") & (radius * SHRINK >= _smallest_window(params))
        if not todo.any():
            break
        if attempt:
            radius = np.where(todo, radius * SHRINK, radius)
        fitted = _fit_round(img, centre[todo], params[todo], radius[todo])
        for array, value in zip((params, cov, rms, converged), fitted):
            array[todo] = value
    params, cov, rms, converged, radius, shadowed = _symmetric_window(img, params, cov, rms, converged, radius)
    reason = rejection_reasons(params, cov, rms, converged, uv, limit, radius)
    reason[shadowed & np.all(np.isfinite(params), axis=1)] = ASYMMETRIC
    # A shadow edge or an occluder at the corner itself can leave a fit of small residual away
    # from it (the model's blur and levels absorb the step): not even the smallest ring about the
    # fitted centre is a clean X there.
    good = reason == ""
    unclean = np.zeros(n, dtype=bool)
    unclean[good] = clean_radius(img, params[good, :2], radii=RADII[RADII < 8.0]) <= 0  # the first rings decide
    reason[unclean] = NO_CLEAN_X
    good = reason == ""
    out.uv[:] = np.where(good[:, None], params[:, :2], np.nan)
    out.sigma_px[:] = np.sqrt(0.5 * np.trace(cov, axis1=1, axis2=2))
    out.contrast[:] = 2.0 * np.abs(params[:, 6])
    out.fit_residual[:] = rms / np.maximum(out.contrast, 1e-9)
    out.blur_px[:], out.window_px[:], out.reason[:] = params[:, 4], radius, reason
    _refit_shadowed(img, out, np.nonzero(good)[0])
    return out


def _refit_shadowed(img: np.ndarray, out: Corners, rows: np.ndarray) -> None:
    """Where the rings about corners out.uv[rows] show a shadow edge near them, the corner fitted
    with the edge in the model (`shadow.shadowed_corners`, its X of at least half the plain fit's
    contrast) replaces the plain fit's, with its sigma and residual, where that fit is confirmed
    (in place): a shadow edge near a clean X draws the plain model's corner by up to ~0.3 px."""
    if len(rows) == 0:
        return
    uv, _, sigma, residual, why = shadowed_corners(img, out.uv[rows], 0.5 * out.contrast[rows], SHADOW_MIN_QUALITY,
                                                   SHADOW_MIN_RADIUS)
    confirmed = why == ""
    rows = rows[confirmed]
    out.uv[rows], out.sigma_px[rows], out.fit_residual[rows] = uv[confirmed], sigma[confirmed], residual[confirmed]


SHRINK = 0.75
REACH_PX = 1.0  # px beyond the window the symmetry is checked: the blur of an edge just outside
MAX_ASYMMETRY = 0.1  # RMS difference of opposite ring samples / contrast, beyond what noise explains
NOISE_ASYMMETRY = 3.0  # and this many times their noise (`symmetric_radius`)
ASYMMETRIC = "asymmetric at the corner (a shadow edge or an occluder)"


def _symmetric_window(img, params, cov, rms, converged, radius):
    """The fits (params (n, 7), cov (n, 2, 2), rms (n,), converged (n,)) and window radii (n,)
    with every window cut to the point-symmetric part about its fitted centre (`symmetric_radius`)
    and refitted where that cut it, twice (the refit moves the centre), checked once more at the
    final centre; shadowed (n,): True where not even MIN_RADIUS or 2 blurs + 1 px is. A blurred
    X-corner is point symmetric however foreshortened; a shadow edge inside the window is not, and
    the fit would move the corner towards it."""
    shadowed = np.zeros(len(params), dtype=bool)
    for attempt in range(3):
        ok = np.all(np.isfinite(params), axis=1) & np.isfinite(radius) & ~shadowed
        limit = np.full(len(params), np.inf)
        if ok.any():
            limit[ok] = symmetric_radius(img, params[ok, :2], 2.0 * np.abs(params[ok, 6]), rms[ok], radius[ok])
        shadowed |= ok & (limit < _smallest_window(params))
        cut = ok & ~shadowed & (limit < radius)
        if attempt == 2 or not cut.any():
            break
        radius = np.where(cut, np.floor(limit * 4.0) / 4.0, radius)
        fitted = _fit_round(img, params[cut, :2], params[cut], radius[cut])
        for array, value in zip((params, cov, rms, converged), fitted):
            array[cut] = value
    return params, cov, rms, converged, radius, shadowed


def _smallest_window(params: np.ndarray) -> np.ndarray:
    """(n,) the smallest window radius (px) a fit of params (n, 7) may shrink to: MIN_RADIUS, or
    2 blurs + 1 px where that is larger."""
    return np.maximum(MIN_RADIUS, 2.0 * np.nan_to_num(params[:, 4], nan=1.0) + 1.0)


def symmetric_radius(img: np.ndarray, centre: np.ndarray, contrast: np.ndarray, rms: np.ndarray,
                     radius: np.ndarray) -> np.ndarray:
    """(n,) the radius (px) up to which rings about centre (n, 2), 1 px apart up to `radius` (n,)
    + REACH_PX (a blurred edge reaches into the window from outside it), are point symmetric: RMS of
    (opposite sample differences) <= MAX_ASYMMETRY x contrast (n,) and NOISE_ASYMMETRY x their noise
    added in quadrature; the first asymmetric ring's radius - 1 px (minus REACH_PX where the ring is
    beyond the window), inf where all are symmetric. Their noise: the smaller of the most symmetric
    ring's RMS difference and sqrt(2) x the fit's RMS residual rms (n,). Either alone can hide
    what the test looks for: the residual includes the misfit of a shadow edge within the window,
    and in a window cut to a few px every ring crosses the edge."""
    radii = np.arange(2.0, float(np.nanmax(radius)) + 1.0 + REACH_PX)
    offsets = (radii[:, None, None] * ring_offsets(1.0)[None]).reshape(-1, 2)  # (r k, 2)
    values = ring_sample(img, centre, offsets).reshape(len(centre), len(radii), -1)
    half = values.shape[2] // 2
    within = radii[None] <= radius[:, None] + REACH_PX  # (n, r)
    asym = np.sqrt(np.mean((values[:, :, :half] - values[:, :, half:]) ** 2, axis=2))  # (n, r)
    noise = np.minimum(np.min(np.where(within, asym, np.inf), axis=1), np.sqrt(2.0) * rms)
    allowed = np.sqrt((MAX_ASYMMETRY * contrast) ** 2 + (NOISE_ASYMMETRY * noise) ** 2)
    bad = (asym > allowed[:, None]) & within
    first = np.where(bad.any(axis=1), radii[np.argmax(bad, axis=1)], np.inf)
    return np.where(first > radius, first - REACH_PX, first) - 1.0


def _window_radius(img: np.ndarray, centre: np.ndarray, radius) -> np.ndarray:
    """(n,) window radii: `radius` within [MIN_RADIUS, MAX_RADIUS], and inside the image."""
    height, width = img.shape
    radius = np.clip(np.broadcast_to(np.asarray(radius, dtype=float), (len(centre),)), MIN_RADIUS, MAX_RADIUS)
    room = np.min([centre[:, 0], centre[:, 1], width - 1 - centre[:, 0], height - 1 - centre[:, 1]], axis=0) - 1.0
    return np.where(np.isfinite(room), np.minimum(radius, np.maximum(np.floor(room), MIN_RADIUS)), np.nan)


def _fit_round(img, centre, params, radius):
    """xfit.fit of every corner in its window (radius (n,) about centre (n, 2)), grouped by radius:
    (params (n, 7), covariance of p (n, 2, 2), RMS residual (n,), converged (n,)); NaN where params
    start as NaN."""
    n = len(centre)
    out = (np.full((n, 7), np.nan), np.full((n, 2, 2), np.nan), np.full(n, np.nan), np.zeros(n, dtype=bool))
    usable = np.isfinite(radius) & np.all(np.isfinite(params), axis=1) & np.all(np.isfinite(centre), axis=1)
    for value in np.unique(radius[usable]):
        idx = np.nonzero(usable & (radius == value))[0]
        x, y, values, weights = xfit.window(img, centre[idx], float(value))
        erfs = np.empty((2,) + x.shape)  # the start's erf factors, made once for the levels and the fit's first pass
        start = xfit.linear_levels(params[idx], x, y, values, weights, erfs)
        for array, result in zip(out, xfit.fit(start, x, y, values, weights, erfs=erfs)):
            array[idx] = result
    return out


def _initial_params(img: np.ndarray, start: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Model parameters (n, 7) from a ring about start (n, 2) (`ring_params`), or where the ring is
    not an X from the local saddle (`_saddle_params`); NaN rows where neither is."""
    rho = np.clip(0.6 * np.nan_to_num(radius, nan=MIN_RADIUS), 2.5, 12.0)
    values = sample(img, start[:, None, :] + rho[:, None, None] * ring_offsets(1.0)[None]).astype(float)
    params = ring_params(start, values)
    # The saddle's only where the ring is no X (each row's numbers are its own: the same as for all rows).
    missing = np.flatnonzero(~np.isfinite(params[:, 0]))
    if len(missing):
        params[missing] = _saddle_params(img, start[missing], np.asarray(radius)[missing])
    return params


def _saddle_params(img: np.ndarray, start: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Model parameters (n, 7) from the Hessian of a quadratic fitted about start (n, 2) (for rings
    too blurred or too small to show four level changes): near a blurred X-corner the image is
    ~ m + k l_1 l_2, whose Hessian has the edge normals' bisectors as eigenvectors and eigenvalues
    in the ratio cot^2 of half their angle. NaN rows where the quadratic is not a saddle."""
    r = np.clip(np.nan_to_num(radius, nan=MIN_RADIUS), MIN_RADIUS, 8.0)
    params = np.full((len(start), 7), np.nan)
    for value in np.unique(r):
        idx = np.nonzero(r == value)[0]
        x, y, values, weights = xfit.window(img, start[idx], float(value))
        dx, dy = x - start[idx, :1], y - start[idx, 1:]
        basis = np.stack([np.ones_like(dx), dx, dy, dx * dx, dx * dy, dy * dy], axis=-1)
        wb = basis * weights[..., None]
        normal = np.einsum("nki,nkj->nij", wb, basis) + 1e-9 * np.eye(6)
        coef = np.linalg.solve(normal, np.einsum("nki,nk->ni", wb, values)[..., None])[..., 0]
        hess = np.stack([np.stack([2 * coef[:, 3], coef[:, 4]], -1), np.stack([coef[:, 4], 2 * coef[:, 5]], -1)], 1)
        lam, vec = np.linalg.eigh(hess)  # ascending: lam[:, 0] < 0 < lam[:, 1] at a saddle
        saddle = (lam[:, 0] < 0) & (lam[:, 1] > 0)
        beta = np.arctan(np.sqrt(np.abs(lam[:, 0]) / np.maximum(lam[:, 1], 1e-12)))
        bisector = np.arctan2(vec[:, 1, 1], vec[:, 0, 1])
        sub = np.column_stack([start[idx], bisector + beta, bisector - beta, np.ones(len(idx)), coef[:, 0],
                               np.ones(len(idx))])
        params[idx] = np.where(saddle[:, None], sub, np.nan)
    return params


