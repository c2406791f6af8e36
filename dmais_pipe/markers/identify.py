"""Automatic identification of detected markers from predicted projections of known points.

Priors (approximate attitude) can be degrees off: at f = 45000 px that is ~1500 px of shift, more
than the spacing of markers, so nearest neighbour alone fails. `identify` therefore aligns the
predicted set with the detected set robustly:

1. hypotheses: the translation taking each predicted point onto each detection (all pairs),
   within `max_shift`, scored by how many detections have a prediction within a coarse gate;
2. the best few are refined by iterated least squares of a 2D similarity, then of a similarity
   plus a radial cubic term about the image centre (unmodelled distortion, focal error), with a
   gate shrinking to `gate_px`;
3. accepted only with >= `min_inliers` one-to-one matches, a small residual, and no competing
   hypothesis (a different assignment) nearly as good; each match must also be unambiguous
   (no second detection or prediction near it, and no X-corner the detector rejected nearer the
   prediction than the detection). Anything else keeps an empty id: a wrong id is worse than none.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

COARSE_GATE_PX = 120.0
GATE_PX = 12.0
MAX_SHIFT_PX = 2500.0
MIN_INLIERS = 4
TOP_HYPOTHESES = 12


def _design(p: np.ndarray, centre: np.ndarray, radial: bool) -> tuple[np.ndarray, np.ndarray]:
    """Rows of the linear model u' = [a -b; b a] p + t (+ k (p - c) |p - c|^2) for points p (n, 2)."""
    n = len(p)
    x, y = p[:, 0], p[:, 1]
    ax = np.zeros((2 * n, 5 if radial else 4))
    ax[0::2, 0], ax[0::2, 1], ax[0::2, 2] = x, -y, 1.0
    ax[1::2, 0], ax[1::2, 1], ax[1::2, 3] = y, x, 1.0
    if radial:
        q = (p - centre) / 1000.0
        r2 = (q**2).sum(1)
        ax[0::2, 4], ax[1::2, 4] = q[:, 0] * r2, q[:, 1] * r2
    return ax, p


def _fit(pred: np.ndarray, det: np.ndarray, centre: np.ndarray, radial: bool) -> np.ndarray:
    a, _ = _design(pred, centre, radial)
    params, *_ = np.linalg.lstsq(a, det.reshape(-1), rcond=None)
    return params


def _apply(params: np.ndarray, pred: np.ndarray, centre: np.ndarray) -> np.ndarray:
    a, _ = _design(pred, centre, len(params) == 5)
    return (a @ params).reshape(-1, 2)


def _match(moved: np.ndarray, det: np.ndarray, gate: float) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours within `gate`: (k,) prediction and (k,) detection indices."""
    if len(moved) == 0 or len(det) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    d_to_p, p_of_d = cKDTree(moved).query(det)
    p_to_d, d_of_p = cKDTree(det).query(moved)
    pi = np.nonzero((p_to_d <= gate) & (p_of_d[d_of_p] == np.arange(len(moved))))[0]
    return pi, d_of_p[pi]


def _refine_hypothesis(pred, det, shift, centre, gate_px):
    """Iterate fit/match from a translation; returns (params, pred idx, det idx, rms) or None."""
    params = np.array([1.0, 0.0, shift[0], shift[1]])
    for gate, radial in ((COARSE_GATE_PX, False), (60.0, False), (30.0, False), (30.0, True),
                         (gate_px, True), (gate_px, True)):
        pi, di = _match(_apply(params, pred, centre), det, gate)
        need = 6 if radial else 2
        if len(pi) < need:
            if radial and len(pi) >= 2:
                radial = False
            else:
                return None
        params = _fit(pred[pi], det[di], centre, radial)
        scale = np.hypot(params[0], params[1])
        if not 0.8 < scale < 1.25:
            return None
    moved = _apply(params, pred, centre)
    pi, di = _match(moved, det, gate_px)
    if len(pi) == 0:
        return None
    rms = float(np.sqrt(np.mean(np.sum((moved[pi] - det[di]) ** 2, axis=1))))
    return params, pi, di, rms


def identify(detections, predicted, point_ids, image_size=None, *, rejected=None, gate_px: float = GATE_PX,
             max_shift: float = MAX_SHIFT_PX, min_inliers: int = MIN_INLIERS) -> np.ndarray:
    """Point ids (n,) object array for detections (n, 2); '' where not identified.

    predicted: (m, 2) projections of the known points from the priors (NaN rows are ignored);
    point_ids: (m,) their ids. image_size: (width, height), the centre of the radial term
    (default: the detections' bounding box centre). rejected: (k, 2) X-corners the detector found
    but did not return (`detect`'s rejections, e.g. a corner a shadow edge crosses): a detection
    farther from its prediction than one of them is not named, for it is likely no marker but a
    "virtual" X beside the rejected one (an outline crossed by the same shadow edge).
    """
    det = np.asarray(detections, dtype=float).reshape(-1, 2)
    pred = np.asarray(predicted, dtype=float).reshape(-1, 2)
    ids = np.asarray(point_ids, dtype=object).reshape(-1)
    out = np.full(len(det), "", dtype=object)
    finite = np.all(np.isfinite(pred), axis=1)
    pred, ids = pred[finite], ids[finite]
    if len(det) < min_inliers or len(pred) < min_inliers:
        return out
    if image_size is not None:
        centre = 0.5 * (np.asarray(image_size, dtype=float) - 1.0)
    else:
        centre = 0.5 * (det.min(0) + det.max(0))
    # 1. translation hypotheses, scored with the coarse gate
    shifts = (det[:, None, :] - pred[None, :, :]).reshape(-1, 2)
    shifts = shifts[np.hypot(*shifts.T) <= max_shift]
    if len(shifts) == 0:
        return out
    tree = cKDTree(det)
    counts = np.array([np.count_nonzero(tree.query(pred + s, distance_upper_bound=COARSE_GATE_PX)[0]
                                        <= COARSE_GATE_PX) for s in shifts])
    order = np.argsort(-counts, kind="stable")
    # 2. refine the best distinct hypotheses
    results = []
    tried: list[np.ndarray] = []
    for k in order:
        if len(tried) >= TOP_HYPOTHESES or counts[k] < min_inliers:
            break
        if any(np.hypot(*(shifts[k] - s)) < 0.5 * COARSE_GATE_PX for s in tried):
            continue
        tried.append(shifts[k])
        result = _refine_hypothesis(pred, det, shifts[k], centre, gate_px)
        if result is not None:
            results.append(result)
    if not results:
        return out
    # 3. accept the best unless a different assignment is nearly as good
    results.sort(key=lambda r: (-len(r[1]), r[3]))
    params, pi, di, rms = results[0]
    if len(pi) < min_inliers or rms > 0.5 * gate_px:
        return out
    best = set(zip(ids[pi], di))
    for other in results[1:]:
        other_pairs = set(zip(ids[other[1]], other[2]))
        if other_pairs != best and not other_pairs <= best and len(other[1]) >= max(min_inliers, len(pi) - 2):
            return out
    # each match must be unambiguous: no second detection / prediction within 2 gates, no rejected
    # X-corner nearer the prediction
    moved = _apply(params, pred, centre)
    nearest_rejected = _nearest(rejected, moved)
    for p, d in zip(pi, di):
        near_det = tree.query_ball_point(moved[p], 2.5 * gate_px)
        near_pred = np.count_nonzero(np.hypot(*(moved - det[d]).T) <= 2.5 * gate_px)
        if len(near_det) == 1 and near_pred == 1 and nearest_rejected[p] >= np.hypot(*(moved[p] - det[d])):
            out[d] = ids[p]
    return out


def _nearest(points, queries: np.ndarray) -> np.ndarray:
    """(m,) distance from each of queries (m, 2) to the nearest of points (k, 2) (inf where none)."""
    points = np.zeros((0, 2)) if points is None else np.asarray(points, dtype=float).reshape(-1, 2)
    if len(points) == 0:
        return np.full(len(queries), np.inf)
    return cKDTree(points).query(queries)[0]
