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


def values(params, x, y):
    """(n, k) `xfit.model`'s values at pixels x, y (n, k) for params (n, 7)."""
    cdef const double[:, ::1] p = np.ascontiguousarray(params, dtype=float)
    cdef const double[:, ::1] xs = np.ascontiguousarray(x, dtype=float)
    cdef const double[:, ::1] ys = np.ascontiguousarray(y, dtype=float)
    out = np.empty((xs.shape[0], xs.shape[1]))
    cdef double[:, ::1] o = out
    cdef Py_ssize_t i, j
    cdef double c1, s1, c2, s2, scale, dx, dy
    for i in range(xs.shape[0]):
        c1, s1, c2, s2 = cos(p[i, 2]), sin(p[i, 2]), cos(p[i, 3]), sin(p[i, 3])
        scale = SQRT2 * p[i, 4]
        for j in range(xs.shape[1]):
            dx, dy = xs[i, j] - p[i, 0], ys[i, j] - p[i, 1]
            o[i, j] = p[i, 5] + p[i, 6] * erf_of((c1 * dx + s1 * dy) / scale) * erf_of((c2 * dx + s2 * dy) / scale)
    return out


def normal_equations(params, x, y, observed, weights, bint meat=False):
    """Of the X-corner model for params (n, 7) at pixels x, y (n, k) against values observed (n, k)
    with weights (n, k): the weighted cost sum w r^2 (n,), J^T W J (n, 7, 7) and J^T W r (n, 7)
    (r = model - observed), and with `meat` J^T W^2 J (n, 7, 7) too (the sandwich's middle):
    `xfit._normal_equations` of `xfit.model`'s values and Jacobian. Zero weights count where the
    model is not finite (the sums are NaN then, as in numpy)."""
    cdef const double[:, ::1] p = np.ascontiguousarray(params, dtype=float)
    cdef const double[:, ::1] xs = np.ascontiguousarray(x, dtype=float)
    cdef const double[:, ::1] ys = np.ascontiguousarray(y, dtype=float)
    cdef const double[:, ::1] v = np.ascontiguousarray(observed, dtype=float)
    cdef const double[:, ::1] w = np.ascontiguousarray(weights, dtype=float)
    cdef Py_ssize_t n = xs.shape[0], i
    cost, hess, grad = np.zeros(n), np.zeros((n, P, P)), np.zeros((n, P))
    squared = np.zeros((n, P, P)) if meat else hess  # meat's sums, or hess's again (unused)
    cdef double[::1] c = cost
    cdef double[:, :, ::1] h = hess, h2 = squared
    cdef double[:, ::1] g = grad
    for i in range(n):
        c[i] = row_sums(&p[i, 0], &xs[i, 0], &ys[i, 0], &v[i, 0], &w[i, 0], xs.shape[1], &h[i, 0, 0], &g[i, 0],
                        &h2[i, 0, 0] if meat else NULL)
    return (cost, hess, grad, squared) if meat else (cost, hess, grad)


cdef double row_sums(const double *p, const double *x, const double *y, const double *v, const double *w,
                     Py_ssize_t k, double *hess, double *grad, double *meat) noexcept nogil:
    """One window's sums (k pixels) into hess (7 x 7), grad (7) and, unless NULL, meat (7 x 7),
    all zero on entry; returns the cost."""
    cdef double trig[4]
    cdef double jac[P]
    cdef double wj[P]
    cdef double total = 0.0, r
    cdef Py_ssize_t j, a, b
    # A pixel of weight 0 adds exact zeros where the model is finite (finite params, blur > 0).
    cdef bint skip_zero = p[4] > 0.0
    for a in range(P):
        skip_zero &= isfinite(p[a])
    trig[0], trig[1], trig[2], trig[3] = cos(p[2]), sin(p[2]), cos(p[3]), sin(p[3])
    for j in range(k):
        if skip_zero and w[j] == 0.0:
            continue
        r = pixel(p, trig, x[j], y[j], jac) - v[j]
        total += w[j] * r * r
        for a in range(P):
            wj[a] = jac[a] * w[j]
            grad[a] += wj[a] * r
        for a in range(P):
            for b in range(a + 1):
                hess[a * P + b] += wj[a] * jac[b]
        if meat != NULL:
            for a in range(P):
                for b in range(a + 1):
                    meat[a * P + b] += wj[a] * w[j] * jac[b]
    mirror(hess)
    if meat != NULL:
        mirror(meat)
    return total


cdef inline void mirror(double *m) noexcept nogil:
    """The lower triangle of m (7 x 7) copied above the diagonal."""
    cdef Py_ssize_t a, b
    for a in range(P):
        for b in range(a):
            m[b * P + a] = m[a * P + b]


cdef inline double pixel(const double *p, const double *trig, double x, double y, double *jac) noexcept nogil:
    """The model's value at x, y for params p (7) and its Jacobian into jac (7), as `xfit.model`;
    trig: cos t1, sin t1, cos t2, sin t2."""
    cdef double c1 = trig[0], s1 = trig[1], c2 = trig[2], s2 = trig[3]
    cdef double s = p[4], c = p[6]
    cdef double dx = x - p[0], dy = y - p[1]
    cdef double l1 = c1 * dx + s1 * dy, l2 = c2 * dx + s2 * dy
    cdef double a = erf_of(l1 / (SQRT2 * s)), b = erf_of(l2 / (SQRT2 * s))
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
