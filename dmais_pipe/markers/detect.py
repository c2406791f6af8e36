"""Detection of diagonal markers (X-corners) in a grayscale image.

1. Candidates: on the half-resolution level of the image pyramid (X-corners look the same at every
   scale, so one level serves markers from ~20 px to thousands of px), the saddle response
   Ixy^2 - Ixx Iyy of the Gaussian-smoothed image, local maxima above a threshold tied to
   MIN_CONTRAST (loose enough for markers of less contrast, e.g. in the shade).
   The minimum contrast of the ring tests is set from the image's clutter (`clutter`: noise and
   ground texture at the scale of the smallest markers), between MIN_CONTRAST_FLOOR and
   MIN_CONTRAST: a marker in the shade keeps ~40% of its contrast, which quiet ground leaves far
   above anything the ground itself forms, while gravel or a cluttered photograph keeps the full
   threshold. An X-corner that a shadow edge crosses near its centre fails the ring tests: it is
   fitted with the shadow edge in the model (`shadow.shadowed_corners`) and returned where that
   fit passes its checks, else reported as rejected with that reason (SHADOW_REASON; also where
   the stricter ring test `shadowed_x` finds a shadowed X the fit did not start on).
2. Verification at full resolution by rings around the candidate (`rings.ring_quality`): an
   X-corner ring is two-valued, point symmetric and changes level exactly four times (two dark
   opposite sectors, two bright opposite sectors), whatever the rotation, foreshortening or
   polarity. Board outline corners (L), T-junctions and texture fail it.
3. Sub-pixel refinement (`refine.refine_corners`: a blurred X-corner model fit, which rejects a
   corner whose fit is poor and gives each its uncertainty; where it calls a corner asymmetric or
   its fit poor, ASYMMETRIC_REASONS, a shadow edge near it is the likely cause, and the fit with
   the edge in the model has a second go), the rejection of detections less
   certain than MAX_SIGMA_PX (UNCERTAIN), and de-duplication.
4. Textured ground (`ground_texture_like`): the contrast threshold stops at MIN_CONTRAST so that
   markers in the shade are found on gravel and grass, but there the ground itself forms X's of
   that contrast: saddles of its texture, clean over the first rings only (scores 0.25-0.58 on
   texture of 25-40 DN blurred by 0.8-2.5 px, contrast up to 13 x the clutter). A saddle of a
   band-limited texture is smooth: on a ring about it the ground is at best a sinusoid of twice the
   angle (the saddle's second-order term), whose ring quality is the bimodality of a sinusoid,
   8 / pi^2 = 0.81, while a marker's ring is a square wave that only the optical blur rounds. An X
   whose contrast is below TEXTURE_FACTOR x the clutter must either score at least
   TEXTURE_MIN_SCORE, stay a clean X to 10 px (markers of 30 px and more seen at up to 45 deg
   score >= 0.87 there), or be sharper than a smooth saddle on a ring near its clean radius
   (`sharpness` >= SHARP_QUALITY: a marker too small or too steep to stay clean to 10 px still has
   a square-wave ring), else it is rejected (TEXTURE).
"""

from __future__ import annotations

import time

import cv2
import numpy as np
import pandas as pd

from . import _rings, _shadow
from .centring import seed
from .neighbours import Neighbours
from .refine import ASYMMETRIC, NO_CLEAN_X, refine_corners
from .rings import (RADII, as_float_image, clean_radius, half_turn, ring_offsets, ring_quality, ring_sample, ring_stats,
                    sample)
from .shadow import SAME_RATIO, SHADOW_REASON, both_sides, line_ends, log_ring_sample, shadowed_corners, step_masks

COLUMNS = ["u", "v", "score", "sigma_px", "fit_residual"]
REJECTED_COLUMNS = ["u", "v", "reason"]
#: px: how far a detection or rejection lies from its candidate at most (the centring's 3 px, the fit's
#: 3 px from that, the fit with a shadow edge's 4 + 8 px), with room.
MOVE_PX = 24
#: px: how far from a candidate its tests and fits read the image: the largest ring of `clean_radius`
#: (`rings.RADII`) and its bilinear neighbour about any position the candidate moves to.
REACH_PX = int(np.ceil(RADII[-1])) + 1 + MOVE_PX
MIN_CONTRAST = 50.0  # DN (8-bit) between the bright and the dark sectors, at most
MIN_CONTRAST_FLOOR = 25.0  # DN (8-bit): the threshold on the quietest images
CLUTTER_FACTOR = 15.0  # threshold = factor x clutter, within [floor, MIN_CONTRAST]
MIN_QUALITY = 0.7  # ring quality (bimodality x point symmetry) at the verification radii
PRE_QUALITY = 0.3  # looser quality of the prefilter at the unrefined candidate position
MIN_CLEAN_RADIUS = 4.0  # px: the ring must stay an X up to at least this radius
RESPONSE_FACTOR = 0.004  # response threshold = (factor * min contrast)^2 at the half-resolution level
MAX_CANDIDATES = 20000
#: px: rings about a saddle peak beyond the MAX_CANDIDATES strongest that must all look like an X for it to
#: be a candidate still (`candidates`): a marker of >= 30 px stays an X to ~8 px, a saddle of texture not.
RESCUE_RADII_PX = (4.0, 6.0, 8.0)
DUPLICATE_PX = 2.0
MAX_SIGMA_PX = 0.1  # px: detections less certain than this are rejected (UNCERTAIN)
UNCERTAIN = "uncertain for a detection (sigma > 0.1 px)"
ASYMMETRIC_REASONS = (ASYMMETRIC, "poor fit", NO_CLEAN_X)  # refinement failures a shadow edge can cause
# Textured ground (`ground_texture_like`). Measured on white noise blurred by 0.8-2.5 px, 25-40 DN,
# ~1400 false detections: their contrast reached 13.2 x the clutter, their score 0.58; the markers
# of the effects benchmark stay >= 24 x the clutter (those of 20 px score down to 0.33 there), the
# markers of >= 30 px on that texture score >= 0.87. Both limits lie between, ~1.35 x from either side.
TEXTURE_FACTOR = 18.0  # an X's contrast below this x the clutter is within what the texture forms
TEXTURE_MIN_SCORE = MIN_QUALITY  # ... and needs a score of a clean X (quality MIN_QUALITY) to 10 px
# ... or a ring sharper than a smooth saddle's: the better of the rings at 3/4 of the clean radius and at
# the clean radius (3-12 px; beyond the probe ring, so that the optical blur rounds less of them). Saddles
# of 15-40 DN texture blurred by 0.8-2.5 px (553 that reached this rule) stayed <= 0.827 on either ring
# (a sinusoid's 8 / pi^2 = 0.81, and noise); 30 px markers foreshortened up to 60 deg (15 px across),
# 75-170 DN, on 40 DN texture (58 that the score alone rejected) >= 0.859, 30-60 px ones >= 0.90.
# The limit lies between, 1.5-2 % from either side: the saddles' side is the sinusoid's bound.
SHARP_RING_SHARES = (0.75, 1.0)
SHARP_QUALITY = 0.84
TEXTURE = (f"within the ground texture (contrast < {TEXTURE_FACTOR:g} x clutter, score < {TEXTURE_MIN_SCORE:g}, "
           f"ring quality < {SHARP_QUALITY:g})")


def _empty() -> pd.DataFrame:
    return pd.DataFrame({name: pd.Series(dtype=float) for name in COLUMNS})


def _dn_scale(image: np.ndarray) -> float:
    """Factor from 8-bit DN to the image's units (1 for uint8; from the bright end of 16-bit data)."""
    if image.dtype == np.uint8:
        return 1.0
    step = max(1, image.size // 100000)
    flat = image.reshape(-1)
    bright = _percentile_u16(flat, 99.5, step) if flat.dtype == np.uint16 else float(np.percentile(flat[::step], 99.5))
    return max(bright / 220.0, 1e-6)


def _percentile_u16(values: np.ndarray, q: float, step: int = 1) -> float:
    """float(np.percentile(values[::step], q)) of uint16 values (n,), n > 0, to the last bit: its two order
    statistics from the sampled values' counts instead of a partition (`_rings.strided_ranks_u16`, one
    pass over the samples without their copy; np.bincount where values are not contiguous), interpolated
    as numpy's `_lerp` does (in float64: a + (b - a) t, or b - (b - a) (1 - t) where t >= 0.5)."""
    n = (len(values) + step - 1) // step
    virtual = (n - 1) * (q / 100.0)
    if virtual >= n - 1:
        low = high = n - 1
    else:
        low = int(np.floor(virtual))
        high = low + 1
    gamma = virtual - low
    if values.ndim == 1 and values.flags.c_contiguous:
        a, b = (float(v) for v in _rings.strided_ranks_u16(values, step, low, high))
    else:
        counts = np.cumsum(np.bincount(values[::step], minlength=1))
        a, b = (float(v) for v in np.searchsorted(counts, [low + 1, high + 1]))  # the values of sorted ranks low, high
    diff = b - a
    return b - diff * (1.0 - gamma) if gamma >= 0.5 else a + diff * gamma


def _median_of_abs(values: np.ndarray):
    """np.median(np.abs(values)) of float32 values (n,), to the last bit: the middle order statistics of
    |values| by their bits (non-negative float32 sort as their uint32 patterns; two counting passes of 16
    bits each instead of a partition), then np.mean of them as np.median takes it; np.median's own where
    a value is NaN or the values are no float32."""
    values = np.abs(values)
    if values.dtype != np.float32 or values.ndim != 1 or len(values) == 0 or np.isnan(values).any():
        return np.median(values)
    n = len(values)
    bits = values.view(np.uint32)
    high = (bits >> 16).astype(np.intp)
    counts = np.cumsum(np.bincount(high, minlength=1))
    ranks = [n // 2 - 1, n // 2] if n % 2 == 0 else [(n - 1) // 2]
    middle = []
    for rank in ranks:
        top = int(np.searchsorted(counts, rank + 1))  # the high 16 bits of the value of this rank
        before = int(counts[top - 1]) if top else 0
        low = np.sort(bits[high == top] & 0xFFFF, kind="stable") if not middle or middle[-1][0] != top else middle[-1][1]
        middle.append((top, low, (top << 16) | int(low[rank - before])))
    return np.mean(np.array([m[2] for m in middle], dtype=np.uint32).view(np.float32))


def clutter(level: np.ndarray) -> float:
    """Robust standard deviation (image units) of a band-pass (Gaussians of 1 and 2 px) of the
    half-resolution level (h, w) on tiles spread over it (`tile_boxes`): pixel noise and fine ground
    texture, where the few markers and edges of an image do not move the median."""
    return clutter_of_tiles([level[y0:y1, x0:x1] for y0, y1, x0, x1 in tile_boxes(level.shape)])


def clutter_of_tiles(tiles: list[np.ndarray]) -> float:
    """`clutter` of the level's tiles (each (80, 80), or the whole level)."""
    band = np.concatenate([(cv2.GaussianBlur(t, (0, 0), 1.0) - cv2.GaussianBlur(t, (0, 0), 2.0)).ravel()
                           for t in tiles])
    return float(1.4826 * _median_of_abs(band))  # a band-pass has zero mean


def tile_boxes(shape: tuple[int, int], size: int = 80, count: int = 4) -> list[tuple[int, int, int, int]]:
    """(y0, y1, x0, x1) of count x count square tiles (size px) spread evenly over an image of
    `shape` (h, w), or the whole image when it is not much larger: a sample of its texture at a
    fraction of the cost."""
    height, width = shape
    if height * width <= 4 * count * count * size * size:
        return [(0, height, 0, width)]
    return [(y, y + size, x, x + size) for y in np.linspace(0, height - size, count).astype(int)
            for x in np.linspace(0, width - size, count).astype(int)]


def contrast_threshold(level: np.ndarray, dn_scale: float) -> float:
    """The minimum contrast (image units) for the half-resolution level (h, w) of an image whose
    8-bit DN are `dn_scale` of its units: CLUTTER_FACTOR x its clutter within the bounds."""
    return _threshold(clutter(level), dn_scale)


def _threshold(texture: float, dn_scale: float) -> float:
    """`contrast_threshold` of an image of clutter `texture` (image units)."""
    return float(np.clip(CLUTTER_FACTOR * texture, MIN_CONTRAST_FLOOR * dn_scale, MIN_CONTRAST * dn_scale))


def ground_texture_like(img: np.ndarray, uv: np.ndarray, radius: np.ndarray, score: np.ndarray,
                        texture: float) -> np.ndarray:
    """(n,) True where the X-corners at uv (n, 2) of clean radius (n,) px and score (n,) in an
    image (h, w) of clutter `texture` (image units) could be a saddle of the ground's texture:
    their contrast on the probe ring (`_probe_ring`) is below TEXTURE_FACTOR x the clutter, their
    score below TEXTURE_MIN_SCORE and their ring no sharper than a smooth saddle's (`sharpness`
    below SHARP_QUALITY)."""
    if len(uv) == 0:
        return np.zeros(0, dtype=bool)
    _, ring_contrast = _probe_ring(img, uv, radius)
    within = (np.abs(ring_contrast) < TEXTURE_FACTOR * texture) & (score < TEXTURE_MIN_SCORE)
    if within.any():
        within[within] = sharpness(img, uv[within], radius[within]) < SHARP_QUALITY
    return within


def sharpness(img: np.ndarray, uv: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """(n,) the best `ring_quality` of the rings about uv (n, 2) at SHARP_RING_SHARES of the clean
    radius (n,) px, 3-12 px: about 1 for a marker's square-wave ring, at most ~0.81 (a sinusoid)
    for a smooth saddle of the ground's texture."""
    quality = [ring_quality(sample(img, uv[:, None, :] + np.clip(share * radius, 3.0, 12.0)[:, None, None]
                                   * ring_offsets(1.0)[None]))[0] for share in SHARP_RING_SHARES]
    return np.max(quality, axis=0)


def _probe_ring(img: np.ndarray, uv: np.ndarray, radius: np.ndarray):
    """`ring_quality` (quality (n,), contrast (n,)) of the ring about uv (n, 2) well inside the
    clean area of radius (n,) px and away from the blurred centre: half the radius, 3-12 px."""
    probe = np.clip(0.5 * radius, 3.0, 12.0)[:, None, None]
    return ring_quality(sample(img, uv[:, None, :] + probe * ring_offsets(1.0)[None]))


def candidates(img: np.ndarray, min_contrast: float, level: np.ndarray | None = None) -> np.ndarray:
    """(k, 2) full-resolution candidate positions: the saddle peaks, strongest first, at most
    MAX_CANDIDATES of them, then those of the weaker peaks that look like an X over every ring of
    RESCUE_RADII_PX (`x_over_rings`); `level`: cv2.pyrDown(img) if already made. On strong texture
    the peaks are ~10^5 and a faint marker's need not be among the strongest (a 40 DN texture at
    1.2-2 px blur: ranks up to ~70,000 of ~220,000), but its rings stay an X where the texture's
    saddles do not (among those peaks, ~600 of the texture's look as much an X as the least of the
    markers)."""
    if min(img.shape) < 8:
        return np.zeros((0, 2))
    level = cv2.pyrDown(img) if level is None else level
    ys, xs, strength = saddle_peaks(saddle_response(level), min_contrast)
    ordered = _by_strength(2 * xs, 2 * ys, strength)
    kept, weaker = ordered[:MAX_CANDIDATES], ordered[MAX_CANDIDATES:]
    return np.vstack([kept, weaker[x_over_rings(img, weaker, min_contrast)]]) if len(weaker) else kept


def saddle_response(level: np.ndarray) -> np.ndarray:
    """(h, w) float32 saddle response Ixy^2 - Ixx Iyy (> 0 at saddles) of the Gaussian-smoothed
    half-resolution level (h, w). A pixel's value depends on the level's pixels within
    RESPONSE_SUPPORT_PX of it (and on the level's border where that is nearer)."""
    smooth = cv2.GaussianBlur(level, (0, 0), 1.0)
    dxx = cv2.Sobel(smooth, cv2.CV_32F, 2, 0, ksize=3)
    dyy = cv2.Sobel(smooth, cv2.CV_32F, 0, 2, ksize=3)
    dxy = cv2.Sobel(smooth, cv2.CV_32F, 1, 1, ksize=3)
    dxx *= dyy
    dxy *= dxy
    dxy -= dxx  # saddle response, > 0 at saddles
    return dxy


#: Half-resolution px a saddle peak depends on: the blur's kernel (sigma 1: 4), Sobel (1), the 3 x 3 maximum (1).
RESPONSE_SUPPORT_PX = 6


def saddle_peaks(response: np.ndarray, min_contrast: float):
    """(ys (k,), xs (k,), strength (k,)) of the local 3 x 3 maxima of `response` (h, w) above the
    threshold of `min_contrast`, in raster order."""
    threshold = np.float32((RESPONSE_FACTOR * min_contrast) ** 2 * 1e4)
    peaks = cv2.dilate(response, np.ones((3, 3), np.uint8))
    # The few above the threshold (~0.4% of a window's level) first, then which of them are maxima: the
    # same positions in the same (raster) order as np.nonzero((response >= peaks) & (response > threshold)).
    values = response.reshape(-1)
    at = np.flatnonzero(values > threshold)
    at = at[values[at] >= peaks.reshape(-1)[at]]
    ys, xs = np.divmod(at, response.shape[1])
    return ys, xs, values[at]


def strongest(x: np.ndarray, y: np.ndarray, strength: np.ndarray) -> np.ndarray:
    """(k, 2) positions x, y (n,) ordered by strength (n,), strongest first, equal strengths in
    raster order (y, then x): at most MAX_CANDIDATES."""
    return _by_strength(x, y, strength)[:MAX_CANDIDATES]


def _by_strength(x: np.ndarray, y: np.ndarray, strength: np.ndarray) -> np.ndarray:
    """(n, 2) positions x, y (n,) ordered by strength (n,), strongest first, equal strengths in raster order."""
    order = np.lexsort((x, y, -strength))
    return np.column_stack([x[order], y[order]]).astype(float)


def x_over_rings(img: np.ndarray, uv: np.ndarray, min_contrast: float) -> np.ndarray:
    """(n,) True where the rings about uv (n, 2) at every radius of RESCUE_RADII_PX pass the
    prefilter of `_verified` (quality PRE_QUALITY, contrast `min_contrast`), in the float image (h, w);
    each ring tested on the positions the smaller ones passed."""
    passed = np.ones(len(uv), dtype=bool)
    for radius in RESCUE_RADII_PX:
        at = np.flatnonzero(passed)
        if len(at) == 0:
            break
        quality, ring_contrast = ring_quality(ring_sample(img, uv[at], ring_offsets(radius)))
        passed[at] = (quality >= PRE_QUALITY) & (np.abs(ring_contrast) >= min_contrast)
    return passed


def contrasts(raw: np.ndarray, texture: float | None, min_contrast: float | None = None):
    """(contrast, lit contrast) in the units of the image `raw` (h, w): the ring tests' minimum
    contrast (`min_contrast` in 8-bit DN, None: from the clutter `texture`, None where the image
    has no half-resolution level) and that of a lit X (the candidates' threshold)."""
    scale = _dn_scale(raw)
    if min_contrast is not None or texture is None:
        contrast = (MIN_CONTRAST if min_contrast is None else min_contrast) * scale
    else:
        contrast = _threshold(texture, scale)
    return contrast, MIN_CONTRAST * scale if min_contrast is None else contrast


def detect(image, min_contrast: float | None = None, min_quality: float = MIN_QUALITY,
           refine_points: bool = True, with_rejected: bool = False, seconds: dict | None = None):
    """Every diagonal marker (X-corner) of a (h, w) 8/16-bit grayscale image.

    Returns a DataFrame with columns u, v (refined, OpenCV pixel convention), score in [0, 1]
    (ring quality x min(largest clean ring radius, 10 px) / 10 px: higher is surer), sigma_px (the
    refinement's standard deviation per axis, px: a weight 1 / sigma^2) and fit_residual (the
    model fit's RMS residual / contrast), sorted by v then u. min_contrast is in 8-bit DN (scaled
    to the bright end of 16-bit images); None: set from the image's clutter (`contrast_threshold`).
    Markers whose X-corner is nearer than ~5 px to the image border are not found. With
    `with_rejected`, also a DataFrame u, v, reason of the X-corners found but not returned: those
    the ring tests failed because a shadow edge crosses them near the centre and whose fit with the
    shadow edge failed its checks (SHADOW_REASON, within ~1.5 px of the corner), the verified ones
    the refinement rejected (e.g. a poor fit) and those the ground's texture could form (TEXTURE,
    `ground_texture_like`); none within DUPLICATE_PX of a detection. The corners fitted with a
    shadow edge have the ring quality MIN_QUALITY in their score (their rings pass only with the
    shade divided out).
    """
    seconds = {} if seconds is None else seconds
    started = time.perf_counter()
    raw = np.asarray(image)
    img = as_float_image(raw)
    level = cv2.pyrDown(img) if min(img.shape) >= 8 else None
    texture = clutter(level) if level is not None else None
    contrast, lit_contrast = contrasts(raw, texture, min_contrast)
    # The saddle response threshold stays at the full contrast's: it is loose enough for markers in
    # the shade (the same recall over the effects grid), and the candidates (the cost) stay few.
    cand = candidates(img, max(contrast, lit_contrast), level)
    del level
    found = detections(img, cand, contrast, lit_contrast, 0.0 if texture is None else texture, min_quality,
                       refine_points, seconds, started)
    return found if with_rejected else found[0]


def detections(img: np.ndarray, cand: np.ndarray, contrast: float, lit_contrast: float, texture: float,
               min_quality: float = MIN_QUALITY, refine_points: bool = True, seconds: dict | None = None,
               started: float | None = None):
    """`detect`'s (detections, rejected) in the float image (h, w) from its candidates (k, 2)
    (`candidates`: strongest first), its contrasts (`contrasts`) and clutter (image units).
    Every test and fit reads only the image within `detect.REACH_PX` of a candidate. seconds, if
    given, receives detect_s (since `started`, the verification's end) and refine_s (the rest)."""
    seconds = {} if seconds is None else seconds
    started = time.perf_counter() if started is None else started
    (cand, radius, quality), shadowed, shade = _verified(img, cand, contrast, min_quality, lit_contrast)
    verified = time.perf_counter()
    seconds["detect_s"] = verified - started
    rejected = [(shadowed, SHADOW_REASON)]  # (uv (n, 2), reason) in the order they are reported
    if len(cand) == 0 and len(shade[0]) == 0:
        seconds["refine_s"] = time.perf_counter() - verified
        return _empty(), _rejection_frame(rejected)
    sigma = fit = np.full(len(cand), np.nan)
    if refine_points:
        corners = refine_corners(img, cand)
        ok = np.all(np.isfinite(corners.uv), axis=1)
        # A shadow edge near the corner can fail the plain fit (asymmetric, a poor fit) where the
        # ring tests passed: such candidates get the fit with the edge in the model.
        asymmetric = np.nonzero(~ok & np.isin(corners.reason, ASYMMETRIC_REASONS))[0]
        more, _, why = _shadow_fits(img, cand[asymmetric], contrast, min_quality)
        shade = tuple(np.concatenate([a, b]) for a, b in zip(shade, more))
        dropped = ~ok
        dropped[asymmetric[why == ""]] = False
        rejected.append((cand[dropped], corners.reason[dropped]))
        cand, radius, quality = corners.uv[ok], radius[ok], quality[ok]
        sigma, fit = corners.sigma_px[ok], corners.fit_residual[ok]
        # The refined centre must still be the centre of a clean X.
        radius = np.minimum(radius, clean_radius(img, cand, min_quality=min_quality))
        ok = radius >= MIN_CLEAN_RADIUS
        rejected.append((cand[~ok], "no clean X at the fit"))
        cand, radius, quality, sigma, fit = cand[ok], radius[ok], quality[ok], sigma[ok], fit[ok]
    # X-corners a shadow edge crosses come fitted with it (`shadow.shadowed_corners`).
    cand, radius, quality, sigma, fit = (np.concatenate([a, b]) for a, b in zip((cand, radius, quality, sigma, fit),
                                                                                 shade))
    # Unlike a refinement from a known start, a detection must also be a marker: one this uncertain
    # is mostly none (a "virtual" X of an outline and a shadow edge along its stem; true corners of
    # the benchmarks' hardest regimes stay below ~0.09 px).
    sure = ~(sigma > MAX_SIGMA_PX)
    rejected.append((cand[~sure], UNCERTAIN))
    cand, radius, quality, sigma, fit = cand[sure], radius[sure], quality[sure], sigma[sure], fit[sure]
    score = np.clip(quality * np.minimum(radius, 10.0) / 10.0, 0.0, 1.0)
    ground = ground_texture_like(img, cand, radius, score, texture)
    rejected.append((cand[ground], TEXTURE))
    cand, score, sigma, fit = cand[~ground], score[~ground], sigma[~ground], fit[~ground]
    keep = _dedupe(cand, score)
    keep = keep[np.lexsort((cand[keep, 0], cand[keep, 1]))]  # by v, then u
    frame = pd.DataFrame({"u": cand[keep, 0], "v": cand[keep, 1], "score": score[keep], "sigma_px": sigma[keep],
                          "fit_residual": fit[keep]})
    seconds["refine_s"] = time.perf_counter() - verified
    return frame, _rejection_frame(rejected, cand[keep])


def _rejection_frame(pieces: list[tuple], detected: np.ndarray | None = None) -> pd.DataFrame:
    """The rejections u, v, reason (object) of pieces (uv (n, 2), reason: one or (n,)) in their order,
    those within DUPLICATE_PX of a detection of detected (m, 2) left out: a second candidate of a
    detected X-corner (e.g. started as a shadowed X) is no rejection."""
    uv = np.concatenate([np.asarray(where, dtype=float).reshape(-1, 2) for where, _ in pieces])
    reason = np.concatenate([np.broadcast_to(np.asarray(why, dtype=object), (len(where),)) for where, why in pieces])
    if len(uv) and detected is not None and len(detected):
        kept = Neighbours(detected).query(uv)[0] >= DUPLICATE_PX
        uv, reason = uv[kept], reason[kept]
    return pd.DataFrame({"u": uv[:, 0], "v": uv[:, 1], "reason": pd.Series(reason, dtype=object)})


def uv_of(frame: pd.DataFrame) -> np.ndarray:
    """(n, 2) float: the u, v columns of a detections or rejections frame (`frame[["u", "v"]]`'s values)."""
    return np.column_stack([frame["u"].to_numpy(dtype=float), frame["v"].to_numpy(dtype=float)]).reshape(-1, 2)


def _shadow_fits(img, uv, contrast, min_quality):
    """`shadow.shadowed_corners` about candidates uv (m, 2): (the corners it confirmed as (uv (j, 2),
    clean radius, ring quality min_quality, sigma_px, fit_residual (j,) each), its positions (m, 2)
    and reasons (m,))."""
    found_uv, found_radius, found_sigma, found_fit, why = shadowed_corners(img, uv, contrast, min_quality,
                                                                           MIN_CLEAN_RADIUS)
    saved = why == ""
    return ((found_uv[saved], found_radius[saved], np.full(saved.sum(), min_quality), found_sigma[saved],
             found_fit[saved]), found_uv, why)


def _verified(img: np.ndarray, cand: np.ndarray, contrast: float, min_quality: float, lit_contrast: float = 0.0):
    """(candidates (k, 2), clean radius (k,), ring quality (k,)) of the X-corners that pass the
    ring tests, unrefined (centred by `seed`); the positions (j, 2) of candidates that fail them
    as X-corners crossed by a shadow edge near the centre whose fit with the edge did not confirm
    a corner (`shadow.shadowed_corners`), or that did not start it but pass `shadowed_x` (lit
    side of at least `lit_contrast`); and the corners fitted with a shadow edge (uv (m, 2), clean
    radius, ring quality MIN_QUALITY, sigma_px, fit_residual (m,) each)."""
    height, width = img.shape
    none = (np.zeros((0, 2)), np.zeros(0), np.zeros(0))
    lit_contrast = max(contrast, lit_contrast)
    if len(cand) == 0:
        return none, np.zeros((0, 2)), tuple(np.zeros((0, 2)) if i == 0 else np.zeros(0) for i in range(5))
    # Prefilter at the unrefined position: a ring of radius 4 px must already look like an X.
    values = ring_sample(img, cand, ring_offsets(4.0))
    quality, ring_contrast = ring_quality(values)
    passed = (quality >= PRE_QUALITY) & (np.abs(ring_contrast) >= contrast)
    # A shadowed X keeps its full contrast on the lit side: the rest is texture.
    spread = values.max(axis=1) - values.min(axis=1) >= lit_contrast
    failed, cand = cand[~passed & spread], cand[passed]
    seeded = seed(img, cand, 3.0)
    inside = np.all(np.isfinite(seeded), axis=1)
    inside[inside] = (seeded[inside] >= 0).all(axis=1) & (seeded[inside] <= [width - 1, height - 1]).all(axis=1)
    unseeded, cand = cand[inside], seeded[inside]
    kept = _dedupe(cand, np.ones(len(cand)))
    unseeded, cand = unseeded[kept], cand[kept]
    radius = clean_radius(img, cand, min_quality=min_quality)
    good = radius >= MIN_CLEAN_RADIUS
    # The centring of a shadowed X is drawn towards the shadow edge: its candidate is the better start.
    failed = np.vstack([failed, unseeded[~good]])
    failed = failed[_dedupe(failed, np.ones(len(failed)))]
    shade, shade_uv, why = _shadow_fits(img, failed, contrast, min_quality)
    unfitted = failed[why == None]  # noqa: E711 (an object array)
    shadowed = unfitted[shadowed_x(img, unfitted, lit_contrast, min_quality)] if len(unfitted) else unfitted
    shadowed = np.vstack([shade_uv[why == SHADOW_REASON], shadowed])
    cand, radius = cand[good], radius[good]
    if len(cand) == 0:
        return none, shadowed, shade
    quality, ring_contrast = _probe_ring(img, cand, radius)
    good = np.abs(ring_contrast) >= contrast
    return (cand[good], radius[good], quality[good]), shadowed, shade


SHADOW_RADII = (4.0, 6.0, 8.0)  # px, rings of the shadowed-X test
SHADOW_SAMPLES = 24  # samples per ring of the shadowed-X test
MIN_SHADOW_LOG = 0.3  # least darkening in the shade, as a step of log(intensity): ~26% of the light
SHADOW_SIDE_SAMPLES = 3  # samples of each level of the X on either side of a shadow line, at least
_SHADOW_LINES = tuple((phi, t) for phi in np.radians(np.arange(0.0, 360.0, 15.0)) for t in (-0.5, 0.0, 0.5))
_SHADOW_PHI = np.array([phi for phi, _ in _SHADOW_LINES])  # the lines' directions, made once
_SHADOW_PHI.flags.writeable = False


def shadowed_x(img: np.ndarray, uv: np.ndarray, contrast: float, min_quality: float = MIN_QUALITY) -> np.ndarray:
    """(n,) True where points uv (n, 2) are an X-corner crossed near its centre by a straight shadow
    edge. A shadow multiplies the light: on a ring of log values it adds a step g on the arc beyond
    a line. With the best line (direction in 15 deg steps, within half the radius of the centre)
    and step taken away, every ring of SHADOW_RADII must be a clean X (ring quality >= min_quality,
    levels >= `contrast` apart on the lit side), the step a real darkening (-g >= MIN_SHADOW_LOG)
    and the line's direction the same within 30 deg on every ring; the line must cross the X's
    edges, not run along one. A T-junction or an L-corner (a marker's outline) splits a ring too,
    but no step turns their rings into an X: the shade keeps a shadowed X's two levels in the same
    ratio, the background beyond an outline has one. Used for the rejections' reason where the
    fit with the shadow edge (`shadow.shadowed_corners`) did not start."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    # Cheap first: the point-symmetric part of the smallest ring, where a shadow line through the
    # centre adds only a constant, must already look like an X of some contrast (not noise along a
    # straight edge, where it is flat).
    offsets = ring_offsets(SHADOW_RADII[0], SHADOW_SAMPLES)
    values = log_ring_sample(img, uv, offsets)
    quality, high, low, _ = ring_stats(0.5 * (values + half_turn(values)))
    ok = (quality >= 0.5) & (high - low >= MIN_SHADOW_LOG)
    direction = None
    for radius in SHADOW_RADII:
        if not ok.any():
            break
        values = log_ring_sample(img, uv[ok], ring_offsets(radius, SHADOW_SAMPLES))
        good, phi = _best_shadow_line(values, contrast, min_quality)
        if direction is not None:
            good &= np.abs(np.angle(np.exp(1j * (phi - direction[ok])))) <= np.radians(30.0)
            direction[ok] = phi
        else:
            direction = np.where(ok, 0.0, np.nan)
            direction[ok] = phi
        ok[np.nonzero(ok)[0][~good]] = False
    return ok


def _best_shadow_line(values: np.ndarray, contrast: float, min_quality: float):
    """For log rings (m, k): (passes (m,), shadow direction (m,)) of the line (of _SHADOW_LINES)
    whose step, least-squares fitted to the rings' point asymmetry and taken away, leaves the best
    X; passes where that X has quality >= min_quality, contrast >= `contrast` and the step darkens."""
    shade, g = _shadow_steps(values)
    ends = line_ends(_SHADOW_LINES, values.shape[1]).reshape(len(_SHADOW_LINES), -1)
    passes, best = _shadow.shadow_lines(values, g, shade, ends, contrast, min_quality, MIN_SHADOW_LOG,
                                        SHADOW_SIDE_SAMPLES, SAME_RATIO)
    return passes, _SHADOW_PHI[best]


def _shadow_steps(values: np.ndarray):
    """(the shaded samples (l, k) of each of _SHADOW_LINES, the log steps (m, l) least-squares fitted to
    the point asymmetry of log rings values (m, k))."""
    k = values.shape[1]
    shade, h = step_masks(_SHADOW_LINES, k)  # (l, k) each
    anti = values - half_turn(values)
    return shade, anti @ h.T / (h * h).sum(axis=1)


def _best_shadow_line_numpy(values: np.ndarray, contrast: float, min_quality: float):
    """`_best_shadow_line` in numpy (the reference of tests/test_marker_shadow_start.py)."""
    m, k = values.shape
    shade, g = _shadow_steps(values)
    lit = values[:, None, :] - g[:, :, None] * shade[None]
    quality, high, low, bright = (a.reshape(m, len(shade), *a.shape[1:])
                                  for a in ring_stats(np.exp(lit).reshape(-1, k)))
    # Both levels of the X on both sides of the line, in the same ratio (a shadow takes the same
    # share of light from both): a step over one level (the background beyond an outline) or over
    # texture is no shadow of the X.
    both = both_sides(lit, bright, shade[None], SHADOW_SIDE_SAMPLES)
    # The line must cross the X's edges, not run along one: an outline T-junction whose background
    # lies near the geometric mean of the cells' levels reads as an X shadowed along an edge.
    ends = bright[:, np.arange(len(shade))[:, None, None], line_ends(_SHADOW_LINES, k)]  # (m, l, 2, w)
    both &= np.all(ends == ends[..., :1], axis=(2, 3))
    good = both & (quality >= min_quality) & (high - low >= contrast) & (-g >= MIN_SHADOW_LOG)
    best = np.argmax(np.where(good, quality, -1.0), axis=1)
    return good.any(axis=1), np.array([phi for phi, _ in _SHADOW_LINES])[best]


def _dedupe(points: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Indexes (k,) of the best-scoring point of every cluster of points (n, 2) closer than DUPLICATE_PX."""
    if len(points) < 2:
        return np.arange(len(points))
    order = np.argsort(-score, kind="stable")
    near = Neighbours(points).query_ball_point(points, DUPLICATE_PX)  # every point's cluster in one query
    taken = np.zeros(len(points), dtype=bool)
    keep = []
    for i in order.tolist():
        if taken[i]:
            continue
        keep.append(i)
        taken[near[i]] = True
    return np.array(keep, dtype=int)
