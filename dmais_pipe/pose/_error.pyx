# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled loops of pose.error_model: sums, per frame or per block of observations, of products of the
observations' 2-row matrices, without the (N, 6, 6) stacks of the numpy expressions they replace (most of
the error model's time and memory per frame, issue 40).

Each sum adds its rows in their order and each product its terms in einsum's order, as
`_sum_by(np.einsum(...))` did: with setup.py's -ffp-contract=off the results are those numbers
(tests/test_error_model.py compares them). Keys are sorted or not; a negative key leaves its row out.
"""

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
