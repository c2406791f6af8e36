# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled loops of markers.xfit: the blurred X-corner model (`xfit.model`), its Jacobian and the
weighted normal equations of a window, in one pass over its pixels (most of a 12 MP image's
refinement, issue 40: numpy made the (n, k, 7) Jacobian, then batched BLAS products of it).

Each pixel's value and Jacobian are formed in the order `xfit.model` forms them, with the same erf
(scipy's, through cython_special); cos, sin and exp are libm's, and the sums over the pixels are
added in their order, so the results are numpy's to rounding (tests/test_xfit.py: 1e-10 relative),
not to the last bit. Arrays are C-ordered doubles; rows (n) are windows, k their pixels.
"""

from libc.math cimport cos, exp, isfinite, sin, sqrt
from scipy.special.cython_special cimport erf

import numpy as np

cdef enum:
    P = 7  # px, py, t1, t2, s, m, c

cdef double SQRT2 = sqrt(2.0)
cdef double DERF = sqrt(2.0 / np.pi)
cdef double ERF_ONE = 6.0


def values(params, x, y, erfs=None):
    """(n, k) `xfit.model`'s values at pixels x, y (n, k) for params (n, 7); with erfs (2, n, k) (float64,
    C-ordered), its two erf factors into erfs[0] and erfs[1]: they depend on the corner, the edges and the
    blur only, and `normal_equations` of params that differ in the levels alone takes them from there."""
    cdef const double[:, ::1] p = np.ascontiguousarray(params, dtype=float)
    cdef const double[:, ::1] xs = np.ascontiguousarray(x, dtype=float)
    cdef const double[:, ::1] ys = np.ascontiguousarray(y, dtype=float)
    out = np.empty((xs.shape[0], xs.shape[1]))
    cdef double[:, ::1] o = out
    cdef double[:, :, ::1] e
    cdef bint keep = erfs is not None
    if keep:
        e = erfs
        if e.shape[0] != 2 or e.shape[1] != xs.shape[0] or e.shape[2] != xs.shape[1]:
            raise ValueError("erfs must be (2, n, k)")
    cdef Py_ssize_t i, j
    cdef double c1, s1, c2, s2, scale, dx, dy, a, b
    for i in range(xs.shape[0]):
        c1, s1, c2, s2 = cos(p[i, 2]), sin(p[i, 2]), cos(p[i, 3]), sin(p[i, 3])
        scale = SQRT2 * p[i, 4]
        for j in range(xs.shape[1]):
            dx, dy = xs[i, j] - p[i, 0], ys[i, j] - p[i, 1]
            a, b = erf_of((c1 * dx + s1 * dy) / scale), erf_of((c2 * dx + s2 * dy) / scale)
            o[i, j] = p[i, 5] + p[i, 6] * a * b
            if keep:
                e[0, i, j], e[1, i, j] = a, b
    return out


def normal_equations(params, x, y, observed, weights, bint meat=False, meat_rows=None, erfs=None):
    """Of the X-corner model for params (n, 7) at pixels x, y (n, k) against values observed (n, k)
    with weights (n, k): the weighted cost sum w r^2 (n,), J^T W J (n, 7, 7) and J^T W r (n, 7)
    (r = model - observed), and with `meat` J^T W^2 J (n, 7, 7) too (the sandwich's middle):
    `xfit._normal_equations` of `xfit.model`'s values and Jacobian. Zero weights count where the
    model is not finite (the sums are NaN then, as in numpy). meat_rows (n,) bool: J^T W^2 J of
    those rows only, in the same pass (the others' zero), returned as with `meat`; each row's sums
    are the same whether or not its meat is made. erfs (2, n, k): the model's erf factors at these
    params, as `values` kept them (the same numbers; not made again)."""
    cdef const double[:, ::1] p = np.ascontiguousarray(params, dtype=float)
    cdef const double[:, ::1] xs = np.ascontiguousarray(x, dtype=float)
    cdef const double[:, ::1] ys = np.ascontiguousarray(y, dtype=float)
    cdef const double[:, ::1] v = np.ascontiguousarray(observed, dtype=float)
    cdef const double[:, ::1] w = np.ascontiguousarray(weights, dtype=float)
    cdef Py_ssize_t n = xs.shape[0], i
    cdef const unsigned char[::1] rows
    if meat_rows is not None:
        rows = np.ascontiguousarray(meat_rows, dtype=bool).view(np.uint8)
        meat = True
    cost, hess, grad = np.zeros(n), np.zeros((n, P, P)), np.zeros((n, P))
    squared = np.zeros((n, P, P)) if meat else hess  # meat's sums, or hess's again (unused)
    cdef double[::1] c = cost
    cdef double[:, :, ::1] h = hess, h2 = squared
    cdef double[:, ::1] g = grad
    cdef bint made, cached = erfs is not None
    cdef const double[:, :, ::1] e
    if cached:
        e = erfs
        if e.shape[0] != 2 or e.shape[1] != n or e.shape[2] != xs.shape[1]:
            raise ValueError("erfs must be (2, n, k)")
    for i in range(n):
        made = meat and (meat_rows is None or rows[i])
        c[i] = row_sums(&p[i, 0], &xs[i, 0], &ys[i, 0], &v[i, 0], &w[i, 0], xs.shape[1], &h[i, 0, 0], &g[i, 0],
                        &h2[i, 0, 0] if made else NULL, &e[0, i, 0] if cached else NULL,
                        &e[1, i, 0] if cached else NULL)
    return (cost, hess, grad, squared) if meat else (cost, hess, grad)


cdef double row_sums(const double *p, const double *x, const double *y, const double *v, const double *w,
                     Py_ssize_t k, double *hess, double *grad, double *meat, const double *erf_a,
                     const double *erf_b) noexcept nogil:
    """One window's sums (k pixels) into hess (7 x 7), grad (7) and, unless NULL, meat (7 x 7),
    all zero on entry; returns the cost. erf_a, erf_b (k): the erf factors of its pixels, or NULL
    (made here). The sums are made in local arrays (no store of one can alias an input), each
    added to in the pixels' order."""
    cdef double q[P]
    cdef double trig[4]
    cdef double jac[P]
    cdef double wj[P]
    cdef double h[P * P]
    cdef double m[P * P]
    cdef double g[P]
    cdef double total = 0.0, r, wv
    cdef Py_ssize_t j, a, b
    cdef bint with_meat = meat != NULL
    for a in range(P):
        q[a], g[a] = p[a], 0.0
    for a in range(P * P):
        h[a], m[a] = 0.0, 0.0
    # A pixel of weight 0 adds exact zeros where the model is finite (finite params, blur > 0).
    cdef bint skip_zero = q[4] > 0.0
    for a in range(P):
        skip_zero &= isfinite(q[a])
    trig[0], trig[1], trig[2], trig[3] = cos(q[2]), sin(q[2]), cos(q[3]), sin(q[3])
    for j in range(k):
        wv = w[j]
        if skip_zero and wv == 0.0:
            continue
        r = pixel(q, trig, x[j], y[j], jac, &erf_a[j] if erf_a != NULL else NULL,
                  &erf_b[j] if erf_b != NULL else NULL) - v[j]
        total += wv * r * r
        for a in range(P):
            wj[a] = jac[a] * wv
            g[a] += wj[a] * r
        for a in range(P):
            for b in range(a + 1):
                h[a * P + b] += wj[a] * jac[b]
        if with_meat:
            for a in range(P):
                for b in range(a + 1):
                    m[a * P + b] += wj[a] * wv * jac[b]
    for a in range(P):
        grad[a] = g[a]
        for b in range(a + 1):
            hess[a * P + b] = h[a * P + b]
            if with_meat:
                meat[a * P + b] = m[a * P + b]
    mirror(hess)
    if with_meat:
        mirror(meat)
    return total


cdef inline void mirror(double *m) noexcept nogil:
    """The lower triangle of m (7 x 7) copied above the diagonal."""
    cdef Py_ssize_t a, b
    for a in range(P):
        for b in range(a):
            m[b * P + a] = m[a * P + b]


cdef inline double pixel(const double *p, const double *trig, double x, double y, double *jac, const double *erf_a,
                         const double *erf_b) noexcept nogil:
    """The model's value at x, y for params p (7) and its Jacobian into jac (7), as `xfit.model`;
    trig: cos t1, sin t1, cos t2, sin t2; erf_a, erf_b: its erf factors, or NULL (made here)."""
    cdef double c1 = trig[0], s1 = trig[1], c2 = trig[2], s2 = trig[3]
    cdef double s = p[4], c = p[6]
    cdef double dx = x - p[0], dy = y - p[1]
    cdef double l1 = c1 * dx + s1 * dy, l2 = c2 * dx + s2 * dy
    cdef double a = erf_a[0] if erf_a != NULL else erf_of(l1 / (SQRT2 * s))
    cdef double b = erf_b[0] if erf_b != NULL else erf_of(l2 / (SQRT2 * s))
    cdef double ca = c * a
    cdef double da = DERF / s * exp(-0.5 * (l1 / s) * (l1 / s))
    cdef double db = DERF / s * exp(-0.5 * (l2 / s) * (l2 / s))
    cdef double dab = da * b, adb = a * db, minus_c = -c
    jac[0] = minus_c * (dab * c1 + adb * c2)
    jac[1] = minus_c * (dab * s1 + adb * s2)
    jac[2] = c * da * b * (-s1 * dx + c1 * dy)
    jac[3] = ca * db * (-s2 * dx + c2 * dy)
    jac[4] = minus_c * (dab * l1 + adb * l2) / s
    jac[5] = 1.0
    jac[6] = a * b
    return p[5] + ca * b


cdef inline double erf_of(double z) noexcept nogil:
    """scipy's erf(z): +-1 beyond ERF_ONE, where erfc(z) < 2.2e-17 rounds 1 - erfc(z) to 1 (most of a
    window's pixels lie that far from one of the edges), else scipy's own."""
    if z >= ERF_ONE:
        return 1.0
    if z <= -ERF_ONE:
        return -1.0
    return erf(z)


def window_pixels(centre, rounded, ox, oy, double radius2, Py_ssize_t width, Py_ssize_t height):
    """`xfit.window`'s arithmetic in one pass: for centres (n, 2), their rounded pixels rounded (n, 2)
    (int) and the disc's offsets ox, oy (k,) (int): the positions x, y (n, k) (float), the rows and
    columns clamped into the image (n, k) (intp, the pixels to read) and the taper weights (n, k),
    max(1 - d^2 / radius2, 0)^2 where the pixel is in the image, else 0 (NaN stays NaN), each number
    as numpy's expressions make it."""
    cdef const double[:, ::1] c = np.ascontiguousarray(centre, dtype=np.float64)
    cdef const Py_ssize_t[:, ::1] r = np.ascontiguousarray(rounded, dtype=np.intp)
    cdef const Py_ssize_t[::1] dx = np.ascontiguousarray(ox, dtype=np.intp)
    cdef const Py_ssize_t[::1] dy = np.ascontiguousarray(oy, dtype=np.intp)
    cdef Py_ssize_t n = c.shape[0], k = dx.shape[0], i, j, xv, yv
    xs, ys = np.empty((n, k)), np.empty((n, k))
    rows, columns = np.empty((n, k), dtype=np.intp), np.empty((n, k), dtype=np.intp)
    weights = np.empty((n, k))
    cdef double[:, ::1] xo = xs, yo = ys, wo = weights
    cdef Py_ssize_t[:, ::1] ro = rows, co = columns
    cdef double ex, ey, t
    with nogil:
        for i in range(n):
            for j in range(k):
                xv, yv = r[i, 0] + dx[j], r[i, 1] + dy[j]
                xo[i, j], yo[i, j] = <double>xv, <double>yv
                co[i, j] = 0 if xv < 0 else (width - 1 if xv > width - 1 else xv)
                ro[i, j] = 0 if yv < 0 else (height - 1 if yv > height - 1 else yv)
                ex, ey = <double>xv - c[i, 0], <double>yv - c[i, 1]
                t = 1.0 - (ex * ex + ey * ey) / radius2
                if not (t >= 0.0 or t != t):  # np.maximum(t, 0.0): NaN stays
                    t = 0.0
                wo[i, j] = t * t * (1.0 if (xv >= 0 and xv < width and yv >= 0 and yv < height) else 0.0)
    return xs, ys, rows, columns, weights
