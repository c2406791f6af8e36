"""X-corners crossed by a cast shadow's edge near their centre.

A shadow multiplies the light: on the log of the image it adds a step on one side of a straight
line, while the X-corner itself stays point symmetric about its centre. The ring tests of
`detect` fail such a corner (its rings are no longer two-valued or point symmetric), and the plain
model fit of `refine` would move the corner towards the shadow edge. Here the corner is fitted
with the shadow edge in the model: the line, its blur and the share of light it takes are fitted
with the X.

- Start: the best straight step on a log ring about the candidate (`_best_step`, the same on a
  wider ring: a sure start; or, on a marker smaller than that ring, on a narrower one), or where
  no sure start is found there about its coarse centring, or about its symmetric centre
  (`_start`). The start is cheap and strict, so that marker outlines and texture seldom
  reach the fits: the ring's point-symmetric part must be an X of a marker's log contrast
  (MIN_X_LOG: the shade does not change it), and the step must darken, leave an X, run across the
  X's sectors rather than along an edge of the X (an outline's T-junction), and leave both levels
  of the X on both sides of its line in the same ratio (a shadow takes the same share of light
  from both; the background beyond an outline is one level).
- Fits: the product of the blurred X and the blurred light (`xfit.shaded_model`, cheap) in a
  small window (again from the symmetric centre where that fit fails, `_first_fit`), then in the
  window of the clean X with the shade divided out; the corner returned is that of a final fit of
  the blurred product (`xfit.product_shaded_model`, `_product_fit`): where the shadow edge
  crosses an edge of the X the product of the blurred factors is not the blurred product, and
  moves the fitted corner by up to ~0.3 px.
- Checks: the final fit plausible (`_plausible`), the X with the shade divided out clean
  (`rings.clean_radius`) beyond MIN_CLEAN_PX, its uncertainty within MAX_SIGMA_PX_SHADED, and
  the corner confirmed (`_confirmed`) by a fit of the X alone to the pixels beside the shadow
  edge with the shade divided out (`_unshaded_corner`), or where that fit does not see the
  corner by the final fit in a smaller window. A marker's edge or outline corner crossed by a
  shadow edge can pass the others (the fitted X's edges are then the marker's edge and the
  shadow's), not this one.

Every candidate with a sure start is either returned or rejected with SHADOW_REASON, never
dropped without a trace. One whose start only the narrower ring confirms is returned where the
fits confirm it and otherwise left to `detect` as no shadowed X: on coarse ground texture (gravel)
such starts are common, and each would be a rejection blaming a shadow edge that is not there
(the effects benchmark's gravel row, seeds 202-213: 130 rejections away from every marker in 120
images; 17 with sure starts only).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.special import ndtr

from . import _shadow, xfit
from .centring import seed
from .rings import RADII, clean_radius, half_turn, ring_offsets, ring_params, ring_sample, ring_stats, sample
from .xfit import rejection_reasons

SHADOW_REASON = "shadow edge at the corner"
START_RING_PX = 5.0  # radius of the log ring the shadow line and the X are started from
INNER_RING_PX = 3.5  # or, less sure (a marker smaller than that ring), a log ring of this radius
CHECK_RING_PX = 7.5  # radius of the log ring that must show the same step
MAX_TURN = np.radians(30.0)  # the step's direction on the two rings, at most this apart
FIRST_WINDOW_PX = 8.0  # radius of the first fit's window
MAX_WINDOW_PX = 15.0  # radius of the second fit's window at most (the clean X with the shade divided out)
MIN_WINDOW_PX = 6.0
MIN_STEP_LOG = 0.2  # least darkening of a start line, as a step of log(intensity)
TOP_STEPS = 24  # steps of a start ring (of _STEPS) that explain the most of its point asymmetry, tried
MIN_X_LOG = 0.5  # least log contrast of the X on the start ring (a marker's cells: ~log(200 / 30) = 1.9)
MIN_START_QUALITY = 0.5  # ring quality of the X with the start step taken away
SAME_RATIO = 0.6  # the X's log contrast on either side of a shadow line: at least this share of the other's
MIN_SIDE_SAMPLES = 2  # samples of each level of the X on either side of the start step, at least
MIN_SHADE, MAX_SHADE = 0.2, 0.95  # the share of light the fitted shade takes
MAX_MOVE_PX = 8.0
SEED_SHIFT_PX = 4.0  # a candidate's coarse centring, at most this far, where no start is found at it
AGREE_PX = 0.13  # the final fit's corner and the check fit's, at most this apart
SMALLER_WINDOW = 0.6  # or the final fit's in a window this much smaller (at least MIN_WINDOW_PX)
WINDOW_AGREE_PX = 0.1  # at most this apart
MAX_SIGMA_PX_SHADED = 0.05  # px: the final fit's uncertainty at most (a corner within 0.1 px at 2 sigma)
PRODUCT_ITERATIONS = 20  # of the final fit, from the second's parameters
UNSHADED_ROUNDS = 3
BAND_BLURS = 2.5  # half-width of the band about the shadow edge the check fit leaves out, in its blurs
MIN_CLEAN_PX = 7.0  # px: the X with the shade divided out must stay clean beyond this radius
CENTRE_RING_PX = 4.0  # `symmetric_centre`: radius of its log ring
CENTRE_REACH_PX = 4  # and how far from the candidate it looks (px)
CENTRE_SAMPLES = 48  # samples of that ring
CENTRE_X_LOG = 0.9  # least log contrast of the X on the start ring about the symmetric centre
_STEPS = tuple((phi, t) for phi in np.radians(np.arange(0.0, 360.0, 15.0)) for t in (-0.6, -0.3, 0.0, 0.3, 0.6))
_STEP_LINES = np.array(_STEPS)  # (l, 2): np.array(_STEPS), made once
_STEP_LINES.flags.writeable = False
#: `symmetric_centre`'s grids (g, 2): of 1 px within CENTRE_REACH_PX, then of 0.5 px about the best.
_CENTRE_GRIDS = tuple(np.array([(x, y) for y in steps for x in steps])
                      for steps in (np.arange(-CENTRE_REACH_PX, CENTRE_REACH_PX + 1e-9), 0.5 * np.arange(-1.0, 2.0)))


def shadowed_corners(img: np.ndarray, uv: np.ndarray, contrast, min_quality: float, min_radius: float):
    """Fit X-corners crossed by a shadow edge near candidates uv (n, 2) of float image img (h, w).

    Returns (uv (n, 2) the corners (where rejected, the candidate's `symmetric_centre`), NaN
    where the candidate shows no shadowed X; clean radius (n,) px of the X with the shade divided
    out; sigma_px (n,); fit_residual (n,); reason (n,): '' for a corner, SHADOW_REASON where a
    sure start found an X crossed by a shadow edge (`_start_params`) but the fits did not confirm a
    corner, None where the candidate shows no shadowed X). contrast: least contrast (image units)
    of the lit X, one or (n,); min_quality, min_radius: the ring tests' (`detect`)."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    n = len(uv)
    out_uv, radius = np.full((n, 2), np.nan), np.zeros(n)
    sigma, residual = np.full(n, np.nan), np.full(n, np.nan)
    reason = np.full(n, None, dtype=object)
    if n == 0:
        return out_uv, radius, sigma, residual, reason
    given, contrast = uv, np.broadcast_to(np.asarray(contrast, dtype=float), (n,))
    uv, start, sure = _start(img, uv)
    tried = np.nonzero(np.all(np.isfinite(start), axis=1) & (2.0 * np.abs(start[:, 6]) >= contrast))[0]
    if len(tried) == 0:
        return out_uv, radius, sigma, residual, reason
    centre, about, moved = _first_fit(img, given[tried], uv[tried], start[tried], contrast[tried])
    # The second fit about the first's corner, over the clean X with the shade divided out.
    window = np.full(len(tried), np.nan)
    if moved.any():
        window[moved] = np.clip(_deshaded_clean_radius(img, centre[moved], about[moved], min_quality), MIN_WINDOW_PX,
                                MAX_WINDOW_PX)
    params = np.where(moved[:, None], about, np.nan)
    params[:, :2] = 0.0
    n_tried = len(tried)
    fitted = (np.full_like(params, np.nan),) + _no_fit(n_tried)
    for value in np.unique(window[moved]):
        idx = np.nonzero(moved & (window == value))[0]
        for array, result in zip(fitted, _fit_about(img, centre[idx], params[idx], float(value))):
            array[idx] = result
    params, cov, rms, converged = fitted
    joint = centre + params[:, :2]
    joint_line = _line_about(params, centre, joint)
    corner, line, cov, rms, converged = _product_fit(img, joint, joint_line, window, cov, rms, converged)
    clean = np.zeros(n_tried)
    good = _plausible(line, cov, rms, converged, window, contrast[tried]) & (np.hypot(*(corner - uv[tried]).T)
                                                                        <= MAX_MOVE_PX)
    if good.any():
        clean[good] = _deshaded_clean_radius(img, corner[good], line[good], min_quality)
    good &= clean >= max(min_radius, MIN_CLEAN_PX)
    with np.errstate(invalid="ignore"):
        final_sigma = np.sqrt(0.5 * np.trace(cov, axis1=1, axis2=2))
        good &= final_sigma <= MAX_SIGMA_PX_SHADED
    good &= _confirmed(img, corner, joint, joint_line, window, good)
    # A shadowed X the start found whose corner the fits do not confirm: rejected, with the reason,
    # at its symmetric centre (the candidate and the fits can be 3-4 px off, drawn to the shadow edge).
    failed = tried[~good & sure[tried]]
    reason[failed] = SHADOW_REASON
    out_uv[failed] = symmetric_centre(img, given[failed])
    rows = tried[good]
    out_uv[rows], radius[rows], reason[rows] = corner[good], clean[good], ""
    sigma[rows] = final_sigma[good]
    residual[rows] = rms[good] / (2.0 * np.abs(line[good, 6]))
    return out_uv, radius, sigma, residual, reason


def _confirmed(img, corner, joint, line, window, rows) -> np.ndarray:
    """(n,) where the final fit's corner (n, 2) is confirmed, of the rows (n,) asked: by the fit of
    the X alone beside the shadow edge (`_unshaded_corner`, from the second fit: its corner joint
    (n, 2), its line (n, 11) and window (n,)) within AGREE_PX, or, where that fit does not see the
    corner (the band it leaves out covers it and it extrapolates, off by up to ~1 px), by the
    final fit in a window SMALLER_WINDOW as large within WINDOW_AGREE_PX. A marker's outline or
    edge crossed by the shadow edge, or a second shadow edge, passes neither."""
    ok = np.zeros(len(corner), dtype=bool)
    unshaded = _unshaded_corner(img, joint, line, np.where(rows, window, np.nan))
    ok[rows] = np.hypot(*(corner - unshaded).T)[rows] <= AGREE_PX
    again = rows & ~ok
    if again.any():
        smaller = np.where(again, np.maximum(MIN_WINDOW_PX, SMALLER_WINDOW * window), np.nan)
        moved = _product_fit(img, joint, line, smaller, *_no_fit(len(corner)))[0]
        ok[again] = np.hypot(*(corner - moved).T)[again] <= WINDOW_AGREE_PX
    return ok


def _no_fit(n: int):
    """(cov (n, 2, 2), rms (n,), converged (n,)) of no fit, for the fits' outputs to fill."""
    return np.full((n, 2, 2), np.nan), np.full(n, np.nan), np.zeros(n, dtype=bool)


def symmetric_centre(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(n, 2) the point within CENTRE_REACH_PX of uv (n, 2), on a grid of 1 px (rings of
    CENTRE_SAMPLES / 2) refined to 0.5 px,
    whose log ring of CENTRE_RING_PX has the point-symmetric part most like an X (ring quality x
    log contrast). A shadow edge adds a step to the log ring whose point-symmetric part is nearly
    constant, so this stays within ~1 px of a shadowed X's corner where the candidate and the fits
    are drawn 3-4 px towards the shadow edge."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    for grid, k in zip(_CENTRE_GRIDS, (CENTRE_SAMPLES // 2, CENTRE_SAMPLES)):
        uv = _most_symmetric_x(img, uv[:, None, :] + grid[None], k)
    return uv


def _most_symmetric_x(img: np.ndarray, points: np.ndarray, k: int) -> np.ndarray:
    """(n, 2) of points (n, g, 2), the one per row whose log ring of CENTRE_RING_PX (k samples) has
    the point-symmetric part most like an X: `_most_symmetric_x_numpy`'s, scored and chosen in one
    compiled pass (`_shadow.most_symmetric`)."""
    n, g = points.shape[:2]
    if n == 0:
        return np.zeros((0, 2))
    logs = log_ring_sample(img, points, ring_offsets(CENTRE_RING_PX, k))
    return points[np.arange(n), _shadow.most_symmetric(logs.reshape(n * g, -1), g)]


def _most_symmetric_x_numpy(img: np.ndarray, points: np.ndarray, k: int) -> np.ndarray:
    """`_most_symmetric_x` in numpy (the reference of tests/test_marker_shadow_start.py)."""
    n, g = points.shape[:2]
    if n == 0:
        return np.zeros((0, 2))
    logs = log_sample(img, points[:, :, None, :] + ring_offsets(CENTRE_RING_PX, k)[None, None])
    logs = logs.reshape(n * g, -1).astype(np.float64)
    quality, high, low, _ = ring_stats(0.5 * (logs + np.roll(logs, logs.shape[1] // 2, axis=1)))
    best = np.argmax((quality * (high - low)).reshape(n, g), axis=1)
    return points[np.arange(n), best]


def _plausible(params, cov, rms, converged, window, contrast) -> np.ndarray:
    """(n,) fits (params (n, 11) about their corner) that are an X crossed by a real shadow edge:
    a fit `refine_corners` would take (`xfit.rejection_reasons`: converged, a good fit, certain, not
    degenerate, not blurred beyond the window), the X of enough contrast; the shade taking
    MIN_SHADE..MAX_SHADE of the light and crossing the window."""
    with np.errstate(invalid="ignore"):  # a degenerate fit's covariance: NaN, or a negative variance
        ok = rejection_reasons(params, cov, rms, converged, params[:, :2], np.inf, window) == ""
        ok &= 2.0 * np.abs(params[:, 6]) >= contrast
        ok &= (params[:, 10] >= MIN_SHADE) & (params[:, 10] <= MAX_SHADE)
        ok &= np.abs(params[:, 8]) < window  # the line about the corner, through the window
    return ok


def _product_fit(img, corner, params, window, cov, rms, converged):
    """The final fit, of `xfit.product_shaded_model` (the blurred product), from the second fit's
    params (n, 11, about corner (n, 2); index 9 the shadow edge's blur) in windows (n,) about the
    corner. Returns (corner, params about it (index 9 the edge's blur again), cov, rms, converged),
    the inputs where the fit is not made (NaN window)."""
    corner, params = corner.copy(), params.copy()
    cov, rms, converged = cov.copy(), rms.copy(), converged.copy()
    ok = np.isfinite(window) & np.all(np.isfinite(params), axis=1)
    for value in np.unique(window[ok]):
        idx = np.nonzero(ok & (window == value))[0]
        x, y, values, weights = _window_about(img, corner[idx], float(value))
        start = params[idx].copy()
        start[:, :2] = 0.0
        start[:, 9] = np.sqrt(np.maximum(start[:, 9] ** 2 - start[:, 4] ** 2, xfit.MIN_BLUR**2))  # the penumbra
        fitted, cov[idx], rms[idx], converged[idx] = xfit.fit(start, x, y, values, weights, PRODUCT_ITERATIONS,
                                                              model=xfit.product_shaded_model)
        fitted[:, 9] = np.hypot(fitted[:, 4], fitted[:, 9])
        new = corner[idx] + fitted[:, :2]
        corner[idx], params[idx] = new, _line_about(fitted, corner[idx], new)
    return corner, params, cov, rms, converged


def _unshaded_corner(img: np.ndarray, corner: np.ndarray, params: np.ndarray, window: np.ndarray) -> np.ndarray:
    """(n, 2) the corner of the check fit: the X alone (`xfit.model`) fitted to the pixels of
    windows (n,) about corner (n, 2) with the fitted shade of params (n, 11, about the corner)
    divided out and the band of BAND_BLURS x its blur about the shadow edge left out (there the
    shade is no constant factor); NaN where the fit is not made (NaN window)."""
    out = np.full((len(corner), 2), np.nan)
    ok = np.isfinite(window) & np.all(np.isfinite(params), axis=1)
    for value in np.unique(window[ok]):
        idx = np.nonzero(ok & (window == value))[0]
        x, y, values, weights = _window_about(img, corner[idx], float(value))
        edge = _edge_blurs(params[idx], x, y)
        weights = weights * (np.abs(edge) > BAND_BLURS)
        shaded = edge > 0
        kept = 1.0 - params[idx, 10:11]  # the share of light in the shade
        fitted = params[idx, :7].copy()
        fitted[:, :2] = 0.0
        for _ in range(UNSHADED_ROUNDS):
            # Outside the band the shade is a constant factor: fit the X to the pixels with it
            # divided out, then the factor to the shaded pixels given the X, and again.
            fitted = xfit.fit(fitted, x, y, np.where(shaded, values / np.maximum(kept, 1e-3), values), weights)[0]
            corner_model = xfit.model(fitted, x, y, jacobian=False)[0]
            w = weights * shaded
            kept = ((w * values * corner_model).sum(1) / np.maximum((w * corner_model**2).sum(1), 1e-12))[:, None]
        out[idx] = corner[idx] + fitted[:, :2]
    return out


def _line_about(params: np.ndarray, old: np.ndarray, new: np.ndarray) -> np.ndarray:
    """params (n, 11) of a shaded model in coordinates about old (n, 2), the line moved to
    coordinates about new (n, 2) (corner and X unchanged)."""
    params = params.copy()
    params[:, 8] -= np.cos(params[:, 7]) * (new[:, 0] - old[:, 0]) + np.sin(params[:, 7]) * (new[:, 1] - old[:, 1])
    params[:, :2] -= new - old
    return params


def _fit_about(img: np.ndarray, centre: np.ndarray, params: np.ndarray, radius: float):
    """xfit.fit of the shaded model in windows of `radius` about centre (n, 2), in coordinates
    about the centre; params (n, 11) in those coordinates."""
    return xfit.fit(params, *_window_about(img, centre, radius), model=xfit.shaded_model)


def _window_about(img: np.ndarray, centre: np.ndarray, radius: float):
    """`xfit.window` of `radius` about centre (n, 2), its pixel positions x, y (n, k) about the centre."""
    x, y, values, weights = xfit.window(img, centre, radius)
    return x - centre[:, :1], y - centre[:, 1:], values, weights


def _first_fit(img: np.ndarray, given: np.ndarray, uv: np.ndarray, start: np.ndarray, contrast: np.ndarray):
    """The first fit of the shaded model in FIRST_WINDOW_PX from start params (m, 11) about uv
    (m, 2); where it is not plausible, again from the start about the symmetric centre of the
    candidates given (m, 2), or the first start moved there where none is found (a start a few px
    off, drawn towards the shadow edge, can fail to converge); contrast (m,) the least of the X.
    Returns (its corners (m, 2), its params about them (m, 11), plausible (m,))."""
    centre, about, ok = _plausible_fit(img, uv, start, contrast, uv)
    again = np.nonzero(~ok)[0]
    if len(again) == 0:
        return centre, about, ok
    moved = symmetric_centre(img, given[again])
    restart = _start_params(img, moved)[0]
    # No start there: the first start's X and line, moved to the symmetric centre.
    unstarted = ~np.all(np.isfinite(restart), axis=1)
    restart[unstarted] = _line_about(start[again[unstarted]], uv[again[unstarted]], moved[unstarted])
    restart[unstarted, :2] = 0.0
    centre2, about2, ok2 = _plausible_fit(img, moved, restart, contrast[again], uv[again])
    rows = again[ok2]
    centre[rows], about[rows], ok[rows] = centre2[ok2], about2[ok2], True
    return centre, about, ok


def _plausible_fit(img, uv, start, contrast, anchor):
    """`_fit_about` in FIRST_WINDOW_PX from start (m, 11) about uv (m, 2): (corners (m, 2), params
    about them (m, 11), plausible (m,): `_plausible` and within MAX_MOVE_PX of anchor (m, 2))."""
    params, cov, rms, converged = _fit_about(img, uv, start, FIRST_WINDOW_PX)
    centre = uv + params[:, :2]
    about = _line_about(params, uv, centre)
    ok = np.all(np.isfinite(centre), axis=1) & (np.hypot(*(centre - anchor).T) <= MAX_MOVE_PX)
    return centre, about, ok & _plausible(about, cov, rms, converged, FIRST_WINDOW_PX, contrast)


def _start(img: np.ndarray, uv: np.ndarray):
    """(start points (n, 2), `_start_params` (n, 11) about them, NaN rows where none, sure (n,)):
    the candidates uv (n, 2); where no sure start is found there but the ring is a point-symmetric
    X, their coarse centring (`centring.seed`; the candidates of a shadowed X can be a few px off
    its corner); where neither gives a sure start, their symmetric centre (`symmetric_centre`, the
    X of at least CENTRE_X_LOG log contrast there). A start found later replaces one found before
    where it is sure or none was found."""
    start, symmetric, sure = _start_params(img, uv)
    given, uv = uv, uv.copy()
    retry = np.nonzero(symmetric & ~sure)[0]
    moved = seed(img, uv[retry], SEED_SHIFT_PX)
    ok = np.all(np.isfinite(moved), axis=1)
    moved_start, _, moved_sure = _start_params(img, moved[ok])
    _take_better(uv, start, sure, retry[ok], moved[ok], moved_start, moved_sure)
    retry = np.nonzero(~sure)[0]
    if len(retry):
        centre = symmetric_centre(img, given[retry])
        centre_start, _, centre_sure = _start_params(img, centre, CENTRE_X_LOG)
        _take_better(uv, start, sure, retry, centre, centre_start, centre_sure)
    return uv, start, sure


def _take_better(uv, start, sure, rows, new_uv, new_start, new_sure) -> None:
    """Replace, in place, the start points uv (n, 2), starts (n, 11) and sure (n,) of rows (m,) by
    new_uv (m, 2), new_start (m, 11), new_sure (m,) where the new start is sure, or found where
    none was."""
    found = np.all(np.isfinite(new_start), axis=1)
    better = found & (new_sure | ~np.all(np.isfinite(start[rows]), axis=1))
    rows = rows[better]
    uv[rows], start[rows], sure[rows] = new_uv[better], new_start[better], new_sure[better]


def _start_params(img: np.ndarray, uv: np.ndarray, min_x_log: float = MIN_X_LOG):
    """Shaded-model parameters (n, 11) about uv (n, 2) from a log ring of START_RING_PX: the
    straight step (`_best_step`) and the X of the ring with it taken away (`rings.ring_params`);
    NaN rows where no step leaves an X; (n,) where the ring's point-symmetric part is an X; and
    sure (n,): the step is the same on the ring of CHECK_RING_PX (else only on the ring of
    INNER_RING_PX, which stays inside markers whose cells are ~5 px across, foreshortened or small)."""
    offsets = ring_offsets(START_RING_PX)
    logs = log_ring_sample(img, uv, offsets).astype(np.float64)
    # Cheap first: the point-symmetric part of the ring, where a shadow line near the centre adds
    # little more than a constant, must already be an X (not a straight edge: flat there) of a
    # marker's log contrast, which the shade does not change (texture's is mostly less).
    quality, high, low, _ = ring_stats(0.5 * (logs + half_turn(logs)))
    is_x = (quality >= MIN_START_QUALITY) & (high - low >= min_x_log)
    symmetric = np.nonzero(is_x)[0]
    phi, offset, step = (np.full(len(uv), np.nan) for _ in range(3))
    lit = np.full(logs.shape, np.nan)
    phi[symmetric], offset[symmetric], step[symmetric], lit[symmetric] = _best_step(logs[symmetric])
    # The same straight step on a wider ring: a shadow edge is a long line, texture is not. That
    # ring reaches past a small marker's outline; a narrower one stands in, less surely.
    near = np.nonzero(np.isfinite(phi))[0]
    sure = np.zeros(len(uv), dtype=bool)
    params = np.full((len(uv), xfit.N_SHADED), np.nan)
    if len(near) == 0:  # no step (the wider and narrower rings' tests of none change nothing)
        return params, is_x, sure
    sure[near] = _same_step(img, uv[near], phi[near], CHECK_RING_PX)
    inner = near[~sure[near]]
    phi[inner[~_same_step(img, uv[inner], phi[inner], INNER_RING_PX)]] = np.nan
    ok = np.isfinite(phi)
    if not ok.any():
        return params, is_x, sure
    x_part = ring_params(np.zeros((ok.sum(), 2)), np.exp(lit[ok]))
    params[ok, :7] = x_part
    params[ok, 7], params[ok, 8], params[ok, 9], params[ok, 10] = phi[ok], offset[ok], 1.0, 1.0 - np.exp(step[ok])
    return params, is_x, sure


def _same_step(img: np.ndarray, uv: np.ndarray, phi: np.ndarray, radius: float) -> np.ndarray:
    """(n,) where the best straight step (`_best_step`) on the log ring of `radius` about uv (n, 2)
    runs within MAX_TURN of the directions phi (n,) found on the start ring."""
    ring = log_ring_sample(img, uv, ring_offsets(radius)).astype(np.float64)
    return np.abs(np.angle(np.exp(1j * (phi - _best_step(ring)[0])))) <= MAX_TURN


def _best_step(logs: np.ndarray):
    """For log rings (n, k) of START_RING_PX: direction (n,) towards the shade, offset (n,) px of
    the line from the centre, log step (n,) (< 0) and the ring with the step taken away (n, k) of
    the straight step (of _STEPS, least squares on the point asymmetry; of the TOP_STEPS that
    explain the most of it) that leaves the best X (quality >= MIN_START_QUALITY, darkening >=
    MIN_STEP_LOG); NaN where none does."""
    n, k = logs.shape
    if n == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0), np.zeros((0, k))
    shade, g, norm = _step_sizes(logs)
    line, ok, step, lit = _shadow.best_steps(logs, g, norm, shade, line_ends(_STEPS, k).reshape(len(_STEPS), -1),
                                             MIN_STEP_LOG, TOP_STEPS, MIN_START_QUALITY, SAME_RATIO,
                                             MIN_SIDE_SAMPLES)
    lines, nan = _STEP_LINES[line], np.full(n, np.nan)
    return np.where(ok, lines[:, 0], nan), np.where(ok, lines[:, 1] * START_RING_PX, nan), np.where(ok, step, nan), lit


def _step_sizes(logs: np.ndarray):
    """(shaded samples (l, k) of the lines of _STEPS, the log step sizes (n, l) that fit the point
    asymmetry of the log rings logs (n, k) best, the lines' asymmetries' squared norms (l,))."""
    k = logs.shape[1]
    shade, asym = step_masks(_STEPS, k)
    anti = logs - half_turn(logs)
    norm = np.maximum((asym * asym).sum(axis=1), 1e-9)
    return shade, anti @ asym.T / norm, norm


def _best_step_numpy(logs: np.ndarray):
    """`_best_step` in numpy (the reference of tests/test_marker_shadow_start.py; its ring with the step
    taken away only where a step is found)."""
    n, k = logs.shape
    if n == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0), np.zeros((0, k))
    shade, g, norm = _step_sizes(logs)
    explained = np.where(-g >= MIN_STEP_LOG, g * g * norm, -1.0)
    top = np.argsort(-explained, axis=1, kind="stable")[:, :TOP_STEPS]  # (n, t)
    g = np.take_along_axis(g, top, axis=1)
    shade = shade[top]  # (n, t, k)
    lit = logs[:, None, :] - g[:, :, None] * shade
    quality, _, _, bright = ring_stats(np.exp(lit).reshape(-1, k))
    quality, bright = quality.reshape(top.shape), bright.reshape(top.shape + (k,))
    # The line must cross the X's sectors, not run along an edge of the X (an outline T-junction).
    ends = line_ends(_STEPS, k)[top]  # (n, t, 2, w)
    ends = np.take_along_axis(bright, ends.reshape(n, top.shape[1], -1), axis=2)
    crosses = np.all(ends == ends[..., :1], axis=2)
    quality = np.where((-g >= MIN_STEP_LOG) & crosses & both_sides(lit, bright, shade), quality, -1.0)
    best = np.argmax(quality, axis=1)
    rows = np.arange(n)
    ok = quality[rows, best] >= MIN_START_QUALITY
    lines = np.array(_STEPS)[top[rows, best]]
    nan = np.full(n, np.nan)
    return (np.where(ok, lines[:, 0], nan), np.where(ok, lines[:, 1] * START_RING_PX, nan),
            np.where(ok, g[rows, best], nan), lit[rows, best])


def both_sides(lit: np.ndarray, bright: np.ndarray, shade: np.ndarray, min_samples: int = MIN_SIDE_SAMPLES
               ) -> np.ndarray:
    """(n, l) True where log rings lit (n, l, k) with a step taken away (bright mask (n, l, k), the
    step's shaded samples shade (n, l, k), or (1, l, k) for the same lines on every ring) have both
    levels of the X on both sides of the step's line, min_samples of each at least, in the same
    ratio: a shadow takes the same share of the light from both. A marker's outline (an L- or
    T-junction, the background beyond it one level) or texture fails."""
    both, contrast = np.ones(lit.shape[:2], dtype=bool), []
    for side in (shade, 1.0 - shade):
        on_bright, on_dark = bright * side, ~bright * side
        n_bright, n_dark = on_bright.sum(axis=2), on_dark.sum(axis=2)
        both &= (n_bright >= min_samples) & (n_dark >= min_samples)
        contrast.append((lit * on_bright).sum(axis=2) / np.maximum(n_bright, 1)
                        - (lit * on_dark).sum(axis=2) / np.maximum(n_dark, 1))
    return both & (np.minimum(*contrast) >= SAME_RATIO * np.maximum(*contrast))


def log_sample(img: np.ndarray, points: np.ndarray) -> np.ndarray:
    """log of the image (h, w) sampled at points (..., 2) (`rings.sample`), from 1 up: a shadow's
    factor on the light is a step there."""
    return np.log(np.maximum(sample(img, points), 1.0))


def log_ring_sample(img: np.ndarray, centres: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(..., k) `log_sample` at centres (..., 2) + offsets (k, 2), to the last bit (`rings.ring_sample`)."""
    return np.log(np.maximum(ring_sample(img, centres, offsets), 1.0))


@lru_cache(maxsize=8)
def line_ends(lines: tuple, k: int, half_width: int = 1) -> np.ndarray:
    """(l, 2, 2 half_width + 1) indexes of the ring samples about the two points where each line
    (phi, t) of lines (l) -- cos(angle - phi) = t -- crosses a ring of k samples."""
    ends = []
    for phi, t in lines:
        crossing = np.mod([phi + np.arccos(t), phi - np.arccos(t)], 2.0 * np.pi)
        centre = np.rint(crossing / (2.0 * np.pi) * k - 0.5).astype(int)
        ends.append(np.mod(centre[:, None] + np.arange(-half_width, half_width + 1)[None], k))
    return np.array(ends)


@lru_cache(maxsize=8)
def step_masks(lines: tuple, k: int):
    """(shade (l, k) 0/1 of each ring sample of k beyond each line (phi, t) of lines (l), its point
    asymmetry (l, k))."""
    angle = 2.0 * np.pi * (np.arange(k) + 0.5) / k
    shade = np.array([(np.cos(angle - phi) > t) for phi, t in lines], dtype=float)
    return shade, shade - np.roll(shade, k // 2, axis=1)


def _deshaded_clean_radius(img: np.ndarray, corner: np.ndarray, params: np.ndarray, min_quality: float):
    """(n,) `rings.clean_radius` about corner (n, 2) of the image with the fitted shade of params
    (n, 11, about the corner) divided out, within MAX_WINDOW_PX + 1 px."""
    half = int(np.ceil(MAX_WINDOW_PX)) + 3
    out = np.zeros(len(corner))
    for i, (c, p) in enumerate(zip(corner, params)):
        x0, y0 = np.floor(c).astype(int) - half
        ys, xs = np.mgrid[0:2 * half + 1, 0:2 * half + 1]
        xs, ys = xs + x0, ys + y0
        crop = img[np.clip(ys, 0, img.shape[0] - 1), np.clip(xs, 0, img.shape[1] - 1)].astype(np.float64)
        light = 1.0 - p[10] * ndtr(_edge_blurs(p[None], xs - c[0], ys - c[1]))
        local = (crop / np.maximum(light, 1e-3)).astype(np.float32)
        out[i] = clean_radius(local, (c - [x0, y0])[None], min_quality=min_quality,
                              radii=RADII[RADII <= MAX_WINDOW_PX + 1.0])[0]
    return out


def _edge_blurs(params: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Signed distance from the shadow edge of params (n, 11, about the corner) towards the shade,
    in its blurs, at x, y (n, k), or at x, y of any shape for one params (1, 11)."""
    return (np.cos(params[:, 7:8]) * x + np.sin(params[:, 7:8]) * y - params[:, 8:9]) / params[:, 9:10]
