"""Coarse centring of X-corners by the gradient condition (as cv2.cornerSubPix does it).

The centre of an X-corner is the point through which all its edges pass: for every pixel x_i near
it with image gradient g_i, g_i . (p - x_i) = 0. `seed` takes a few steps of the Gaussian-weighted
least squares of that condition in a small window: the start of `refine`'s model fit and of
`shadow`'s.
"""

from __future__ import annotations

import numpy as np

from . import _centring
from .rings import _flat

SEED_RADIUS = 5.0
SEED_EPS = 0.01
SEED_STEPS = 4
SIGMA_FRACTION = 0.35
MIN_SIGMA = 2.5


def seed(img: np.ndarray, uv: np.ndarray, max_shift) -> np.ndarray:
    """A coarse centring (n, 2) with a small window (SEED_RADIUS); NaN where it fails."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    # A few steps, not to convergence: under strong blur a small window's fixed point can drift.
    return _refine_fixed(img, uv, SEED_RADIUS, SEED_STEPS, SEED_EPS,
                         np.broadcast_to(np.asarray(max_shift, float), (len(uv),)), converge=False)


def _refine_fixed(img, start, radius, max_iterations, eps, max_shift, converge: bool = True) -> np.ndarray:
    """`_refine_fixed_numpy` in compiled steps per point (`_centring.gradient_steps`, the same numbers)
    where img is a C-ordered float32 image (h, w) or `rings.ImageParts`."""
    flat = _flat(img)
    if flat is None:
        return _refine_fixed_numpy(img, start, radius, max_iterations, eps, max_shift, converge)
    buffer, bases, lefts, tops, widths, heights, rows, _, cells, cell_px = flat
    cells = np.zeros((1, 1), dtype=np.intp) if cells is None else cells
    start = np.array(start, dtype=float).reshape(-1, 2)
    height, width = img.shape
    return _centring.gradient_steps(buffer, bases, lefts, tops, widths, heights, rows, cells, cell_px, height, width,
                                    start,
                                    _half_window(radius, max_shift), float(radius), _sigma2(radius), max_iterations,
                                    eps, np.broadcast_to(np.asarray(max_shift, float), (len(start),)), converge)


def _half_window(radius: float, max_shift) -> int:
    """Half-size (px) of the fixed window about the start (weights follow p smoothly, so the iteration converges)."""
    return int(np.ceil(radius + min(float(np.max(max_shift, initial=0.0)), 2 * radius + 4))) + 1


def _sigma2(radius: float) -> float:
    """2 sigma^2 of the Gaussian weights: not narrower than MIN_SIGMA (the blurred saddle at the very
    centre violates the edge model)."""
    return 2.0 * max(SIGMA_FRACTION * radius, MIN_SIGMA) ** 2


def _refine_fixed_numpy(img, start, radius, max_iterations, eps, max_shift, converge: bool = True) -> np.ndarray:
    """The gradient condition's fixed point with one window half-size for all points, vectorized over points (n, 2).

    Gradients are central differences at the integer pixels of a window around the start (no
    interpolation, whose smoothing depends on the sub-pixel phase and would bias the result);
    p = argmin sum_i w_i (g_i . (p - x_i))^2 in closed form, the Gaussian weights w_i centred on
    the previous p; iterated until p moves less than `eps`.
    """
    height, width = img.shape
    half = _half_window(radius, max_shift)
    offs = np.arange(-half, half + 1)
    oy, ox = np.meshgrid(offs, offs, indexing="ij")
    ox, oy = ox.ravel(), oy.ravel()
    sigma2 = _sigma2(radius)
    p = np.array(start, dtype=float).reshape(-1, 2)
    n = len(p)
    out = np.full((n, 2), np.nan)
    active = np.nonzero(np.all(np.isfinite(p), axis=1))[0]
    # The window and its gradients stay where the start put them: gathered once, for every step.
    cx, cy = np.rint(p[active, 0]).astype(int), np.rint(p[active, 1]).astype(int)
    x_all = cx[:, None] + ox[None]  # (k, m) integer pixel positions
    y_all = cy[:, None] + oy[None]
    xc, yc = np.clip(x_all, 1, width - 2), np.clip(y_all, 1, height - 2)
    gx_all = 0.5 * (img[yc, xc + 1].astype(np.float64) - img[yc, xc - 1])
    gy_all = 0.5 * (img[yc + 1, xc].astype(np.float64) - img[yc - 1, xc])
    kept_all = (x_all == xc) * (y_all == yc)
    slot = np.full(n, -1)
    slot[active] = np.arange(len(active))
    for _ in range(max_iterations):
        if len(active) == 0:
            break
        q = p[active]
        inside = (q[:, 0] >= 0) & (q[:, 0] <= width - 1) & (q[:, 1] >= 0) & (q[:, 1] <= height - 1)
        q = np.where(inside[:, None], q, 0.0)  # a step outside the image ends that point (ok below)
        rows = slot[active]
        x, y, gx, gy = x_all[rows], y_all[rows], gx_all[rows], gy_all[rows]
        rx, ry = x - q[:, :1], y - q[:, 1:]
        d2 = rx**2 + ry**2
        # Gaussian tapered smoothly to 0 at `radius`: no pixel enters or leaves the window abruptly.
        w = np.exp(-d2 / sigma2) * np.maximum(1.0 - d2 / radius**2, 0.0) ** 2 * kept_all[rows]
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
