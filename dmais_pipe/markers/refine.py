"""Sub-pixel refinement of X-corners (diagonal markers, inner chessboard corners).

The centre of an X-corner is the point through which all its edges pass: for every pixel x_i near
it with image gradient g_i, g_i . (p - x_i) = 0. `refine` solves the Gaussian-weighted least squares
of that condition iteratively (as cv2.cornerSubPix does), on a float patch sampled bilinearly
around the current estimate, with a window adapted to each corner's size: the largest ring around
the corner that still shows a clean four-sector pattern (`clean_radius`), so large markers use
many edge pixels (less noise) and small chessboard squares never let a neighbour into the window.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from . import xfit

RING_SAMPLES = 48
MIN_RADIUS = 3.0  # px, smallest window radius
MAX_RADIUS = 25.0  # px, largest window half-size
RADIUS_FRACTION = 0.8
SEED_RADIUS = 5.0
SEED_EPS = 0.01
SEED_STEPS = 4
SIGMA_FRACTION = 0.35
MIN_SIGMA = 2.5
_RADII = 3.0 * 1.35 ** np.arange(14)  # ring radii probed by clean_radius: 3 ... ~150 px


def as_float_image(image) -> np.ndarray:
    """(h, w) float32 copy/view of an 8- or 16-bit (or float) grayscale image."""
    image = np.asarray(image)
    if image.ndim != 2:
        raise ValueError(f"expected a (height, width) grayscale image, got shape {image.shape}")
    return image.astype(np.float32, copy=False)


def sample(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Bilinear samples of float32 `image` at pixel positions xy (..., 2); replicated border."""
    xy = np.asarray(xy, dtype=np.float32)
    shape = xy.shape[:-1]
    flat = xy.reshape(-1, 1, 2)
    # cv2.remap is limited to SHRT_MAX rows per call.
    out = np.empty(len(flat), dtype=np.float32)
    for s in range(0, len(flat), 30000):
        out[s:s + 30000] = cv2.remap(image, flat[s:s + 30000, :, 0].copy(), flat[s:s + 30000, :, 1].copy(),
                                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).ravel()
    return out.reshape(shape)


def ring_quality(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Quality (m,) in [0, 1] and contrast (m,) of rings of samples (m, k) as an X-corner.

    An X-corner ring is point symmetric (opposite samples equal), two-valued, and changes level
    exactly four times. Quality = bimodality (between-class / total variance of the two levels split
    at the ring mean) x point symmetry, 0 unless there are exactly 4 transitions.
    """
    quality, high_level, low_level, _ = _ring_stats(values)
    return quality, high_level - low_level


def _ring_stats(values: np.ndarray):
    """quality (m,), bright level (m,), dark level (m,), bright mask (m, k) of rings (m, k)."""
    values = np.asarray(values, dtype=np.float64)
    k = values.shape[1]
    mean = values.mean(axis=1, keepdims=True)
    high = values > mean
    transitions = np.count_nonzero(high != np.roll(high, 1, axis=1), axis=1)
    n_high = high.sum(axis=1)
    total = ((values - mean) ** 2).sum(axis=1) + 1e-9
    mean_high = np.where(high, values, 0).sum(axis=1) / np.maximum(n_high, 1)
    mean_low = np.where(~high, values, 0).sum(axis=1) / np.maximum(k - n_high, 1)
    within = (np.where(high, values - mean_high[:, None], values - mean_low[:, None]) ** 2).sum(axis=1)
    bimodal = np.clip(1.0 - within / total, 0.0, 1.0)
    opposite = np.roll(values, k // 2, axis=1)
    symmetric = np.clip(1.0 - ((values - opposite) ** 2).sum(axis=1) / (2.0 * total), 0.0, 1.0)
    quality = np.where(transitions == 4, bimodal * symmetric, 0.0)
    return quality, mean_high, mean_low, high


def _ring_offsets(radius: float, k: int = RING_SAMPLES) -> np.ndarray:
    angle = 2.0 * np.pi * (np.arange(k) + 0.5) / k
    return radius * np.column_stack([np.cos(angle), np.sin(angle)])


def clean_radius(image: np.ndarray, uv: np.ndarray, min_quality: float = 0.6,
                 radii: np.ndarray = _RADII, max_first: float = 8.0) -> np.ndarray:
    """(n,) largest radius of `radii` up to which the rings around uv (n, 2) stay the same clean
    X-corner: quality >= min_quality, the same bright/dark sectors (edges are straight lines through
    the centre, so the pattern does not change with the radius) and the same two levels as the
    previous ring (the pattern: as the first clean ring, at most `max_first` px); 0 where no ring qualifies."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    n = len(uv)
    result = np.zeros(n)
    started = np.zeros(n, dtype=bool)
    alive = np.ones(n, dtype=bool)
    ref_high, ref_low = np.zeros(n), np.zeros(n)
    ref_mask = np.zeros((n, RING_SAMPLES), dtype=bool)
    for radius in radii:
        idx = np.nonzero(alive)[0]
        if len(idx) == 0:
            break
        values = sample(image, uv[idx, None, :] + _ring_offsets(radius)[None])
        quality, high, low, mask = _ring_stats(values)
        ok = quality >= min_quality
        was = started[idx]
        contrast = np.maximum(ref_high[idx] - ref_low[idx], 1e-9)
        same = ((np.mean(mask == ref_mask[idx], axis=1) >= 0.9)
                & (high >= ref_high[idx] - 0.25 * contrast) & (low <= ref_low[idx] + 0.25 * contrast))
        ok = np.where(was, ok & same, ok)
        first = ok & ~was
        ref_mask[idx[first]] = mask[first]
        # Levels, ring to ring: blur lets them spread with the radius, but a ring leaving the
        # board (background, outline) pulls a level back.
        ref_high[idx[ok]], ref_low[idx[ok]] = high[ok], low[ok]
        started[idx[first]] = True
        result[idx[ok]] = radius
        stop = np.where(was, ~ok, ~ok & (radius >= max_first))
        alive[idx[stop]] = False
    return result


REJECT_RESIDUAL = 0.08  # fit RMS residual / contrast above which a corner is rejected
MAX_SIGMA_PX = 0.5  # corners less certain than this are rejected
MIN_EDGE_ANGLE = np.radians(15.0)  # edges closer than this in direction are degenerate
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
    REJECT_RESIDUAL of the contrast (e.g. a shadow edge or an occluder through it), its
    uncertainty exceeds MAX_SIGMA_PX, or no ring about the fitted centre is a clean X (NO_CLEAN_X:
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
    clean_uv, clean_first = clean_radius(img, uv), clean_radius(img, first)
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
        todo = np.ones(n, dtype=bool) if attempt == 0 else (_reasons(params, cov, rms, converged, uv, limit, radius)
                                                            == "poor fit") & (radius * SHRINK >= _smallest_window(params))
        if not todo.any():
            break
        if attempt:
            radius = np.where(todo, radius * SHRINK, radius)
        fitted = _fit_round(img, centre[todo], params[todo], radius[todo])
        for array, value in zip((params, cov, rms, converged), fitted):
            array[todo] = value
    params, cov, rms, converged, radius, shadowed = _symmetric_window(img, params, cov, rms, converged, radius)
    reason = _reasons(params, cov, rms, converged, uv, limit, radius)
    reason[shadowed & np.all(np.isfinite(params), axis=1)] = ASYMMETRIC
    # A shadow edge or an occluder at the corner itself can leave a fit of small residual away
    # from it (the model's blur and levels absorb the step): not even the smallest ring about the
    # fitted centre is a clean X there.
    good = reason == ""
    unclean = np.zeros(n, dtype=bool)
    unclean[good] = clean_radius(img, params[good, :2], radii=_RADII[_RADII < 8.0]) <= 0  # the first rings decide
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
    from .shadow import shadowed_corners  # it builds on this module's ring tests and fits

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
    values = sample(img, centre[:, None, None, :] + radii[None, :, None, None] * _ring_offsets(1.0)[None, None])
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
        start = xfit.linear_levels(params[idx], x, y, values, weights)
        for array, result in zip(out, xfit.fit(start, x, y, values, weights)):
            array[idx] = result
    return out


def _reasons(params, cov, rms, converged, uv, limit, window) -> np.ndarray:
    """(n,) '' for a good fit (window radius (n,) px), else why the corner is rejected (REASONS)."""
    p = params[:, :2]
    sigma = np.sqrt(0.5 * np.trace(cov, axis1=1, axis2=2))
    residual = rms / np.maximum(2.0 * np.abs(params[:, 6]), 1e-9)
    edge_angle = np.abs(np.sin(params[:, 2] - params[:, 3]))
    reason = np.full(len(p), "", dtype=object)
    reason[sigma > MAX_SIGMA_PX] = "uncertain"
    reason[residual > REJECT_RESIDUAL] = "poor fit"
    # Blurred wider than its window the model is a smooth saddle, whose centre any smooth shading
    # (a shadow edge through the corner) sets, with a small residual and a tiny sigma.
    reason[params[:, 4] > window] = "blur exceeds window"
    reason[edge_angle < np.sin(MIN_EDGE_ANGLE)] = "degenerate edges"
    reason[~(np.hypot(*(p - uv).T) <= limit)] = "moved too far"
    reason[~(converged & np.all(np.isfinite(p), axis=1) & np.isfinite(sigma))] = "no convergence"
    reason[~np.all(np.isfinite(params), axis=1)] = "no X pattern"
    return reason


def _initial_params(img: np.ndarray, start: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Model parameters (n, 7) from a ring about start (n, 2) (`ring_params`), or where the ring is
    not an X from the local saddle (`_saddle_params`); NaN rows where neither is."""
    rho = np.clip(0.6 * np.nan_to_num(radius, nan=MIN_RADIUS), 2.5, 12.0)
    values = sample(img, start[:, None, :] + rho[:, None, None] * _ring_offsets(1.0)[None]).astype(float)
    params = _saddle_params(img, start, radius)
    ring = ring_params(start, values)
    ok = np.isfinite(ring[:, 0])
    params[ok] = ring[ok]
    return params


def ring_params(start: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Model parameters (n, 7) from rings of samples values (n, k) (`_ring_offsets` order) about
    start (n, 2): edge normals from its four level changes, blur 1 px, levels from the ring; NaN
    rows where the ring does not change level exactly four times."""
    params = np.full((len(start), 7), np.nan)
    k = values.shape[1]
    mean = values.mean(axis=1, keepdims=True)
    high = values > mean
    nxt = np.roll(values, -1, axis=1)
    change = high != np.roll(high, -1, axis=1)
    ok = change.sum(axis=1) == 4
    if not ok.any():
        return params
    # Sub-sample angle of each level change (the crossing of the ring mean between samples j, j+1).
    j = np.nonzero(change[ok])[1].reshape(-1, 4)
    rows = np.arange(ok.sum())[:, None]
    v0, v1 = values[ok][rows, j], nxt[ok][rows, j]
    t = np.clip((v0 - mean[ok]) / np.where(v0 == v1, 1.0, v0 - v1), 0.0, 1.0)
    angle = 2.0 * np.pi * (j + 0.5 + t) / k
    # An edge line runs through changes 0 and 2, the other through 1 and 3; normals = direction + 90 deg.
    d1 = _mean_direction(angle[:, 0], angle[:, 2] - np.pi)
    d2 = _mean_direction(angle[:, 1], angle[:, 3] - np.pi)
    params[ok] = np.column_stack([start[ok], d1 + 0.5 * np.pi, d2 + 0.5 * np.pi, np.ones(ok.sum()), mean[ok, 0],
                                  0.5 * (values[ok].max(axis=1) - values[ok].min(axis=1))])
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


def _mean_direction(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.arctan2(np.sin(a) + np.sin(b), np.cos(a) + np.cos(b))


def seed(img: np.ndarray, uv: np.ndarray, max_shift) -> np.ndarray:
    """A coarse centring (n, 2) with a small window (SEED_RADIUS); NaN where it fails."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    # A few steps, not to convergence: under strong blur a small window's fixed point can drift.
    return _refine_fixed(img, uv, SEED_RADIUS, SEED_STEPS, SEED_EPS,
                         np.broadcast_to(np.asarray(max_shift, float), (len(uv),)), converge=False)


def _refine_fixed(img, start, radius, max_iterations, eps, max_shift, converge: bool = True) -> np.ndarray:
    """refine() with one window half-size for all points, vectorized over points (n, 2).

    Gradients are central differences at the integer pixels of a window around the start (no
    interpolation, whose smoothing depends on the sub-pixel phase and would bias the result);
    p = argmin sum_i w_i (g_i . (p - x_i))^2 in closed form, the Gaussian weights w_i centred on
    the previous p; iterated until p moves less than `eps`.
    """
    height, width = img.shape
    # A fixed window around the start (weights follow p smoothly, so the iteration converges).
    half = int(np.ceil(radius + min(float(np.max(max_shift, initial=0.0)), 2 * radius + 4))) + 1
    offs = np.arange(-half, half + 1)
    oy, ox = np.meshgrid(offs, offs, indexing="ij")
    ox, oy = ox.ravel(), oy.ravel()
    # Not narrower than MIN_SIGMA: the blurred saddle at the very centre violates the edge model.
    sigma2 = 2.0 * max(SIGMA_FRACTION * radius, MIN_SIGMA) ** 2
    p = np.array(start, dtype=float).reshape(-1, 2)
    n = len(p)
    out = np.full((n, 2), np.nan)
    active = np.nonzero(np.all(np.isfinite(p), axis=1))[0]
    for _ in range(max_iterations):
        if len(active) == 0:
            break
        q = p[active]
        inside = (q[:, 0] >= 0) & (q[:, 0] <= width - 1) & (q[:, 1] >= 0) & (q[:, 1] <= height - 1)
        q = np.where(inside[:, None], q, 0.0)
        s0 = np.where(inside[:, None], start[active], 0.0)
        cx, cy = np.rint(s0[:, 0]).astype(int), np.rint(s0[:, 1]).astype(int)
        x = cx[:, None] + ox[None]  # (k, m) integer pixel positions
        y = cy[:, None] + oy[None]
        xc, yc = np.clip(x, 1, width - 2), np.clip(y, 1, height - 2)
        gx = 0.5 * (img[yc, xc + 1].astype(np.float64) - img[yc, xc - 1])
        gy = 0.5 * (img[yc + 1, xc].astype(np.float64) - img[yc - 1, xc])
        rx, ry = x - q[:, :1], y - q[:, 1:]
        d2 = rx**2 + ry**2
        # Gaussian tapered smoothly to 0 at `radius`: no pixel enters or leaves the window abruptly.
        w = np.exp(-d2 / sigma2) * np.maximum(1.0 - d2 / radius**2, 0.0) ** 2 * (x == xc) * (y == yc)
        wxx, wxy, wyy = (w * gx * gx).sum(1), (w * gx * gy).sum(1), (w * gy * gy).sum(1)
        bx = (w * (gx * gx * x + gx * gy * y)).sum(1)
        by = (w * (gx * gy * x + gy * gy * y)).sum(1)
        det = wxx * wyy - wxy**2
        trace = wxx + wyy
        ok = inside & (trace > 0) & (det > 1e-6 * trace**2)
        with np.errstate(divide="ignore", invalid="ignore"):
            new = np.column_stack([wyy * bx - wxy * by, wxx * by - wxy * bx]) / det[:, None]
        delta = new - q
        ok &= np.all(np.isfinite(new), axis=1) & (np.hypot(*(new - start[active]).T) <= max_shift[active])
        p[active] = new
        done = ok & (np.hypot(*delta.T) < eps)
        out[active[done]] = new[done]
        active = active[ok & ~done]
        if not converge:
            out[active] = p[active]
    return out
