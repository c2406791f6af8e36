"""Automatic identification of detected markers from predicted projections of known points.

Priors (approximate attitude) can be degrees off: at f = 45000 px that is ~1500 px of shift, more
than the spacing of markers, so nearest neighbour alone fails. `identify` therefore aligns the
predicted set with the detected set robustly:

1. hypotheses: the translation taking each predicted point onto each detection (all pairs),
   within `max_shift`, scored by how many detections have a prediction within a coarse gate;
2. the best few are refined by iterated least squares of a 2D similarity, then of a similarity
   plus a radial cubic term about the image centre (unmodelled distortion, focal error), with a
   gate shrinking to `gate_px`; with `projective` (a wide field of view, where a prior's attitude
   error is not a similarity: a turn by w about an image axis moves a point by f w (1 + y^2 / f^2)
   along it and f w x y / f^2 across), that model plus the two keystone terms of such a turn
   (du, dv) = g1 (x^2, x y) + g2 (x y, y^2) about the image centre, once 8 pairs are matched; a match's gate is also at most PERIOD_GATE_FRACTION of its
   prediction's local period (the distance to the nearest other prediction);
3. periodic patterns: the alignments shifted by one period of the pattern (every id moved to its
   neighbouring point along a period vector: the two shortest independent offsets between the
   aligned predictions nearest the image centre, their sum and difference, both signs) are refined
   too; the best moves to a cheaper one while there is one, and is accepted only when each of them
   costs at least SHIFT_COST_RATIO times as much (`_cost`: the points either leaves unexplained, so
   a pattern whose ends are out of view is refused);
4. accepted only with >= `min_inliers` one-to-one matches, a small residual, and no competing
   hypothesis (a different assignment) nearly as good; each match must also be unambiguous
   (no second detection or prediction near it, no X-corner the detector rejected nearer the
   prediction than the detection, and no shift by one local period of the ids of its
   neighbourhood that the alignment explains about as well). Anything else keeps an empty id, with
   the reason: a wrong id is worse than none.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .neighbours import Neighbours

COARSE_GATE_PX = 120.0
GATE_PX = 12.0
MAX_SHIFT_PX = 2500.0
MIN_INLIERS = 4
TOP_HYPOTHESES = 12
#: Translation hypotheses start from every detection, each scored against every prediction: n m^2
#: point queries. Beyond this many (a dense pattern of hundreds of points: minutes), only the
#: detections nearest the image centre (least distorted) start them; a DMAIS field (tens of
#: markers: the demo's images at most 16,000) and a 9 x 6 chessboard (~270,000) stay below it.
MAX_HYPOTHESIS_WORK = 2_000_000
#: A match's gate is at most this fraction of its prediction's local period: the gates of neighbouring
#: points never overlap, and a detection one period away (a shifted id) always lies beyond the gate
#: (costs a whole unexplained point in `_cost`), even where the alignment is off by a few pixels.
PERIOD_GATE_FRACTION = 0.3
#: An alignment (or a neighbourhood's ids) is accepted only when every alternative shifted by one
#: period costs at least this many times as much, its own cost counted as at least one point (a
#: missed detection is always possible). Whole alignments (`_cost`: points left unexplained): a shift
#: towards an edge of the pattern in view leaves that edge's row of detections and a row of predicted
#: points unexplained (6 or more), while the points entering or leaving at the image's border, a
#: missed corner or a stray detection make one or two: refused as ambiguous. A neighbourhood
#: (`_local_shift_reason`: each point's squared distance in gates, at most 1): its 9 ids are accepted
#: while their RMS distance stays below 1/sqrt(3) of the gate, ~0.17 of the period.
SHIFT_COST_RATIO = 3.0
#: The ids a local shift moves: a detection and its nearest identified ones (a 3 x 3 block of a grid).
NEIGHBOURHOOD = 9
#: How often the alignment may move to a cheaper one-period shift of itself (the hypotheses of a dense
#: pattern start within a period or two of the priors, which may be that far off).
MAX_PERIOD_MOVES = 4
#: The fewest matched pairs the projective model (7 parameters) is fitted to.
PROJECTIVE_PAIRS = 8

TOO_FEW = "fewer detections or predicted points than the fewest matches"
NO_ALIGNMENT = "no alignment of the predictions matches enough detections"
POOR_FIT = "the alignment's residual is too large"
COMPETING = "a different alignment matches nearly as many detections"
UNMATCHED = "no predicted point within the gate"
AMBIGUOUS = "a second detection or prediction near its prediction"
REJECTED_NEARER = "an X-corner the detector rejected lies nearer its prediction"


@dataclass(frozen=True)
class Identification:
    """Point ids (n,) of the detections ('' where not identified) and the reasons (n,) why ('' where named)."""

    ids: np.ndarray
    reasons: np.ndarray


@dataclass(frozen=True)
class _Alignment:
    """Model parameters (4 or 5), matched prediction and detection indices (k,), and their distances (k,)."""

    params: np.ndarray
    pi: np.ndarray
    di: np.ndarray
    distance: np.ndarray

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.distance**2)))

    def pairs(self) -> set:
        return set(zip(self.pi.tolist(), self.di.tolist()))


def _design(p: np.ndarray, centre: np.ndarray, radial: bool, projective: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Rows of the linear model u' = [a -b; b a] p + t (+ k (p - c) |p - c|^2, + with `projective`
    the keystone g1 (q_x^2, q_x q_y) + g2 (q_x q_y, q_y^2), q = (p - c) / 1000) for points p (n, 2)."""
    n = len(p)
    x, y = p[:, 0], p[:, 1]
    ax = np.zeros((2 * n, 7 if projective else 5 if radial else 4))
    ax[0::2, 0], ax[0::2, 1], ax[0::2, 2] = x, -y, 1.0
    ax[1::2, 0], ax[1::2, 1], ax[1::2, 3] = y, x, 1.0
    if radial or projective:
        q = (p - centre) / 1000.0
        r2 = (q**2).sum(1)
        ax[0::2, 4], ax[1::2, 4] = q[:, 0] * r2, q[:, 1] * r2
    if projective:
        ax[0::2, 5], ax[1::2, 5] = q[:, 0] ** 2, q[:, 0] * q[:, 1]
        ax[0::2, 6], ax[1::2, 6] = q[:, 0] * q[:, 1], q[:, 1] ** 2
    return ax, p


def _fit(pred: np.ndarray, det: np.ndarray, centre: np.ndarray, radial: bool, projective: bool = False) -> np.ndarray:
    a, _ = _design(pred, centre, radial, projective)
    params, *_ = np.linalg.lstsq(a, det.reshape(-1), rcond=None)
    return params


def _apply(params: np.ndarray, pred: np.ndarray, centre: np.ndarray) -> np.ndarray:
    a, _ = _design(pred, centre, len(params) >= 5, len(params) == 7)
    return (a @ params).reshape(-1, 2)


def _match(moved: np.ndarray, det: np.ndarray, gate,
           det_tree: Neighbours | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours within `gate` (a number, or (m,) per prediction): (k,) prediction
    and (k,) detection indices. det_tree: Neighbours(det) if already made."""
    if len(moved) == 0 or len(det) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    _, p_of_d = Neighbours(moved).query(det)
    p_to_d, d_of_p = (Neighbours(det) if det_tree is None else det_tree).query(moved)
    pi = np.nonzero((p_to_d <= gate) & (p_of_d[d_of_p] == np.arange(len(moved))))[0]
    return pi, d_of_p[pi]


def _local_periods(pred: np.ndarray) -> np.ndarray:
    """(m,) distance from each prediction (m, 2) to the nearest other one (inf for a single one)."""
    if len(pred) < 2:
        return np.full(len(pred), np.inf)
    return Neighbours(pred).query(pred, 2)[0][:, 1]


def _scale_ok(params: np.ndarray) -> bool:
    return 0.8 < np.hypot(params[0], params[1]) < 1.25


@dataclass(frozen=True)
class _Scene:
    """One image: detections det (n, 2), predictions pred (m, 2) and their gates (m,), the centre (2,)
    of the radial term, the view [lo, hi] (2,) where a predicted point should have been detected, the
    X-corners the detector rejected (k, 2), and the fewest matches of an alignment."""

    det: np.ndarray
    pred: np.ndarray
    gates: np.ndarray
    centre: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    rejected: np.ndarray
    min_inliers: int
    projective: bool = False

    @cached_property
    def det_tree(self) -> Neighbours:
        """Neighbours of the detections, made once."""
        return Neighbours(self.det)

    def moved(self, params: np.ndarray) -> np.ndarray:
        return _apply(params, self.pred, self.centre)

    def unseen(self, params: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(k,) whether each of points (k,) (prediction indices), moved by `params`, lies in the view
        without a rejected X-corner within its gate (one the detector found but did not return, e.g.
        a blurred or shadowed corner, is no evidence against the point)."""
        uv = _apply(params, self.pred[points], self.centre)
        in_view = np.all((uv >= self.lo) & (uv <= self.hi), axis=1)
        return in_view & (_nearest(self.rejected, uv) > self.gates[points])


def _aligned(scene: _Scene, params: np.ndarray) -> _Alignment | None:
    """The matches of the predictions moved by `params` within the gates, or None without any."""
    moved = scene.moved(params)
    pi, di = _match(moved, scene.det, scene.gates, scene.det_tree)
    if len(pi) == 0:
        return None
    return _Alignment(params, pi, di, np.hypot(*(moved[pi] - scene.det[di]).T))


def _refine_hypothesis(scene: _Scene, shift: np.ndarray) -> _Alignment | None:
    """Iterate fit/match from a translation, the last steps within the scene's gates."""
    pred, det, centre = scene.pred, scene.det, scene.centre
    params = np.array([1.0, 0.0, shift[0], shift[1]])
    for gate, radial in ((COARSE_GATE_PX, False), (60.0, False), (30.0, False), (30.0, True),
                         (scene.gates, True), (scene.gates, True)):
        pi, di = _match(_apply(params, pred, centre), det, gate, scene.det_tree)
        need = 6 if radial else 2
        if len(pi) < need:
            if radial and len(pi) >= 2:
                radial = False
            else:
                return None
        params = _fit(pred[pi], det[di], centre, radial, radial and scene.projective and len(pi) >= PROJECTIVE_PAIRS)
        if not _scale_ok(params):
            return None
    return _aligned(scene, params)


def _polish(scene: _Scene, pi: np.ndarray, di: np.ndarray) -> _Alignment | None:
    """The alignment fitted to the pairs (pi, di) (k,), then matched and refitted within the gates."""
    alignment = None
    for _ in range(3):
        if len(pi) < max(scene.min_inliers, 2):
            return None
        params = _fit(scene.pred[pi], scene.det[di], scene.centre, len(pi) >= 6,
                      scene.projective and len(pi) >= PROJECTIVE_PAIRS)
        if not _scale_ok(params):
            return None
        alignment = _aligned(scene, params)
        if alignment is None:
            return None
        pi, di = alignment.pi, alignment.di
    return alignment


def _cost(alignment: _Alignment, other: _Alignment, scene: _Scene) -> int:
    """How many points `alignment` leaves unexplained of those either explains: the detections only
    `other` matches, and the points only `other` matches that `alignment` predicts unseen
    (`_Scene.unseen`). Matches both make fit about equally well, so that their residuals would only
    dilute the difference."""
    only_other = np.array(sorted(set(other.pi.tolist()) - set(alignment.pi.tolist())), dtype=int)
    unseen = scene.unseen(alignment.params, only_other)
    return len(set(other.di.tolist()) - set(alignment.di.tolist())) + int(np.count_nonzero(unseen))


def _period_vectors(moved: np.ndarray, anchor: int) -> np.ndarray:
    """(k, 2) one-period shifts of the pattern at prediction `anchor` of moved (m, 2): the shortest
    offset a to another prediction, the shortest b not within 30 deg of its direction, a + b and
    a - b, with both signs (k = 0 without a neighbour, 2 without an independent one)."""
    offsets = moved - moved[anchor]
    offsets = offsets[np.hypot(*offsets.T) > 0]
    if len(offsets) == 0:
        return np.zeros((0, 2))
    offsets = offsets[np.argsort(np.hypot(*offsets.T))]
    a = offsets[0]
    sines = np.abs(a[0] * offsets[:, 1] - a[1] * offsets[:, 0]) / (np.hypot(*a) * np.hypot(*offsets.T))
    independent = offsets[sines > 0.5]
    basis = [a] if len(independent) == 0 else [a, independent[0], a + independent[0], a - independent[0]]
    return np.vstack([v for b in basis for v in (b, -b)])


def _neighbours_along(moved: np.ndarray, tree: Neighbours, points: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """(s, k) index of the prediction one period shifts[j] (s, 2) from each of points (k,) of moved
    (m, 2), -1 where none lies within half the shift of where it would be: one query for every shift."""
    if len(shifts) == 0:
        return np.zeros((0, len(points)), dtype=int)
    distance, index = tree.query((moved[points][None, :, :] + shifts[:, None, :]).reshape(-1, 2))
    shape = (len(shifts), len(points))
    return np.where(distance.reshape(shape) < 0.5 * np.hypot(*shifts.T)[:, None], index.reshape(shape), -1)


def _period_alternatives(scene: _Scene, best: _Alignment) -> list[tuple[np.ndarray, _Alignment]]:
    """(shift (2,), alignment) for each period vector at the image centre: `best` with every id moved
    one period along it, refitted."""
    moved = scene.moved(best.params)
    tree = Neighbours(moved)
    anchor = int(best.pi[np.argmin(np.hypot(*(moved[best.pi] - scene.centre).T))])
    out = []
    shifts = _period_vectors(moved, anchor)
    for shift, neighbour in zip(shifts, _neighbours_along(moved, tree, best.pi, shifts)):
        alternative = _polish(scene, neighbour[neighbour >= 0], best.di[neighbour >= 0])
        if alternative is not None and alternative.pairs() != best.pairs():
            out.append((shift, alternative))
    return out


def _settle_period(scene: _Scene, best: _Alignment) -> tuple[_Alignment, str]:
    """The alignment among `best` and its one-period shifts that explains the detections best, moving
    while a shift is cheaper; with the reason it is refused ('' when no shift costs nearly as much)."""
    for moves in range(MAX_PERIOD_MOVES + 1):
        alternatives = _period_alternatives(scene, best)
        cheaper = [(_cost(a, best, scene) - _cost(best, a, scene), k) for k, (_, a) in enumerate(alternatives)]
        cheaper = [c for c in cheaper if c[0] < 0]
        if not cheaper or moves == MAX_PERIOD_MOVES:  # one still cheaper after the last move fails below
            break
        best = alternatives[min(cheaper)[1]][1]
    for shift, alternative in alternatives:
        ratio = _cost(alternative, best, scene) / max(_cost(best, alternative, scene), 1.0)
        if ratio < SHIFT_COST_RATIO:
            return best, (f"the alignment shifted by one period ({shift[0]:+.0f}, {shift[1]:+.0f}) px explains the "
                          f"detections about as well (cost ratio {ratio:.2f} < {SHIFT_COST_RATIO:g})")
    return best, ""


def _local_shift_reason(scene: _Scene, best: _Alignment, k: int, matched_tree: Neighbours, moved: np.ndarray,
                        moved_tree: Neighbours) -> str:
    """Why match k of `best` is refused by its neighbourhood's one-period shifts ('' when none fits
    about as well): the ids of its detection and its nearest identified ones (matched_tree: of the
    matched detections), all moved one local period, against the same alignment (moved (m, 2))."""
    near = np.atleast_1d(matched_tree.query(scene.det[best.di[k]], min(NEIGHBOURHOOD, len(best.pi)))[1])
    points, dets = best.pi[near], best.di[near]
    own = max(float(np.sum((best.distance[near] / scene.gates[points]) ** 2)), 1.0)
    shifts = _period_vectors(moved, best.pi[k])
    for shift, ratio in zip(shifts, _shift_ratios(scene, moved, dets, _neighbours_along(moved, moved_tree, points,
                                                                                        shifts), own)):
        if ratio < SHIFT_COST_RATIO:
            return (f"its neighbourhood's ids shifted by one period ({shift[0]:+.0f}, {shift[1]:+.0f}) px fit about "
                    f"as well (cost ratio {ratio:.2f} < {SHIFT_COST_RATIO:g})")
    return ""


def _shift_ratios(scene: _Scene, moved: np.ndarray, dets: np.ndarray, neighbours: np.ndarray, own: float) -> list:
    """(s,) per one-period shift, the cost of the ids of detections dets (q,) moved to the predictions
    neighbours (s, q) (-1: none) over `own`: the squared distances in gates (at most 1) of the found
    ones, plus 1 per one not found. The distances of all shifts at once, each shift's sum as np.sum
    of its found ones has it."""
    found = neighbours >= 0
    at = np.where(found, neighbours, 0)
    offset = moved[at] - scene.det[dets][None]  # (s, q, 2)
    cost = np.minimum((np.hypot(offset[..., 0], offset[..., 1]) / scene.gates[at]) ** 2, 1.0)
    missing = np.count_nonzero(~found, axis=1)
    return [(float(np.sum(row[mask])) + int(lost)) / own for row, mask, lost in zip(cost, found, missing)]


def identify(detections, predicted, point_ids, image_size=None, *, rejected=None, gate_px: float = GATE_PX,
             max_shift: float = MAX_SHIFT_PX, min_inliers: int = MIN_INLIERS, projective: bool = False) -> np.ndarray:
    """Point ids (n,) object array for detections (n, 2); '' where not identified.

    predicted: (m, 2) projections of the known points from the priors (NaN rows are ignored);
    point_ids: (m,) their ids. image_size: (width, height), the centre of the radial term and the
    view (default: the detections' bounding box and its centre). rejected: (k, 2) X-corners the
    detector found but did not return (`detect`'s rejections, e.g. a corner a shadow edge crosses):
    a detection farther from its prediction than one of them is not named, for it is likely no
    marker but a "virtual" X beside the rejected one (an outline crossed by the same shadow edge).
    projective: also fit the keystone of a turn about the image axes (step 2 of the module
    docstring; a wide field of view). `identify_with_reasons` gives the same ids with the reason for each one left empty.
    """
    return identify_with_reasons(detections, predicted, point_ids, image_size, rejected=rejected, gate_px=gate_px,
                                 max_shift=max_shift, min_inliers=min_inliers, projective=projective).ids


def identify_with_reasons(detections, predicted, point_ids, image_size=None, *, rejected=None,
                          gate_px: float = GATE_PX, max_shift: float = MAX_SHIFT_PX,
                          min_inliers: int = MIN_INLIERS, projective: bool = False) -> Identification:
    """`identify`'s ids (n,) and, for each detection left without one, the reason (n,)."""
    det = np.asarray(detections, dtype=float).reshape(-1, 2)
    pred = np.asarray(predicted, dtype=float).reshape(-1, 2)
    ids = np.asarray(point_ids, dtype=object).reshape(-1)
    finite = np.all(np.isfinite(pred), axis=1)
    pred, ids = pred[finite], ids[finite]

    def refused(reason: str) -> Identification:
        return Identification(np.full(len(det), "", dtype=object), np.full(len(det), reason, dtype=object))

    if len(det) < min_inliers or len(pred) < min_inliers:
        return refused(TOO_FEW)
    scene = _scene(det, pred, image_size, gate_px, min_inliers, rejected, projective)
    results = _hypotheses(scene, max_shift)
    if not results:
        return refused(NO_ALIGNMENT)
    best = results[0]
    if len(best.pi) >= min_inliers:
        best, period_reason = _settle_period(scene, best)
        if period_reason:
            return refused(period_reason)
    if len(best.pi) < min_inliers:
        return refused(NO_ALIGNMENT)
    if best.rms > 0.5 * gate_px:
        return refused(POOR_FIT)
    pairs = best.pairs()
    for other in results:
        other_pairs = other.pairs()
        if other_pairs != pairs and not other_pairs <= pairs and len(other.pi) >= max(min_inliers, len(best.pi) - 2):
            return refused(COMPETING)
    return _name_matches(scene, best, ids, gate_px, rejected)


def _scene(det: np.ndarray, pred: np.ndarray, image_size, gate_px: float, min_inliers: int, rejected,
           projective: bool = False) -> _Scene:
    """The scene of detections det (n, 2), predictions pred (m, 2) and rejected X-corners (k, 2) (or None):
    gates, centre and view."""
    if image_size is not None:
        lo, hi = np.full(2, -0.5), np.asarray(image_size, dtype=float) - 0.5
    else:
        lo, hi = det.min(0), det.max(0)
    gates = np.minimum(gate_px, PERIOD_GATE_FRACTION * _local_periods(pred))
    rejected = np.zeros((0, 2)) if rejected is None else np.asarray(rejected, dtype=float).reshape(-1, 2)
    return _Scene(det, pred, gates, 0.5 * (lo + hi), lo, hi, rejected, min_inliers, projective)


def _hypotheses(scene: _Scene, max_shift: float) -> list[_Alignment]:
    """The refined alignments of the best distinct translation hypotheses, best (most matches, then
    smallest residual) first."""
    det, pred = scene.det, scene.pred
    anchors = det
    if len(det) * len(pred) ** 2 > MAX_HYPOTHESIS_WORK:
        anchors = det[np.argsort(np.hypot(*(det - scene.centre).T))[:max(MAX_HYPOTHESIS_WORK // len(pred) ** 2, 1)]]
    shifts = (anchors[:, None, :] - pred[None, :, :]).reshape(-1, 2)
    shifts = shifts[np.hypot(*shifts.T) <= max_shift]
    if len(shifts) == 0:
        return []
    counts = _coarse_counts(Neighbours(det), pred, shifts)
    results, tried = [], []
    for k in np.argsort(-counts, kind="stable"):
        if len(tried) >= TOP_HYPOTHESES or counts[k] < scene.min_inliers:
            break
        if any(np.hypot(*(shifts[k] - s)) < 0.5 * COARSE_GATE_PX for s in tried):
            continue
        tried.append(shifts[k])
        result = _refine_hypothesis(scene, shifts[k])
        if result is not None:
            results.append(result)
    results.sort(key=lambda r: (-len(r.pi), r.rms))
    return results


def _coarse_counts(tree: Neighbours, pred: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """(s,) how many of the predictions (m, 2) moved by each of shifts (s, 2) have a detection (tree)
    within the coarse gate."""
    per_chunk = max(200_000 // len(pred), 1)
    counts = []
    for start in range(0, len(shifts), per_chunk):
        moved = (shifts[start:start + per_chunk, None, :] + pred[None, :, :]).reshape(-1, 2)
        near = tree.query(moved, distance_upper_bound=COARSE_GATE_PX)[0] <= COARSE_GATE_PX
        counts.append(near.reshape(-1, len(pred)).sum(axis=1))
    return np.concatenate(counts)


def _name_matches(scene: _Scene, best: _Alignment, ids: np.ndarray, gate_px: float, rejected) -> Identification:
    """The ids of the matches of `best` that are unambiguous: no second detection or prediction near
    (within 2.5 gates, at most half the local period), no rejected X-corner nearer the prediction,
    and no one-period shift of its neighbourhood's ids that fits about as well."""
    det = scene.det
    out = np.full(len(det), "", dtype=object)
    reasons = np.full(len(det), UNMATCHED, dtype=object)
    moved = scene.moved(best.params)
    moved_tree, det_tree, matched_tree = Neighbours(moved), Neighbours(det), Neighbours(det[best.di])
    radius = np.minimum(2.5 * gate_px, 0.5 * _local_periods(scene.pred))
    nearest_rejected = _nearest(rejected, moved)
    for k, (p, d) in enumerate(zip(best.pi, best.di)):
        near_det = det_tree.query_ball_point(moved[p], radius[p])
        near_pred = len(moved_tree.query_ball_point(det[d], radius[p]))
        if len(near_det) != 1 or near_pred != 1:
            reasons[d] = AMBIGUOUS
        elif nearest_rejected[p] < np.hypot(*(moved[p] - det[d])):
            reasons[d] = REJECTED_NEARER
        else:
            reasons[d] = _local_shift_reason(scene, best, k, matched_tree, moved, moved_tree)
            out[d] = "" if reasons[d] else ids[p]
    return Identification(out, reasons)


def _nearest(points, queries: np.ndarray) -> np.ndarray:
    """(m,) distance from each of queries (m, 2) to the nearest of points (k, 2) (inf where none)."""
    points = np.zeros((0, 2)) if points is None else np.asarray(points, dtype=float).reshape(-1, 2)
    if len(points) == 0:
        return np.full(len(queries), np.inf)
    return Neighbours(points).query(queries)[0]
