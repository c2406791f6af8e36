# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled loops of pose.error_model: sums, per frame or per block of observations, of products of the
observations' 2-row matrices, without the (N, 6, 6) stacks of the numpy expressions they replace (most of
the error model's time and memory per frame, issue 40).

Each sum adds its rows in their order and each product its terms in einsum's order, as
`_sum_by(np.einsum(...))` did: with setup.py's -ffp-contract=off the results are those numbers
(tests/test_error_model.py compares them). Keys are sorted or not; a negative key leaves its row out.

The per-observation passes (`linearised_rows`, `calibration_columns`, `covariance_sums`, `curvature_sums`)
do in one loop what numpy did in a dozen passes over (N, 2, k) stacks, each number by the same operations
in the same order: einsum's three-term contractions as `dot3z` (its output's zero added last), np.cross
and np.linalg.norm as written out (tests/test_error_model_rows.py compares them with the numpy, bit for bit).
"""

from libc.math cimport fabs, sqrt

import numpy as np


def row_products(left, right, key, Py_ssize_t n_keys, weight=None):
    """(n_keys, a, b): per key (N,), the sum of left_n^T right_n over its rows, left (N, 2, a), right (N, 2, b):
    error_model._sum_by(np.einsum("nki,nkj->nij", left, right), key, n_keys); with weight (N,), of left each row
    times its weight (left * weight[:, None, None], without the copy)."""
    cdef const double[:, :, ::1] l = np.ascontiguousarray(left, dtype=float)
    cdef const double[:, :, ::1] r = np.ascontiguousarray(right, dtype=float)
    cdef const Py_ssize_t[::1] k = np.ascontiguousarray(key, dtype=np.intp)
    cdef bint weighted = weight is not None
    cdef const double[::1] w = np.ascontiguousarray(weight if weighted else np.ones(0), dtype=float)
    out = np.zeros((n_keys, l.shape[2], r.shape[2]))
    cdef double[:, :, ::1] o = out
    cdef Py_ssize_t n, i, j, slot
    cdef double first, second
    for n in range(l.shape[0]):
        slot = k[n]
        if slot < 0:
            continue
        for i in range(l.shape[2]):
            first, second = l[n, 0, i], l[n, 1, i]
            if weighted:
                first, second = first * w[n], second * w[n]
            for j in range(r.shape[2]):
                o[slot, i, j] += first * r[n, 0, j] + second * r[n, 1, j]
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


cdef inline double dot3z(const double *a, const double *b) noexcept nogil:
    """a . b as np.einsum's contraction of three ("nij,nj->ni", "ni,ni->n", "nki,nip->nkp") makes it: the
    products in the order 0, 2, 1, added to the output's initial zero (a sum of -0 terms is +0)."""
    return 0.0 + ((a[0] * b[0] + a[2] * b[2]) + a[1] * b[1])


cdef inline double norm3(const double *a) noexcept nogil:
    """np.linalg.norm of a (3,) along its axis: the squares added in order."""
    return sqrt((a[0] * a[0] + a[1] * a[1]) + a[2] * a[2])


cdef inline void cross3(const double *a, const double *b, double *out) noexcept nogil:
    """out = np.cross(a, b), a, b (3,); out must not alias them."""
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]


cdef inline void tangent_basis(const double *f, double *b1, double *b2) noexcept nogil:
    """refine.tangent_bases of one unit direction f (3,): b1 = f x a / ||f x a||, a the axis of the least
    |f_k| (the first of equal ones, or of a NaN, as np.argmin), b2 = f x b1."""
    cdef double axis[3]
    cdef double m0 = fabs(f[0]), m1 = fabs(f[1]), m2 = fabs(f[2]), least, norm
    cdef int k = 0
    if m0 != m0:
        k = 0
    elif m1 != m1:
        k = 1
    elif m2 != m2:
        k = 2
    else:
        least = m0
        if m1 < least:
            k, least = 1, m1
        if m2 < least:
            k = 2
    axis[0] = axis[1] = axis[2] = 0.0
    axis[k] = 1.0
    cross3(f, axis, b1)
    norm = norm3(b1)
    b1[0] = b1[0] / norm
    b1[1] = b1[1] / norm
    b1[2] = b1[2] / norm
    cross3(f, b1, b2)


def tangent_bases(directions):
    """(n, 2, 3) refine.tangent_bases of unit directions (n, 3), by `tangent_basis` (tests compare them)."""
    cdef const double[:, ::1] f = np.ascontiguousarray(directions, dtype=float)
    out = np.empty((f.shape[0], 2, 3))
    cdef double[:, :, ::1] b = out
    cdef Py_ssize_t n
    for n in range(f.shape[0]):
        tangent_basis(&f[n, 0], &b[n, 0, 0], &b[n, 1, 0])
    return out


def linearised_rows(origins, directions, points, centroid, R, t, t_centred, frame, axes, camera):
    """The per-observation arrays of error_model.linearised_solve, N observations of F frames: origins,
    directions, points (N, 3) (rig frame, rig frame, world), centroid (F, 3) each frame's point centroid,
    R (F, 3, 3), t (F, 3) rig_from_world, t_centred (F, 3) t + R centroid, frame (N,), axes (C, 3) each
    camera's optical axis in the rig, camera (N,) its row of axes (negative: from the end, as numpy).

    Returns unit (N, 3) the unit rays f, bases (N, 2, 3) B (refine.tangent_bases), residual (N, 2) and
    J (N, 2, 6) (refine._jacobian about the centroid), squares (N,) |p|^2 of p = R m + t - o, dr_dp (N, 2, 3)
    (B - r (p / |p|)^T) / |p|, rotation (N, 2, 3) B [f]x, focal_effect (N, 2) -(f . a) B a and
    points_centred (N, 3), each as linearised_solve's numpy made it."""
    cdef const double[:, ::1] o = np.ascontiguousarray(origins, dtype=float)
    cdef const double[:, ::1] d = np.ascontiguousarray(directions, dtype=float)
    cdef const double[:, ::1] m = np.ascontiguousarray(points, dtype=float)
    cdef const double[:, ::1] mean = np.ascontiguousarray(centroid, dtype=float)
    cdef const double[:, :, ::1] r = np.ascontiguousarray(R, dtype=float)
    cdef const double[:, ::1] tt = np.ascontiguousarray(t, dtype=float)
    cdef const double[:, ::1] tc = np.ascontiguousarray(t_centred, dtype=float)
    cdef const Py_ssize_t[::1] k = np.ascontiguousarray(frame, dtype=np.intp)
    cdef const double[:, ::1] a = np.ascontiguousarray(axes, dtype=float)
    cdef const Py_ssize_t[::1] cam = np.ascontiguousarray(camera, dtype=np.intp)
    cdef Py_ssize_t N = m.shape[0], n_cameras = a.shape[0], n, f, c, i, j, row
    unit_out, bases_out = np.empty((N, 3)), np.empty((N, 2, 3))
    residual_out, J_out, squares_out = np.empty((N, 2)), np.empty((N, 2, 6)), np.empty(N)
    dr_dp_out, rotation_out, focal_out = np.empty((N, 2, 3)), np.empty((N, 2, 3)), np.empty((N, 2))
    centred_out = np.empty((N, 3))
    cdef double[:, ::1] unit = unit_out, residual = residual_out, focal = focal_out, centred = centred_out
    cdef double[:, :, ::1] bases = bases_out, J = J_out, dr_dp = dr_dp_out, rotation = rotation_out
    cdef double[::1] squares = squares_out
    cdef double q[3]
    cdef double p[3]
    cdef double u[3]
    cdef double v[3]
    cdef double step[3]
    cdef double norm, square, along
    for n in range(N):
        f = k[n]
        if f < 0 or f >= r.shape[0]:
            raise IndexError(f"linearised_rows: frame {f} of row {n} is not one of {r.shape[0]}")
        norm = norm3(&d[n, 0])
        for i in range(3):
            unit[n, i] = d[n, i] / norm
        tangent_basis(&unit[n, 0], &bases[n, 0, 0], &bases[n, 1, 0])
        for i in range(3):
            centred[n, i] = m[n, i] - mean[f, i]
        # refine._jacobian about the centroid
        for i in range(3):
            q[i] = dot3z(&r[f, i, 0], &centred[n, 0])
            p[i] = (q[i] + tc[f, i]) - o[n, i]
        norm = norm3(p)
        for i in range(3):
            u[i] = p[i] / norm
        for row in range(2):
            residual[n, row] = dot3z(&bases[n, row, 0], u)
            for j in range(3):
                step[j] = (bases[n, row, j] - residual[n, row] * u[j]) / norm
                J[n, row, 3 + j] = step[j]
            cross3(q, step, &J[n, row, 0])
        # the ray-to-point vector of the uncentred points: the weights and the survey's dr/dp
        for i in range(3):
            p[i] = (dot3z(&r[f, i, 0], &m[n, 0]) + tt[f, i]) - o[n, i]
        square = (p[0] * p[0] + p[1] * p[1]) + p[2] * p[2]
        squares[n] = square
        norm = sqrt(square)
        for j in range(3):
            v[j] = p[j] / norm
        for row in range(2):
            for j in range(3):
                dr_dp[n, row, j] = (bases[n, row, j] - residual[n, row] * v[j]) / norm
            cross3(&bases[n, row, 0], &unit[n, 0], &rotation[n, row, 0])
        c = cam[n]
        if c < 0:
            c = c + n_cameras
        if c < 0 or c >= n_cameras:
            raise IndexError(f"linearised_rows: camera {cam[n]} of row {n} is not a row of axes ({n_cameras})")
        along = -dot3z(&unit[n, 0], &a[c, 0])
        for row in range(2):
            focal[n, row] = along * dot3z(&bases[n, row, 0], &a[c, 0])
    return unit_out, bases_out, residual_out, J_out, squares_out, dr_dp_out, rotation_out, focal_out, centred_out


def calibration_columns(w, dw, rig_from_cam, bases, rotation, dr_dp, rows, columns, parameters, effects):
    """Fill error_model._calibration_effects' C_i of one camera's observations `rows` (n,) into effects
    (N, 2, K), zero where not filled: for the camera's own parameters (columns (p,) of effects, parameters
    (p,) their columns of dw), -B_i times the change of the ray (rig frame) of its pixel's undistorted
    point w (n, 3) (x, y, 1), whose (x, y) change per parameter is dw (n, 2, P), i.e. -B_i (I - f f^T) dw / |w|
    turned by rig_from_cam (3, 3) (error_model._ray_changes); then its rotation (G_i, columns 5:8) and
    -dr_dp (columns 8:11). bases, rotation, dr_dp (N, 2, 3)."""
    cdef const double[:, ::1] ww = np.ascontiguousarray(w, dtype=float)
    cdef const double[:, :, ::1] change = np.ascontiguousarray(dw, dtype=float)
    cdef const double[:, ::1] M = np.ascontiguousarray(rig_from_cam, dtype=float)
    cdef const double[:, :, ::1] b = np.ascontiguousarray(bases, dtype=float)
    cdef const double[:, :, ::1] g = np.ascontiguousarray(rotation, dtype=float)
    cdef const double[:, :, ::1] dr = np.ascontiguousarray(dr_dp, dtype=float)
    cdef const Py_ssize_t[::1] index = np.ascontiguousarray(rows, dtype=np.intp)
    cdef const Py_ssize_t[::1] column = np.ascontiguousarray(columns, dtype=np.intp)
    cdef const Py_ssize_t[::1] parameter = np.ascontiguousarray(parameters, dtype=np.intp)
    cdef double[:, :, ::1] out = effects
    cdef Py_ssize_t a, n, i, j, row, e
    cdef double f[3]
    cdef double moved[3]
    cdef double turned[3]
    cdef double norm, along
    for a in range(index.shape[0]):
        n = index[a]
        if column.shape[0]:
            norm = norm3(&ww[a, 0])
            for i in range(3):
                f[i] = ww[a, i] / norm
            for e in range(column.shape[0]):
                j = parameter[e]  # the ray's third component (1) does not change: numpy's 0 written out
                along = ((0.0 + f[0] * change[a, 0, j]) + f[1] * change[a, 1, j]) + f[2] * 0.0
                for i in range(2):
                    moved[i] = (change[a, i, j] - f[i] * along) / norm
                moved[2] = (0.0 - f[2] * along) / norm
                for i in range(3):
                    turned[i] = ((0.0 + M[i, 0] * moved[0]) + M[i, 1] * moved[1]) + M[i, 2] * moved[2]
                for row in range(2):
                    out[n, row, column[e]] = -dot3z(&b[n, row, 0], turned)
        for row in range(2):
            for i in range(3):
                out[n, row, 5 + i] = g[n, row, i]
                out[n, row, 8 + i] = -dr[n, row, i]


cdef inline void outer_sum(double l[2][6], double e[2][2], Py_ssize_t width, double scale,
                           double *out) noexcept nogil:
    """out (6, 6) += scale K K^T, K = l^T e (6, width) (l (2, 6), e (2, width)), as scaled_outer_sums adds it.
    With scale 1 each (i, m) term is the (m, i) one to the bit ((K_ij 1) K_mj = K_mj K_ij): made once."""
    cdef double K[6][2]
    cdef Py_ssize_t i, j, m
    cdef double value
    cdef bint symmetric = scale == 1.0
    for i in range(6):
        for j in range(width):
            K[i][j] = l[0][i] * e[0][j] + l[1][i] * e[1][j]
    for i in range(6):
        for m in range(i if symmetric else 0, 6):
            value = (K[i][0] * scale) * K[m][0]
            for j in range(1, width):
                value = value + (K[i][j] * scale) * K[m][j]
            out[6 * i + m] += value
            if symmetric and m != i:
                out[6 * m + i] += value


def covariance_sums(J, weight, focal, survey, survey_sigma, rotation, focal_effect, calibration, frame, block,
                    camera, Py_ssize_t n_frames, Py_ssize_t n_blocks, Py_ssize_t n_cameras, double pixel_variance):
    """error_model.frame_covariances' sums over the observations, of the rows w_i J_i (J (N, 2, 6), weight
    (N,)) and each component's effect, in one pass: per frame (frame (N,)) the pixel's, survey's and
    vertical survey's sum of K V K^T (F, 6, 6) (`scaled_outer_sums` of I / focal (N,) at pixel_variance, of
    survey (N, 2, 3) D_i times survey_sigma (N, 3) along x, y and along z); per block of a frame's camera
    (block (N,)) the `row_products` of the rotation G_i (N, 2, 3) (B, 6, 3) and of the focal effect h_i
    (N, 2) (B, 6, 1); per frame, those of the calibration C_i (N, 2, K) in its camera's columns (camera (N,)
    non-negative) (F, 6, K n_cameras)."""
    cdef const double[:, :, ::1] jac = np.ascontiguousarray(J, dtype=float)
    cdef const double[::1] wt = np.ascontiguousarray(weight, dtype=float)
    cdef const double[::1] fl = np.ascontiguousarray(focal, dtype=float)
    cdef const double[:, :, ::1] sv = np.ascontiguousarray(survey, dtype=float)
    cdef const double[:, ::1] ss = np.ascontiguousarray(survey_sigma, dtype=float)
    cdef const double[:, :, ::1] rot = np.ascontiguousarray(rotation, dtype=float)
    cdef const double[:, ::1] fe = np.ascontiguousarray(focal_effect, dtype=float)
    cdef const double[:, :, ::1] cal = np.ascontiguousarray(calibration, dtype=float)
    cdef const Py_ssize_t[::1] fr = np.ascontiguousarray(frame, dtype=np.intp)
    cdef const Py_ssize_t[::1] bl = np.ascontiguousarray(block, dtype=np.intp)
    cdef const Py_ssize_t[::1] cm = np.ascontiguousarray(camera, dtype=np.intp)
    cdef Py_ssize_t n_parameters = cal.shape[2]
    pixel_out, survey_out, vertical_out = np.zeros((n_frames, 6, 6)), np.zeros((n_frames, 6, 6)), \
        np.zeros((n_frames, 6, 6))
    rotation_out, focal_out = np.zeros((n_blocks, 6, 3)), np.zeros((n_blocks, 6, 1))
    calibration_out = np.zeros((n_frames, 6, n_parameters * n_cameras))
    cdef double[:, :, ::1] pixel = pixel_out, surveyed = survey_out, vertical = vertical_out
    cdef double[:, :, ::1] rotated = rotation_out, focused = focal_out, calibrated = calibration_out
    cdef double l[2][6]
    cdef double e[2][2]
    cdef Py_ssize_t n, f, b, i, j, k, first
    cdef double inverse, zero
    for n in range(jac.shape[0]):
        f, b = fr[n], bl[n]
        if f < 0 or f >= n_frames:
            raise IndexError(f"covariance_sums: frame {f} of row {n} is not one of {n_frames}")
        for k in range(2):
            for i in range(6):
                l[k][i] = jac[n, k, i] * wt[n]
        # the pixel noise: E = I / focal (numpy's eye divided, its zeros too)
        inverse, zero = 1.0 / fl[n], 0.0 / fl[n]
        e[0][0], e[0][1], e[1][0], e[1][1] = inverse, zero, zero, inverse
        outer_sum(l, e, 2, pixel_variance, &pixel[f, 0, 0])
        for k in range(2):
            e[k][0], e[k][1] = sv[n, k, 0] * ss[n, 0], sv[n, k, 1] * ss[n, 1]
        outer_sum(l, e, 2, 1.0, &surveyed[f, 0, 0])
        for k in range(2):
            e[k][0] = sv[n, k, 2] * ss[n, 2]
        outer_sum(l, e, 1, 1.0, &vertical[f, 0, 0])
        if b < 0 or b >= n_blocks or cm[n] < 0 or cm[n] >= n_cameras:  # no block, no camera: not summed
            continue
        first = n_parameters * cm[n]
        for i in range(6):
            for j in range(3):
                rotated[b, i, j] += l[0][i] * rot[n, 0, j] + l[1][i] * rot[n, 1, j]
            focused[b, i, 0] += l[0][i] * fe[n, 0] + l[1][i] * fe[n, 1]
            for j in range(n_parameters):
                calibrated[f, i, first + j] += l[0][i] * cal[n, 0, j] + l[1][i] * cal[n, 1, j]
    return pixel_out, survey_out, vertical_out, rotation_out, focal_out, calibration_out


cdef inline void moved_residual(const double *R, const double *t, const double *m, const double *o,
                                const double *b1, const double *b2, double *out) noexcept nogil:
    """out (2,): the residuals (b1, b2 . the unit ray-to-point vector) of the point m under R (3, 3), t (3,),
    as predicted_directions makes them."""
    cdef double p[3]
    cdef double norm
    cdef int i
    for i in range(3):
        p[i] = (dot3(&R[3 * i], m) + t[i]) - o[i]
    norm = sqrt((p[0] * p[0] + p[1] * p[1]) + p[2] * p[2])
    for i in range(3):
        p[i] = p[i] / norm
    out[0], out[1] = dot3(b1, p), dot3(b2, p)


def curvature_sums(R, t, frame, points, origins, noise):
    """nonlinear.curvature_index's sums, per step s and frame, of the squared second-order part of the
    residuals, in units of 2 noise: R (2 S + 1, F, 3, 3), t (2 S + 1, F, 3) the solved poses (about the
    centroids) then each step's (plus, minus) poses; frame (N,), points (N, 3) less their centroid, origins
    (N, 3), noise (N,) (rows without noise add 0). The residuals are in the tangent bases of the directions
    the solved poses predict. Returns (S, F)."""
    cdef const double[:, :, :, ::1] r = np.ascontiguousarray(R, dtype=float)
    cdef const double[:, :, ::1] tt = np.ascontiguousarray(t, dtype=float)
    cdef const Py_ssize_t[::1] k = np.ascontiguousarray(frame, dtype=np.intp)
    cdef const double[:, ::1] m = np.ascontiguousarray(points, dtype=float)
    cdef const double[:, ::1] o = np.ascontiguousarray(origins, dtype=float)
    cdef const double[::1] sigma = np.ascontiguousarray(noise, dtype=float)
    cdef Py_ssize_t steps = (r.shape[0] - 1) // 2, n, f, s, i
    out = np.zeros((steps, r.shape[1]))
    cdef double[:, ::1] sums = out
    cdef double p[3]
    cdef double b1[3]
    cdef double b2[3]
    cdef double centre[2]
    cdef double plus[2]
    cdef double minus[2]
    cdef double second[2]
    cdef double norm
    for n in range(m.shape[0]):
        f = k[n]
        if f < 0 or f >= r.shape[1]:
            raise IndexError(f"curvature_sums: frame {f} of row {n} is not one of {r.shape[1]}")
        for i in range(3):
            p[i] = (dot3(&r[0, f, i, 0], &m[n, 0]) + tt[0, f, i]) - o[n, i]
        norm = sqrt((p[0] * p[0] + p[1] * p[1]) + p[2] * p[2])
        for i in range(3):
            p[i] = p[i] / norm
        tangent_basis(p, b1, b2)
        centre[0], centre[1] = dot3(b1, p), dot3(b2, p)
        for s in range(steps):
            moved_residual(&r[1 + 2 * s, f, 0, 0], &tt[1 + 2 * s, f, 0], &m[n, 0], &o[n, 0], b1, b2, plus)
            moved_residual(&r[2 + 2 * s, f, 0, 0], &tt[2 + 2 * s, f, 0], &m[n, 0], &o[n, 0], b1, b2, minus)
            for i in range(2):
                second[i] = ((plus[i] + minus[i]) - 2.0 * centre[i]) / (2.0 * sigma[n]) if sigma[n] > 0 else 0.0
            sums[s, f] += second[0] * second[0] + second[1] * second[1]
    return out


def block_outer_sums(blocks, sigma, block_frame, Py_ssize_t n_frames):
    """(n_frames, 6, 6) per frame the sum over its blocks of L L^T, L = blocks (B, 6, w) scaled per column by
    sigma (B, w), w 1 or 3: error_model._sum_by(np.einsum("bij,bkj->bik", L, L), block_frame (B,), n_frames)."""
    cdef const double[:, :, ::1] L = np.ascontiguousarray(blocks, dtype=float)
    cdef const double[:, ::1] s = np.ascontiguousarray(sigma, dtype=float)
    cdef const Py_ssize_t[::1] k = np.ascontiguousarray(block_frame, dtype=np.intp)
    cdef Py_ssize_t width = L.shape[2], b, f, i, m, j
    if width not in (1, 3):
        raise ValueError(f"block_outer_sums: blocks of {width} columns (1 or 3)")
    out = np.zeros((n_frames, 6, 6))
    cdef double[:, :, ::1] o = out
    cdef double scaled[6][3]
    for b in range(L.shape[0]):
        f = k[b]
        if f < 0 or f >= n_frames:
            raise IndexError(f"block_outer_sums: frame {f} of block {b} is not one of {n_frames}")
        for i in range(6):
            for j in range(width):
                scaled[i][j] = L[b, i, j] * s[b, j]
        for i in range(6):
            for m in range(6):
                if width == 3:
                    o[f, i, m] += dot3z(scaled[i], scaled[m])
                else:
                    o[f, i, m] += 0.0 + scaled[i][0] * scaled[m][0]
    return out


def noise_rows(double pixel, focal, survey_sigma, survey):
    """(N,) nonlinear.observation_noise's sqrt((pixel / focal)^2 + sum_j survey_sigma_j^2 |D_i e_j|^2 / 2),
    focal (N,), survey_sigma (N, 3), survey (N, 2, 3) D_i, as its numpy makes it."""
    cdef const double[::1] fl = np.ascontiguousarray(focal, dtype=float)
    cdef const double[:, ::1] ss = np.ascontiguousarray(survey_sigma, dtype=float)
    cdef const double[:, :, ::1] D = np.ascontiguousarray(survey, dtype=float)
    out = np.empty(fl.shape[0])
    cdef double[::1] o = out
    cdef Py_ssize_t n, j
    cdef double ratio
    cdef double term[3]
    for n in range(fl.shape[0]):
        ratio = pixel / fl[n]
        for j in range(3):
            term[j] = (ss[n, j] * ss[n, j]) * (D[n, 0, j] * D[n, 0, j] + D[n, 1, j] * D[n, 1, j])
        o[n] = sqrt(ratio * ratio + ((term[0] + term[1]) + term[2]) / 2.0)
    return out


def frame_points(R, t, frame, points):
    """(N, 3) R[frame] m + t[frame] of points m (N, 3) for poses R (F, 3, 3), t (F, 3) and rows' frames (N,),
    as np.einsum("...ij,...j->...i", R[frame], points) + t[frame] makes it."""
    cdef const double[:, :, ::1] r = np.ascontiguousarray(R, dtype=float)
    cdef const double[:, ::1] tt = np.ascontiguousarray(t, dtype=float)
    cdef const Py_ssize_t[::1] k = np.ascontiguousarray(frame, dtype=np.intp)
    cdef const double[:, ::1] m = np.ascontiguousarray(points, dtype=float)
    out = np.empty((m.shape[0], 3))
    cdef double[:, ::1] o = out
    cdef Py_ssize_t n, f, i
    for n in range(m.shape[0]):
        f = k[n]
        if f < 0 or f >= r.shape[0]:
            raise IndexError(f"frame_points: frame {f} of row {n} is not one of {r.shape[0]}")
        for i in range(3):
            o[n, i] = dot3z(&r[f, i, 0], &m[n, 0]) + tt[f, i]
    return out
