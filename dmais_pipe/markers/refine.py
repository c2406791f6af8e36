"""Sub-pixel refinement of X-corners (diagonal markers, inner chessboard corners).

The centre of an X-corner is the point through which all its edges pass: for every pixel x_i near
it with image gradient g_i, g_i . (p - x_i) = 0. `refine` solves the Gaussian-weighted least squares
of that condition iteratively (as cv2.cornerSubPix does), on a float patch sampled bilinearly
around the current estimate, with a window adapted to each corner's size: the largest ring around
the corner that still shows a clean four-sector pattern (`clean_radius`), so large markers use
many edge pixels (less noise) and small chessboard squares never let a neighbour into the window.
"""

from __future__ import annotations

import cv2
import numpy as np

RING_SAMPLES = 48
MIN_RADIUS = 2.5  # px, smallest window half-size
MAX_RADIUS = 40.0  # px, largest window half-size
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


def refine(image, uv, radius=None, max_iterations: int = 30, eps: float = 1e-3,
           max_shift: float | None = None) -> np.ndarray:
    """Sub-pixel X-corner positions (n, 2) from approximate ones uv (n, 2) (within ~2 px).

    image: (h, w) 8/16-bit or float grayscale. radius: window half-size in px, a scalar or (n,);
    default per point: a first pass with a 4 px window, then 0.8 x the largest clean X ring around
    that (`clean_radius`), within [2.5, 40] px (and inside the image). Rows are NaN where the
    iteration does not converge, the gradients show fewer than two edge directions, or the point
    moves farther than `max_shift` (default 3 px; max(3, radius) with an explicit radius).
    """
    img = as_float_image(image)
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    n = len(uv)
    if n == 0:
        return np.zeros((0, 2))
    height, width = img.shape
    if radius is None:
        limit = np.full(n, 3.0 if max_shift is None else float(max_shift))
        first = seed(img, uv, limit)
        start = np.where(np.isfinite(first), first, uv)
        radius = np.clip(RADIUS_FRACTION * clean_radius(img, start), MIN_RADIUS, MAX_RADIUS)
        limit = np.where(np.isfinite(first[:, 0]), 1.5, limit)  # the seed pass has centred the point
    else:
        start = uv
        radius = np.broadcast_to(np.asarray(radius, dtype=float), (n,))
        limit = np.maximum(3.0, radius) if max_shift is None else np.full(n, float(max_shift))
    # Windows must stay inside the image (a replicated border biases the gradients).
    room = np.min([start[:, 0], start[:, 1], width - 1 - start[:, 0], height - 1 - start[:, 1]], axis=0) - limit - 2.0
    radius = np.where(np.isfinite(room), np.minimum(radius, np.maximum(np.floor(room), MIN_RADIUS)), radius)
    out = np.full((n, 2), np.nan)
    for value in np.unique(radius[np.isfinite(radius)]):
        for shift in np.unique(limit):
            idx = np.nonzero((radius == value) & (limit == shift))[0]
            if len(idx):
                out[idx] = _refine_fixed(img, start[idx], float(value), max_iterations, eps, limit[idx])
    moved = np.hypot(*(out - uv).T) > (3.0 + (0 if max_shift is None else max_shift))
    out[moved] = np.nan
    return out


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
