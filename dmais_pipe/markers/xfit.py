"""Least-squares fit of a blurred X-corner model to the pixels around a corner.

Model of the grey value at pixel x (p the corner, n_k = (cos t_k, sin t_k) the normals of its two
edges, s the blur, m the mean level, c half the contrast, signed by the polarity):

    M(x) = m + c * erf(l_1 / (sqrt(2) s)) * erf(l_2 / (sqrt(2) s)),   l_k = n_k . (x - p)

exact for two perpendicular edges under a Gaussian PSF (pixel area adds ~1/12 px^2 to s^2), and
point symmetric about p for any angle between the edges, as the blurred corner itself is: the
misfit near the centre of an oblique corner is even, the model's derivative in p odd, so it does
not move p to first order. Fitting explicitly for the blur is what keeps small, blurred and
foreshortened corners accurate, where the gradient condition of cv2.cornerSubPix is biased by the
rounded saddle at the centre and needs a window larger than the marker.

An X crossed by a cast shadow's edge: `shaded_model`, the product of the blurred X and the
blurred light (cheap, exact away from where the shadow edge crosses an edge of the X), and
`product_shaded_model`, the blurred product (computed on a fine grid).

`fit` runs Levenberg-Marquardt on all corners at once (one window radius), with fixed taper
weights w = (1 - d^2 / R^2)^2 about a fixed window centre, the blurs held at their floor
MIN_BLUR while a step would push them below, and returns the parameters, the covariance of p
from the weighted residual (a sandwich estimate, so misfit raises it too) and the RMS residual.
For `model` the values, Jacobian and normal equations of a window come from one compiled pass
over its pixels (`_xfit`, equal to the numpy expressions to rounding).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.special import erf

from . import _xfit

N_PARAMS = 7  # px, py, t1, t2, s, m, c
N_SHADED = 11  # and t3, e3, s3, q of a straight shadow edge (`shaded_model`)
MIN_BLUR = 0.3  # px
_SQRT2 = np.sqrt(2.0)
_DERF = np.sqrt(2.0 / np.pi)


def window(img: np.ndarray, centre: np.ndarray, radius: float):
    """Pixels of discs of `radius` about centres (n, 2): positions x, y (n, k), values (n, k) and
    taper weights (n, k), 0 outside the disc or the image. Only pixels within radius + 1 of the
    rounded centre are listed (the taper is 0 beyond radius from the centre itself)."""
    height, width = img.shape
    ox, oy = _disc(float(radius))
    c = np.rint(np.nan_to_num(centre)).astype(int)
    x, y, rows, columns, weights = _xfit.window_pixels(centre, c, ox, oy, radius**2, width, height)
    return x, y, img[rows, columns].astype(np.float64), weights


def _window_numpy(img: np.ndarray, centre: np.ndarray, radius: float):
    """`window` in numpy (the reference of tests/test_xfit_compiled.py)."""
    height, width = img.shape
    ox, oy = _disc(float(radius))
    c = np.rint(np.nan_to_num(centre)).astype(int)
    x = c[:, :1] + ox[None]
    y = c[:, 1:] + oy[None]
    inside = (x >= 0) & (x < width) & (y >= 0) & (y < height)
    values = img[np.clip(y, 0, height - 1), np.clip(x, 0, width - 1)].astype(np.float64)
    d2 = (x - centre[:, :1]) ** 2 + (y - centre[:, 1:]) ** 2
    weights = np.maximum(1.0 - d2 / radius**2, 0.0) ** 2 * inside
    return x.astype(float), y.astype(float), values, weights


@lru_cache(maxsize=64)
def _disc(radius: float) -> tuple[np.ndarray, np.ndarray]:
    """(k,) column and row offsets (int, read-only) of `window`'s disc of `radius`: within radius + 1 px
    of the rounded centre, in raster order."""
    half = int(np.ceil(radius)) + 1
    offs = np.arange(-half, half + 1)
    oy, ox = np.meshgrid(offs, offs, indexing="ij")
    disc = ox**2 + oy**2 <= (radius + 1.0) ** 2
    ox, oy = ox[disc], oy[disc]
    ox.flags.writeable = oy.flags.writeable = False
    return ox, oy


def model(params: np.ndarray, x: np.ndarray, y: np.ndarray, jacobian: bool = True):
    """Model values (n, k) at pixels x, y (n, k) for params (n, 7), and its Jacobian (n, k, 7)."""
    px, py, t1, t2, s, m, c = (params[:, i:i + 1] for i in range(N_PARAMS))
    dx, dy = x - px, y - py
    c1, s1, c2, s2 = np.cos(t1), np.sin(t1), np.cos(t2), np.sin(t2)
    l1, l2 = c1 * dx + s1 * dy, c2 * dx + s2 * dy
    a, b = erf(l1 / (_SQRT2 * s)), erf(l2 / (_SQRT2 * s))
    ca = c * a
    value = m + ca * b
    if not jacobian:
        return value, None
    da = _DERF / s * np.exp(-0.5 * (l1 / s) ** 2)  # d a / d l1
    db = _DERF / s * np.exp(-0.5 * (l2 / s) ** 2)
    # The products each column shares, each in the order the column's formula multiplies it.
    dab, adb, minus_c = da * b, a * db, -c
    jac = np.empty(x.shape + (N_PARAMS,))
    jac[..., 0] = minus_c * (dab * c1 + adb * c2)
    jac[..., 1] = minus_c * (dab * s1 + adb * s2)
    jac[..., 2] = c * da * b * (-s1 * dx + c1 * dy)
    jac[..., 3] = ca * db * (-s2 * dx + c2 * dy)
    jac[..., 4] = minus_c * (dab * l1 + adb * l2) / s
    jac[..., 5] = 1.0
    jac[..., 6] = a * b
    return value, jac


def shaded_model(params: np.ndarray, x: np.ndarray, y: np.ndarray, jacobian: bool = True):
    """The X-corner `model` crossed by a straight shadow edge: values (n, k) at pixels x, y (n, k)
    for params (n, 11), and the Jacobian (n, k, 11).

    A cast shadow multiplies the light: M(x) = X(x) (1 - q Phi(l_3 / s_3)), l_3 = n_3 . x - e_3
    (n_3 = (cos t_3, sin t_3) towards the shade, e_3 its offset from the coordinates' origin, s_3
    the edge's blur with the penumbra, q the share of the light the shade takes). The product of
    the blurred factors stands for the blurred product, as erf(l_1) erf(l_2) does for an oblique X:
    exact away from where the shadow edge crosses an edge of the X.
    """
    corner, jac_x = model(params[:, :N_PARAMS], x, y, jacobian)
    t3, e3, s3, q = (params[:, i:i + 1] for i in range(N_PARAMS, N_SHADED))
    c3, n3 = np.cos(t3), np.sin(t3)
    l3 = c3 * x + n3 * y - e3
    shade = 0.5 * (1.0 + erf(l3 / (_SQRT2 * s3)))
    light = 1.0 - q * shade
    value = corner * light
    if not jacobian:
        return value, None
    dshade = _DERF / (2.0 * s3) * np.exp(-0.5 * (l3 / s3) ** 2)  # d Phi / d l3
    jac = np.empty(x.shape + (N_SHADED,))
    jac[..., :N_PARAMS] = jac_x * light[..., None]
    jac[..., 7] = -corner * q * dshade * (-n3 * x + c3 * y)
    jac[..., 8] = corner * q * dshade
    jac[..., 9] = corner * q * dshade * l3 / s3
    jac[..., 10] = -corner * shade
    return value, jac


GRID_PX = 0.25  # `product_shaded_model`: spacing of its fine grid (1 px / an integer)
_SOFT = GRID_PX  # and the softening of the X's edges on it (standard deviation, taken off the blur)
_LOGISTIC = np.sqrt(3.0) / np.pi  # a logistic step's scale per its standard deviation
MAX_GRID_BLUR = 3.0  # px: the grid reaches 4 such blurs beyond the pixels at most (the kernel is cut there)


def product_shaded_model(params: np.ndarray, x: np.ndarray, y: np.ndarray, jacobian: bool = True):
    """The blurred product of a sharp X-corner and a shadow edge's light: values (n, k) at pixels
    x, y (n, k) (each row on one integer lattice) for params (n, 11), and the Jacobian (n, k, 11).

    The parameters are `shaded_model`'s but for index 9: here the shadow edge's softness before
    the optical blur (its penumbra, px; its blur in the image is sqrt(s^2 + penumbra^2)). The light
    (1 - q step(l_3 / penumbra)) multiplies the X (m + c step(l_1) step(l_2), +-1 steps) on a fine
    grid (GRID_PX; logistic steps, those of the X of standard deviation _SOFT), which is then
    blurred by a Gaussian of sqrt(s^2 - _SOFT^2) and sampled at the pixels: separable, so two
    matrix products per row. Exact where `shaded_model` is not, where the shadow edge crosses an
    edge of the X (there the product of the blurred factors moves a fitted corner by up to
    ~0.3 px); ~10 ms per evaluation of a row of a 15 px window (~100x `shaded_model`).
    """
    n, k = x.shape
    value = np.empty((n, k))
    jac = np.empty((n, k, N_SHADED)) if jacobian else None
    for i in range(n):
        value[i], row = _product_on_grid(params[i], x[i], y[i], jacobian)
        if jacobian:
            jac[i] = row
    return value, jac


def _product_on_grid(p: np.ndarray, x: np.ndarray, y: np.ndarray, jacobian: bool):
    """One row of `product_shaded_model`: values (k,) and Jacobian (k, 11) or None."""
    px, py, t1, t2, s, m, c, t3, e3, soft, q = p
    blur = np.sqrt(max(s * s - _SOFT * _SOFT, 1e-4))
    cols, col_of = np.unique(x, return_inverse=True)
    rows, row_of = np.unique(y, return_inverse=True)
    pad = np.ceil(4.0 * min(blur, MAX_GRID_BLUR) + 1.0)  # a trial step's huge blur must not make a huge grid
    gx = np.arange(cols[0] - pad, cols[-1] + pad + 1e-9, GRID_PX)
    gy = np.arange(rows[0] - pad, rows[-1] + pad + 1e-9, GRID_PX)
    kx, dkx = _blur_matrix(cols, gx, blur)
    ky, dky = _blur_matrix(rows, gy, blur)
    zx, zy = gx[None, :], gy[:, None]
    c1, s1, c2, s2, c3, s3 = np.cos(t1), np.sin(t1), np.cos(t2), np.sin(t2), np.cos(t3), np.sin(t3)
    ex, ey = zx - px, zy - py
    l1, l2 = c1 * ex + s1 * ey, c2 * ex + s2 * ey
    l3 = c3 * zx + s3 * zy - e3
    # Sigmoids of the grid's edges: tanh(l / (2 w)) is a logistic step of standard deviation
    # w pi / sqrt(3) (as smooth on the grid as the Gaussian's, at a third of erf's cost).
    w_x, w_3 = _SOFT * _LOGISTIC, soft * _LOGISTIC
    a, b = np.tanh(l1 * (0.5 / w_x)), np.tanh(l2 * (0.5 / w_x))
    shade = np.tanh(l3 * (0.5 / w_3))
    dshade = 1.0 - shade * shade  # d shade / d l3 = dshade / (4 w_3), shade in [0, 1] below
    shade += 1.0
    shade *= 0.5
    ab = a * b
    light = 1.0 - q * shade
    corner = c * ab
    corner += m
    if not jacobian:
        return (ky @ (corner * light) @ kx.T)[row_of, col_of], None
    maps = np.empty((11,) + l1.shape)
    np.multiply(corner, light, out=maps[0])
    maps[5] = light
    np.multiply(ab, light, out=maps[6])
    np.multiply(corner, shade, out=maps[10])
    np.negative(maps[10], out=maps[10])
    # d a / d l1 = (1 - a^2) / (2 w_x), likewise b; times c * light and the other factor.
    scale = c * light * (0.5 / w_x)
    da = 1.0 - a * a
    da *= b
    da *= scale
    db = 1.0 - b * b
    db *= a
    db *= scale
    np.negative(c1 * da + c2 * db, out=maps[1])
    np.negative(s1 * da + s2 * db, out=maps[2])
    np.multiply(da, -s1 * ex + c1 * ey, out=maps[3])
    np.multiply(db, -s2 * ex + c2 * ey, out=maps[4])
    qc = dshade
    qc *= corner
    qc *= q / (4.0 * w_3)
    maps[8] = qc
    np.multiply(qc, -s3 * zx + c3 * zy, out=maps[7])
    np.negative(maps[7], out=maps[7])
    np.multiply(qc, l3 * (1.0 / soft), out=maps[9])
    blurred = ky @ maps @ kx.T  # (11, rows, cols)
    # d/ds acts on the kernels: d(Ky V Kx^T) = dKy V Kx^T + Ky V dKx^T, times d blur / d s.
    dblur = (dky @ maps[0] @ kx.T + ky @ maps[0] @ dkx.T) * (s / blur)
    out = blurred[:, row_of, col_of]
    jac = np.empty((len(x), N_SHADED))
    jac[:, [0, 1, 2, 3, 5, 6, 7, 8, 9, 10]] = out[1:].T
    jac[:, 4] = dblur[row_of, col_of]
    return out[0], jac


def _blur_matrix(pixels: np.ndarray, grid: np.ndarray, blur: float):
    """(m, g) weights of a Gaussian of `blur` from grid points (g,) to pixels (m,), each row
    summing to 1, and their derivative in `blur`."""
    u = pixels[:, None] - grid[None, :]
    w = np.exp(-0.5 * (u / blur) ** 2)
    dw = w * (u * u / blur**3)  # the -1/blur of the Gaussian's scale cancels in the normalisation
    total, dtotal = w.sum(axis=1, keepdims=True), dw.sum(axis=1, keepdims=True)
    return w / total, (dw - w * dtotal / total) / total


def linear_levels(params: np.ndarray, x, y, values, weights, erfs: np.ndarray | None = None) -> np.ndarray:
    """params (n, 7) with m, c set by weighted linear least squares for the other parameters; with
    erfs (2, n, k), the model's erf factors kept there (`fit`'s first pass of these params takes them)."""
    params = params.copy()
    params[:, 5], params[:, 6] = 0.0, 1.0
    ab = _xfit.values(params, x, y, erfs)
    sw, sa, saa = weights.sum(1), (weights * ab).sum(1), (weights * ab * ab).sum(1)
    sv, sav = (weights * values).sum(1), (weights * ab * values).sum(1)
    det = np.maximum(sw * saa - sa**2, 1e-12)
    params[:, 6] = (sw * sav - sa * sv) / det
    params[:, 5] = (sv - params[:, 6] * sa) / np.maximum(sw, 1e-12)
    return params


def _normal_equations(residual: np.ndarray, jac: np.ndarray, weights: np.ndarray):
    """Weighted cost (n,), J^T W J (n, p, p) and J^T W r (n, p) of residuals (n, k) and Jacobians (n, k, p)."""
    wj = (jac * weights[..., None]).transpose(0, 2, 1)  # (n, 7, k): batched BLAS products
    return (weights * residual**2).sum(1), np.matmul(wj, jac), np.matmul(wj, residual[..., None])[..., 0]


def _equations(fitted, params, x, y, values, weights):
    """`_normal_equations` of the model `fitted` for params (n, p) at pixels x, y, values, weights
    (n, k): `model`'s in one compiled pass over the pixels (`_xfit`), another's from its Jacobian."""
    if fitted is model:
        return _xfit.normal_equations(params, x, y, values, weights)
    value, jac = fitted(params, x, y)
    return _normal_equations(value - values, jac, weights)


def _is_compiled(fitted) -> bool:
    """Whether the model `fitted` is `model`, whose normal equations `_xfit` makes."""
    return fitted is model


def _sandwich(fitted, params, x, y, values, weights):
    """(weighted cost (n,), J^T W J (n, p, p), J^T W^2 J (n, p, p)) of the model `fitted` at params
    (n, p): the covariance's parts."""
    if fitted is model:
        cost, hess, _, meat = _xfit.normal_equations(params, x, y, values, weights, meat=True)
        return cost, hess, meat
    r, jac = fitted(params, x, y)
    r = r - values
    wj = (jac * weights[..., None]).transpose(0, 2, 1)
    return (weights * r**2).sum(1), np.matmul(wj, jac), np.matmul(wj * weights[:, None, :], jac)


def fit(params: np.ndarray, x, y, values, weights, iterations: int = 40, model=model, erfs: np.ndarray | None = None):
    """Levenberg-Marquardt from params (n, p) on pixels x, y, values, weights (n, k), of `model`
    (`model`, p = 7, or `shaded_model`, p = 11). erfs (2, n, k): `model`'s erf factors at params, as
    `linear_levels` kept them (its pass of params takes them instead of making them again).

    Returns (params (n, p), covariance of the corner (n, 2, 2), weighted RMS residual (n,), converged (n,)).
    """
    params = params.copy()
    n = len(params)
    lam = np.full(n, 1e-3)
    if erfs is not None and _is_compiled(model):
        cost, hess, grad = _xfit.normal_equations(params, x, y, values, weights, erfs=erfs)
    else:
        cost, hess, grad = _equations(model, params, x, y, values, weights)
    n_params = params.shape[1]
    # The compiled model's J^T W^2 J (the covariance's middle) is made in the pass that evaluates a
    # trial whose step is small (where it is taken, the fit is done there): no pass of its own but
    # for fits that end otherwise. Every sum is that pass's, so the same as a pass of its own.
    compiled = _is_compiled(model)
    meat = np.zeros((n, n_params, n_params)) if compiled else None
    has_meat = np.zeros(n, dtype=bool)
    eye = np.eye(n_params)
    converged = np.zeros(n, dtype=bool)
    active = np.arange(n)
    bounded = [4, 9] if n_params == N_SHADED else [4]  # blurs, at least MIN_BLUR
    for _ in range(iterations):
        if len(active) == 0:
            break
        h = hess[active]
        damped = h + lam[active, None, None] * (eye * np.diagonal(h, axis1=1, axis2=2)[:, None, :] + 1e-9 * eye)
        g = grad[active].copy()
        # A blur at its floor that the step would push below is held for this step (an active
        # set): clamping the step instead would spoil the other parameters' steps, and the fit creep.
        for j in bounded:
            held = (params[active, j] <= MIN_BLUR) & (g[:, j] > 0)
            damped[held, j, :], damped[held, :, j], damped[held, j, j], g[held, j] = 0.0, 0.0, 1.0, 0.0
        try:
            step = -np.linalg.solve(damped, g[..., None])[..., 0]
        except np.linalg.LinAlgError:
            step = -np.stack([np.linalg.lstsq(d, r, rcond=None)[0] for d, r in zip(damped, g)])
        trial = params[active] + step
        trial[:, bounded] = np.maximum(trial[:, bounded], MIN_BLUR)
        # The trial's Jacobian with its values: the next step's normal equations where it is taken.
        rows = slice(None) if len(active) == n else active  # no copies while every fit is active
        small = np.hypot(step[:, 0], step[:, 1]) < 1e-4
        if compiled:
            new_cost, new_hess, new_grad, new_meat = _xfit.normal_equations(trial, x[rows], y[rows], values[rows],
                                                                            weights[rows], meat_rows=small)
        else:
            new_cost, new_hess, new_grad = _equations(model, trial, x[rows], y[rows], values[rows], weights[rows])
        better = np.isfinite(new_cost) & (new_cost <= cost[active])
        taken = active[better]
        params[taken], cost[taken] = trial[better], new_cost[better]
        hess[taken], grad[taken] = new_hess[better], new_grad[better]
        if compiled:
            meat[taken], has_meat[taken] = new_meat[better], small[better]
        lam[active] = np.where(better, lam[active] / 3.0, lam[active] * 4.0)
        done = (better & small) | (lam[active] > 1e6)
        converged[active[done]] = better[done] | small[done]
        active = active[~done]
    if not compiled:
        cost, hess, meat = _sandwich(model, params, x, y, values, weights)
    elif not has_meat.all():  # the fits not ended by a small step taken: their covariance's parts made again
        again = np.flatnonzero(~has_meat)
        cost[again], hess[again], meat[again] = _sandwich(model, params[again], x[again], y[again], values[again],
                                                          weights[again])
    sw = weights.sum(1)
    dof = np.maximum(np.count_nonzero(weights > 0, axis=1) - n_params, 1)
    sigma2 = cost / np.maximum(sw, 1e-12) * np.count_nonzero(weights > 0, axis=1) / dof
    cov = np.full((n, 2, 2), np.nan)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # a degenerate fit (a shade of no area): NaN
        ok = np.isfinite(hess).all(axis=(1, 2)) & (np.abs(np.linalg.det(hess)) > 0)
        if ok.any():
            inv = np.linalg.inv(hess[ok])
            cov[ok] = (sigma2[ok, None, None] * (inv @ meat[ok] @ inv))[:, :2, :2]
    rms = np.sqrt(cost / np.maximum(sw, 1e-12))
    return params, cov, rms, converged


REJECT_RESIDUAL = 0.08  # fit RMS residual / contrast above which a corner is rejected
MAX_SIGMA_PX = 0.5  # corners less certain than this are rejected
MIN_EDGE_ANGLE = np.radians(15.0)  # edges closer than this in direction are degenerate


def rejection_reasons(params, cov, rms, converged, uv, limit, window) -> np.ndarray:
    """(n,) '' for a good fit (window radius (n,) px), else why the corner is rejected (`refine.REASONS`)."""
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
