# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled loops of pose.error_model: sums, per frame or per block of observations, of products of the
observations' 2-row matrices, without the (N, 6, 6) stacks of the numpy expressions they replace (most of
the error model's time and memory per frame, issue 40).

Each sum adds its rows in their order and each product its terms in einsum's order, as
`_sum_by(np.einsum(...))` did: with setup.py's -ffp-contract=off the results are those numbers
(tests/test_error_model.py compares them). Keys are sorted or not; a negative key leaves its row out.
"""

from libc.math cimport sqrt

import numpy as np


def row_products(left, right, key, Py_ssize_t n_keys):
    """(n_keys, a, b): per key (N,), the sum of left_n^T right_n over its rows, left (N, 2, a), right (N, 2, b):
    error_model._sum_by(np.einsum("nki,nkj->nij", left, right), key, n_keys)."""
    cdef const double[:, :, ::1] l = np.ascontiguousarray(left, dtype=float)
    cdef const double[:, :, ::1] r = np.ascontiguousarray(right, dtype=float)
    cdef const Py_ssize_t[::1] k = np.ascontiguousarray(key, dtype=np.intp)
    out = np.zeros((n_keys, l.shape[2], r.shape[2]))
    cdef double[:, :, ::1] o = out
    cdef Py_ssize_t n, i, j, slot
    for n in range(l.shape[0]):
        slot = k[n]
        if slot < 0:
            continue
        for i in range(l.shape[2]):
            for j in range(r.shape[2]):
                o[slot, i, j] += l[n, 0, i] * r[n, 0, j] + l[n, 1, i] * r[n, 1, j]
    return out


def scaled_outer_sums(left, effect, scale, key, Py_ssize_t n_keys):
    """(n_keys, a, a): per key (N,), the sum of scale_n K_n K_n^T over its rows, K_n = left_n^T effect_n (a, e),
    left (N, 2, a), effect (N, 2, e), scale (N,): error_model's _sum_by(_scaled_outer(np.einsum("nki,nkj->nij",
    left, effect), scale), key, n_keys)."""
    cdef const double[:, :, ::1] l = np.ascontiguousarray(left, dtype=float)
    cdef const double[:, :, ::1] e = np.ascontiguousarray(effect, dtype=float)
    cdef const double[::1] s = np.ascontiguousarray(scale, dtype=float)
    cdef const Py_ssize_t[::1] k = np.ascontiguousarray(key, dtype=np.intp)
    cdef Py_ssize_t a = l.shape[2], width = e.shape[2]
    out = np.zeros((n_keys, a, a))
    cdef double[:, :, ::1] o = out
    product = np.zeros((a, width))
    cdef double[:, ::1] K = product
    cdef Py_ssize_t n, i, j, m, slot
    cdef double value
    for n in range(l.shape[0]):
        slot = k[n]
        if slot < 0:
            continue
        for i in range(a):
            for j in range(width):
                K[i, j] = l[n, 0, i] * e[n, 0, j] + l[n, 1, i] * e[n, 1, j]
        for i in range(a):
            for m in range(a):
                value = (K[i, 0] * s[n]) * K[m, 0]
                for j in range(1, width):
                    value = value + (K[i, j] * s[n]) * K[m, j]
                o[slot, i, m] += value
    return out


cdef inline double dot3(const double *a, const double *b) noexcept nogil:
    """a . b of three numbers as np.einsum("...j,...j") adds them: (a0 b0 + a2 b2) + a1 b1."""
    return (a[0] * b[0] + a[2] * b[2]) + a[1] * b[1]


def predicted_directions(R, t, frame, points, origins, bases=None):
    """(N, 3) the unit directions from each ray's origin to its point for the poses R (F, 3, 3), t (F, 3) of the
    rows' frames (N,), points and origins (N, 3): error_model's p = R[frame] m + t[frame] - o over its norm; with
    bases (N, 2, 3), their products with them instead (N, 2) (the residuals of nonlinear.py), as numpy's einsum,
    norm and division make them."""
    cdef const double[:, :, ::1] r = np.ascontiguousarray(R, dtype=float)
    cdef const double[:, ::1] tt = np.ascontiguousarray(t, dtype=float)
    cdef const Py_ssize_t[::1] k = np.ascontiguousarray(frame, dtype=np.intp)
    cdef const double[:, ::1] m = np.ascontiguousarray(points, dtype=float)
    cdef const double[:, ::1] o = np.ascontiguousarray(origins, dtype=float)
    cdef bint residuals = bases is not None
    cdef const double[:, :, ::1] b = np.ascontiguousarray(bases if residuals else np.zeros((0, 2, 3)), dtype=float)
    out = np.empty((m.shape[0], 2 if residuals else 3))
    cdef double[:, ::1] result = out
    cdef Py_ssize_t n, i, f
    cdef double p[3]
    cdef double norm
    for n in range(m.shape[0]):
        f = k[n]
        for i in range(3):
            p[i] = (dot3(&r[f, i, 0], &m[n, 0]) + tt[f, i]) - o[n, i]
        norm = sqrt((p[0] * p[0] + p[1] * p[1]) + p[2] * p[2])
        for i in range(3):
            p[i] = p[i] / norm
        if residuals:
            result[n, 0] = dot3(&b[n, 0, 0], p)
            result[n, 1] = dot3(&b[n, 1, 0], p)
        else:
            result[n, 0], result[n, 1], result[n, 2] = p[0], p[1], p[2]
    return out
