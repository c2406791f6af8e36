"""Detection of diagonal markers (X-corners) in a grayscale image.

1. Candidates: on the half-resolution level of the image pyramid (X-corners look the same at every
   scale, so one level serves markers from ~20 px to thousands of px), the saddle response
   Ixy^2 - Ixx Iyy of the Gaussian-smoothed image, local maxima above a threshold tied to the
   minimum contrast.
2. Verification at full resolution by rings around the candidate (`refine.ring_quality`): an
   X-corner ring is two-valued, point symmetric and changes level exactly four times (two dark
   opposite sectors, two bright opposite sectors), whatever the rotation, foreshortening or
   polarity. Board outline corners (L), T-junctions and texture fail it.
3. Sub-pixel refinement (`refine.refine_corners`: a blurred X-corner model fit, which rejects a
   corner whose fit is poor and gives each its uncertainty) and de-duplication.
"""

from __future__ import annotations

import cv2
import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from .refine import _ring_offsets, as_float_image, clean_radius, refine_corners, ring_quality, sample, seed

COLUMNS = ["u", "v", "score", "sigma_px", "fit_residual"]
REJECTED_COLUMNS = ["u", "v", "reason"]
MIN_CONTRAST = 50.0  # DN (8-bit) between the bright and the dark sectors
MIN_QUALITY = 0.7  # ring quality (bimodality x point symmetry) at the verification radii
PRE_QUALITY = 0.3  # looser quality of the prefilter at the unrefined candidate position
MIN_CLEAN_RADIUS = 4.0  # px: the ring must stay an X up to at least this radius
RESPONSE_FACTOR = 0.004  # response threshold = (factor * min contrast)^2 at the half-resolution level
MAX_CANDIDATES = 20000
DUPLICATE_PX = 2.0


def _empty() -> pd.DataFrame:
    return pd.DataFrame({name: pd.Series(dtype=float) for name in COLUMNS})


def _dn_scale(image: np.ndarray) -> float:
    """Factor from 8-bit DN to the image's units (1 for uint8; from the bright end of 16-bit data)."""
    if image.dtype == np.uint8:
        return 1.0
    step = max(1, image.size // 100000)
    bright = float(np.percentile(image.reshape(-1)[::step], 99.5))
    return max(bright / 220.0, 1e-6)


def candidates(img: np.ndarray, min_contrast: float) -> np.ndarray:
    """(k, 2) full-resolution candidate positions, strongest first (at most MAX_CANDIDATES)."""
    if min(img.shape) < 8:
        return np.zeros((0, 2))
    level = cv2.pyrDown(img)
    smooth = cv2.GaussianBlur(level, (0, 0), 1.0)
    dxx = cv2.Sobel(smooth, cv2.CV_32F, 2, 0, ksize=3)
    dyy = cv2.Sobel(smooth, cv2.CV_32F, 0, 2, ksize=3)
    dxy = cv2.Sobel(smooth, cv2.CV_32F, 1, 1, ksize=3)
    dxx *= dyy
    dxy *= dxy
    dxy -= dxx  # saddle response, > 0 at saddles
    del dxx, dyy
    response = dxy
    threshold = np.float32((RESPONSE_FACTOR * min_contrast) ** 2 * 1e4)
    peaks = cv2.dilate(response, np.ones((5, 5), np.uint8))
    ys, xs = np.nonzero((response >= peaks) & (response > threshold))
    strength = response[ys, xs]
    order = np.argsort(-strength)[:MAX_CANDIDATES]
    return np.column_stack([2.0 * xs[order], 2.0 * ys[order]]).astype(float)


def detect(image, min_contrast: float = MIN_CONTRAST, min_quality: float = MIN_QUALITY,
           refine_points: bool = True, with_rejected: bool = False):
    """Every diagonal marker (X-corner) of a (h, w) 8/16-bit grayscale image.

    Returns a DataFrame with columns u, v (refined, OpenCV pixel convention), score in [0, 1]
    (ring quality x min(largest clean ring radius, 10 px) / 10 px: higher is surer), sigma_px (the
    refinement's standard deviation per axis, px: a weight 1 / sigma^2) and fit_residual (the
    model fit's RMS residual / contrast), sorted by v then u. min_contrast is in 8-bit DN (scaled
    to the bright end of 16-bit images). Markers whose X-corner is nearer than ~5 px to the image
    border are not found. With `with_rejected`, also a DataFrame u, v, reason of the verified
    X-corners the refinement rejected (e.g. a poor fit: a shadow edge or an occluder through it).
    """
    raw = np.asarray(image)
    img = as_float_image(raw)
    contrast = min_contrast * _dn_scale(raw)
    cand = _verified(img, contrast, min_quality)
    rejected = pd.DataFrame({name: pd.Series(dtype=object if name == "reason" else float) for name in REJECTED_COLUMNS})
    if len(cand) == 0:
        return (_empty(), rejected) if with_rejected else _empty()
    cand, radius, quality = cand
    sigma = fit = np.full(len(cand), np.nan)
    if refine_points:
        corners = refine_corners(img, cand)
        ok = np.all(np.isfinite(corners.uv), axis=1)
        rejected = pd.DataFrame({"u": cand[~ok, 0], "v": cand[~ok, 1], "reason": corners.reason[~ok]})
        cand, radius, quality = corners.uv[ok], radius[ok], quality[ok]
        sigma, fit = corners.sigma_px[ok], corners.fit_residual[ok]
        # The refined centre must still be the centre of a clean X.
        radius = np.minimum(radius, clean_radius(img, cand, min_quality=min_quality))
        ok = radius >= MIN_CLEAN_RADIUS
        lost = pd.DataFrame({"u": cand[~ok, 0], "v": cand[~ok, 1], "reason": "no clean X at the fit"})
        rejected = pd.concat([rejected, lost], ignore_index=True) if len(lost) else rejected
        cand, radius, quality, sigma, fit = cand[ok], radius[ok], quality[ok], sigma[ok], fit[ok]
    score = np.clip(quality * np.minimum(radius, 10.0) / 10.0, 0.0, 1.0)
    keep = _dedupe(cand, score)
    frame = pd.DataFrame({"u": cand[keep, 0], "v": cand[keep, 1], "score": score[keep], "sigma_px": sigma[keep],
                          "fit_residual": fit[keep]}).sort_values(["v", "u"], ignore_index=True)
    return (frame, rejected) if with_rejected else frame


def _verified(img: np.ndarray, contrast: float, min_quality: float):
    """(candidates (k, 2), clean radius (k,), ring quality (k,)) of the X-corners that pass the
    ring tests, unrefined (centred by `seed`); an empty tuple when there are none."""
    height, width = img.shape
    cand = candidates(img, contrast)
    if len(cand) == 0:
        return ()
    # Prefilter at the unrefined position: a ring of radius 4 px must already look like an X.
    values = sample(img, cand[:, None, :] + _ring_offsets(4.0)[None])
    quality, ring_contrast = ring_quality(values)
    cand = cand[(quality >= PRE_QUALITY) & (np.abs(ring_contrast) >= contrast)]
    if len(cand) == 0:
        return ()
    seeded = seed(img, cand, 3.0)
    cand = seeded[np.all(np.isfinite(seeded), axis=1)]
    cand = cand[(cand[:, 0] >= 0) & (cand[:, 0] <= width - 1) & (cand[:, 1] >= 0) & (cand[:, 1] <= height - 1)]
    cand = cand[_dedupe(cand, np.ones(len(cand)))]
    if len(cand) == 0:
        return ()
    radius = clean_radius(img, cand, min_quality=min_quality)
    good = radius >= MIN_CLEAN_RADIUS
    cand, radius = cand[good], radius[good]
    if len(cand) == 0:
        return ()
    # Contrast and quality on a ring well inside the clean area, away from the blurred centre.
    probe = np.clip(0.5 * radius, 3.0, 12.0)[:, None, None]
    quality, ring_contrast = ring_quality(sample(img, cand[:, None, :] + probe * _ring_offsets(1.0)[None]))
    good = np.abs(ring_contrast) >= contrast
    if not good.any():
        return ()
    return cand[good], radius[good], quality[good]


def _dedupe(points: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Indexes (k,) of the best-scoring point of every cluster of points (n, 2) closer than DUPLICATE_PX."""
    if len(points) < 2:
        return np.arange(len(points))
    order = np.argsort(-score, kind="stable")
    tree = cKDTree(points)
    taken = np.zeros(len(points), dtype=bool)
    keep = []
    for i in order:
        if taken[i]:
            continue
        keep.append(i)
        taken[tree.query_ball_point(points[i], DUPLICATE_PX)] = True
    return np.array(keep, dtype=int)
