# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled loops of markers.shadow's start: the symmetric centre's choice among a grid of log rings
(`shadow._most_symmetric_x`) and the best straight step of log rings (`shadow._best_step`), each ring's
numbers as numpy's expressions make them (`shadow._most_symmetric_x_numpy`, `shadow._best_step_numpy`):
the ring statistics by `_rings.one_ring` (np.sum's pairwise order), libm's exp (numpy's float64 exp on a
CPU without AVX-512, as here), the steps ordered as np.argsort(kind="stable") orders them. The log of the
samples and the steps' least-squares sizes (a matrix product) stay numpy's. tests/test_marker_shadow_start.py
compares both with numpy's."""

import numpy as np

from libc.math cimport INFINITY, exp, fabs, isfinite

from dmais_pipe.markers._rings cimport one_ring
from dmais_pipe.markers._sums cimport pairwise_sum


def most_symmetric(logs, Py_ssize_t groups):
    """(n,) intp: per run of `groups` rings of the float32 log rings logs (n groups, k), the index in
    the run of the ring whose point-symmetric part, 0.5 (ring + ring rolled by k // 2), has the
    largest quality x (bright - dark level) (`_rings.one_ring`), the first of equals (np.argmax: the
    first NaN where there is one)."""
    cdef const float[:, ::1] v = np.ascontiguousarray(logs, dtype=np.float32)
    cdef Py_ssize_t k = v.shape[1], n = v.shape[0] // groups if groups else 0, half = k // 2, i, j, a, r
    out = np.zeros(n, dtype=np.intp)
    cdef Py_ssize_t[::1] best = out
    work = np.empty(2 * k if k else 1)
    cdef double[::1] w = work
    masks = np.empty(k if k else 1, dtype=np.uint8)
    cdef unsigned char[::1] m = masks
    cdef double quality, high, low, score, top, lo, hi
    cdef bint nan
    if k == 0:
        raise ValueError("rings of no samples")
    with nogil:
        for i in range(n):
            top = -INFINITY
            for j in range(groups):
                r = i * groups + j
                lo, hi, nan = INFINITY, -INFINITY, False
                for a in range(k):  # np.roll by half: the sample half a ring before
                    w[a] = 0.5 * (<double>v[r, a] + <double>v[r, a - half if a >= half else a - half + k])
                    lo = w[a] if w[a] < lo else lo
                    hi = w[a] if w[a] > hi else hi
                    nan = nan or w[a] != w[a]
                if j > 0 and not nan and (hi - lo) + 1e-6 * (hi - lo) + 1e-9 * (fabs(hi) + fabs(lo)) < top:
                    # Its score, quality (<= 1) x (bright - dark level), the levels means of samples within
                    # lo..hi, is at most hi - lo, with room for the means' roundings (~k 1e-16 of the values):
                    # below the best, it is not chosen (nor is a ring with a NaN, whose score is, skipped).
                    continue
                if not_four(&w[0], k):
                    score = 0.0  # quality 0 times finite levels: 0 (or -0, equal to it in every comparison)
                else:
                    one_ring(&w[0], k, &w[k], &m[0], &quality, &high, &low)
                    score = quality * (high - low)
                if score != score:
                    best[i] = j
                    break
                if j == 0 or score > top:
                    best[i], top = j, score
    return out


cdef inline bint not_four(const double *v, Py_ssize_t k) noexcept nogil:
    """Whether the ring v (k) has a finite mean and does not change level exactly four times about it
    (bright: above the mean): then `_rings.one_ring` gives it quality 0 and finite levels, so its
    quality x (bright - dark) is 0 and its numbers need not be made. The mean as one_ring makes it."""
    cdef double mean = pairwise_sum(v, k) / <double>k
    cdef Py_ssize_t j, transitions
    if not (mean - mean == 0.0):  # NaN or infinite: one_ring's numbers decide (NaN propagates)
        return False
    transitions = (v[0] > mean) != (v[k - 1] > mean)
    for j in range(1, k):
        transitions += (v[j] > mean) != (v[j - 1] > mean)
    return transitions != 4


cdef inline bint after(double a, double b) noexcept nogil:
    """Whether np.sort puts a after b: a larger, or a NaN and b not."""
    return a > b or (a != a and b == b)


cdef void stable_order(const double *key, Py_ssize_t l, Py_ssize_t *order) noexcept nogil:
    """order (l): the indexes of key (l) as np.argsort(key, kind="stable") has them (NaN last)."""
    cdef Py_ssize_t i, j, index
    for i in range(l):
        index, j = i, i
        while j > 0 and after(key[order[j - 1]], key[index]):
            order[j] = order[j - 1]
            j -= 1
        order[j] = index


cdef bint both_sides(const double *lit, const unsigned char *bright, const double *shade, Py_ssize_t k,
                     Py_ssize_t min_samples, double same_ratio, double *t) noexcept nogil:
    """`shadow.both_sides` of one log ring lit (k) with its bright mask (k) and a step's shaded samples
    shade (k, 0 or 1); t: k doubles of scratch."""
    cdef double contrast[2]
    cdef double side, n_bright, n_dark, low, high
    cdef Py_ssize_t s, a
    cdef bint both = True
    for s in range(2):
        n_bright, n_dark = 0.0, 0.0
        for a in range(k):
            side = shade[a] if s == 0 else 1.0 - shade[a]
            n_bright += side if bright[a] else 0.0
            n_dark += 0.0 if bright[a] else side
        both = both and n_bright >= min_samples and n_dark >= min_samples
        for a in range(k):
            side = shade[a] if s == 0 else 1.0 - shade[a]
            t[a] = lit[a] * (side if bright[a] else 0.0 * side)
        contrast[s] = pairwise_sum(t, k) / (n_bright if n_bright > 1.0 else 1.0)
        for a in range(k):
            side = shade[a] if s == 0 else 1.0 - shade[a]
            t[a] = lit[a] * (0.0 * side if bright[a] else side)
        contrast[s] = contrast[s] - pairwise_sum(t, k) / (n_dark if n_dark > 1.0 else 1.0)
    if contrast[0] != contrast[0] or contrast[1] != contrast[1]:
        return False  # np.minimum and np.maximum propagate NaN, and NaN >= x is False
    low = contrast[0] if contrast[0] < contrast[1] else contrast[1]
    high = contrast[1] if contrast[0] < contrast[1] else contrast[0]
    return both and low >= same_ratio * high


cdef void step_ring(const double *v, const double *ev, double step, const double *shade, Py_ssize_t k, double *lit,
                    double *scratch, unsigned char *bright, double *quality, double *high, double *low) noexcept nogil:
    """The log ring v (k) with the step of log size `step` beyond a line (its shaded samples shade (k),
    0 or 1) taken away into lit (k), and the ring statistics of its exp (`_rings.one_ring`: quality,
    levels, bright mask (k)). ev (k): exp(v), the exp of an unshaded sample where step is finite (v - step 0
    is v but for the sign of a zero, whose exp is 1 either way; a NaN keeps its bits). scratch: 3 k doubles."""
    cdef Py_ssize_t a
    cdef bint finite = isfinite(step)
    for a in range(k):
        lit[a] = v[a] - step * shade[a]
        scratch[a] = ev[a] if (finite and shade[a] == 0.0) else exp(lit[a])
    one_ring(scratch, k, &scratch[k], bright, quality, high, low)


cdef inline void exp_ring(const double *v, Py_ssize_t k, double *ev) noexcept nogil:
    """ev (k) = exp(v) of a log ring v (k): its unshaded samples' exp, made once for every step tried on it."""
    cdef Py_ssize_t a
    for a in range(k):
        ev[a] = exp(v[a])


cdef bint step_crosses(const double *lit, const unsigned char *bright, const double *shade, const Py_ssize_t *ends,
                       Py_ssize_t e, Py_ssize_t runs, Py_ssize_t k, Py_ssize_t min_samples, double same_ratio,
                       double *scratch) noexcept nogil:
    """Of a ring `step_ring` made (lit (k), bright (k)): whether the line crosses the X's sectors (the
    bright mask the same at the samples of each of `runs` equal runs of its e ends' samples) with both
    levels on both sides in the same ratio (`both_sides`). scratch: k doubles."""
    cdef Py_ssize_t a, run = e // runs
    cdef bint crosses = True
    for a in range(e):
        crosses = crosses and bright[ends[a]] == bright[ends[a - a % run]]
    return crosses and both_sides(lit, bright, shade, k, min_samples, same_ratio, scratch)


def best_steps(logs, g, norm, shade, ends, double min_step, Py_ssize_t top, double min_quality, double same_ratio,
               Py_ssize_t min_samples):
    """`shadow._best_step`'s choice for log rings logs (n, k) and the log steps g (n, l) of the lines
    whose shaded samples are shade (l, k) (0 or 1), norm (l,) their asymmetries' squared norms and ends
    (l, e) the ring samples about the points where each line crosses the ring (all alike for a line
    that crosses the sectors): per ring, the line
    index (n,) of the best step of the `top` that explain the most of its point asymmetry (ordered as
    np.argsort(kind="stable") orders -explained), whether its X is good enough (n,), its log step (n,)
    and the ring with it taken away (n, k)."""
    cdef const double[:, ::1] v = np.ascontiguousarray(logs, dtype=np.float64)
    cdef const double[:, ::1] steps = np.ascontiguousarray(g, dtype=np.float64)
    cdef const double[::1] norms = np.ascontiguousarray(norm, dtype=np.float64)
    cdef const double[:, ::1] shaded = np.ascontiguousarray(shade, dtype=np.float64)
    cdef const Py_ssize_t[:, ::1] crossing = np.ascontiguousarray(ends, dtype=np.intp)
    cdef Py_ssize_t n = v.shape[0], k = v.shape[1], l = steps.shape[1], e = crossing.shape[1], i, s, a, line
    cdef Py_ssize_t t = top if top < l else l, chosen
    choice, good, step = np.zeros(n, dtype=np.intp), np.zeros(n, dtype=bool), np.zeros(n)
    lit_out = np.zeros((n, k))
    cdef Py_ssize_t[::1] c = choice
    cdef unsigned char[::1] ok = good.view(np.uint8)
    cdef double[::1] out_step = step
    cdef double[:, ::1] out_lit = lit_out
    work = np.empty(l + 5 * k + 1)
    cdef double[::1] w = work  # -explained (l), lit (k), scratch (3 k), exp of the ring (k)
    orders = np.empty(l + 1, dtype=np.intp)
    cdef Py_ssize_t[::1] order = orders
    masks = np.empty(k + 1, dtype=np.uint8)
    cdef unsigned char[::1] bright = masks
    cdef double gl, quality, high, low, best, score
    cdef double *lit = &w[l]
    cdef bint taken
    if n == 0 or t == 0:
        return choice, good, step, lit_out
    with nogil:
        for i in range(n):
            for line in range(l):
                gl = steps[i, line]
                w[line] = -(gl * gl * norms[line] if -gl >= min_step else -1.0)
            stable_order(&w[0], l, &order[0])
            best, chosen = 0.0, 0
            for s in range(t):
                line = order[s]
                gl = steps[i, line]
                if not (-gl >= min_step):
                    # Scores -1 whatever its X (the ring is not made): so do the rest, sorted after it.
                    if s == 0:
                        best, chosen = -1.0, s
                    break
                if s == 0:
                    exp_ring(&v[i, 0], k, &w[l + 4 * k])
                step_ring(&v[i, 0], &w[l + 4 * k], gl, &shaded[line, 0], k, lit, &w[l + k], &bright[0], &quality,
                          &high, &low)
                if quality == quality and (quality < min_quality or (s > 0 and not quality > best)):
                    # A step of less quality than min_quality, or no better than one before it, is never
                    # the chosen step of a ring whose best step is good enough (the others' choice is not
                    # used): it scores -1 without its crossing and sides.
                    score = -1.0
                else:
                    taken = step_crosses(lit, &bright[0], &shaded[line, 0], &crossing[line, 0], e, 1, k, min_samples,
                                         same_ratio, &w[l + 2 * k])
                    score = quality if taken else -1.0
                if score != score:  # np.argmax: the first NaN
                    best, chosen = score, s
                    break
                if s == 0 or score > best:
                    best, chosen = score, s
            line = order[chosen]
            c[i], ok[i], out_step[i] = line, best >= min_quality, steps[i, line]
            for a in range(k):
                out_lit[i, a] = v[i, a] - steps[i, line] * shaded[line, a]
    return choice, good, step, lit_out


def shadow_lines(logs, g, shade, ends, double contrast, double min_quality, double min_step, Py_ssize_t min_samples,
                 double same_ratio):
    """`detect._best_shadow_line` of log rings logs (m, k) and the log steps g (m, l) of the lines whose
    shaded samples are shade (l, k) (0 or 1), ends (l, 2 w) the w ring samples about each of the two
    points where a line crosses the ring (each run of w alike for a line that crosses the sectors): (whether
    a line passes (m,):
    its step taken away leaves an X of quality >= min_quality and levels >= contrast apart, crossing the
    X's sectors, both levels on both sides in the same ratio and -step >= min_step; the index (m,) of the
    passing line of best quality, the first of equals, 0 where none passes)."""
    cdef const double[:, ::1] v = np.ascontiguousarray(logs, dtype=np.float64)
    cdef const double[:, ::1] steps = np.ascontiguousarray(g, dtype=np.float64)
    cdef const double[:, ::1] shaded = np.ascontiguousarray(shade, dtype=np.float64)
    cdef const Py_ssize_t[:, ::1] crossing = np.ascontiguousarray(ends, dtype=np.intp)
    cdef Py_ssize_t m = v.shape[0], k = v.shape[1], l = steps.shape[1], e = crossing.shape[1], i, line
    passes, choice = np.zeros(m, dtype=bool), np.zeros(m, dtype=np.intp)
    cdef unsigned char[::1] ok = passes.view(np.uint8)
    cdef Py_ssize_t[::1] c = choice
    work = np.empty(5 * k + 1)
    cdef double[::1] w = work  # lit (k), scratch (3 k), exp of the ring (k)
    masks = np.empty(k + 1, dtype=np.uint8)
    cdef unsigned char[::1] bright = masks
    cdef double gl, quality, high, low, best, score
    cdef bint good, made
    if m == 0 or l == 0:
        return passes, choice
    with nogil:
        for i in range(m):
            best = 0.0
            made = False
            for line in range(l):
                gl = steps[i, line]
                good = -gl >= min_step  # else it does not pass, whatever its X: the ring is not made
                if good:
                    if not made:
                        exp_ring(&v[i, 0], k, &w[4 * k])
                        made = True
                    step_ring(&v[i, 0], &w[4 * k], gl, &shaded[line, 0], k, &w[0], &w[k], &bright[0], &quality, &high,
                              &low)
                    good = quality >= min_quality and high - low >= contrast
                    # Once a line passed, one no better than the best cannot change the result: its
                    # crossing and sides are not made.
                    if good and (not ok[i] or quality > best):
                        good = step_crosses(&w[0], &bright[0], &shaded[line, 0], &crossing[line, 0], e, 2, k,
                                            min_samples, same_ratio, &w[k])
                    elif good:
                        good = False
                ok[i] = ok[i] or good
                score = quality if good else -1.0  # never NaN: a NaN quality does not pass
                if line == 0 or score > best:
                    c[i], best = line, score
    return passes, choice
