# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled loops of pose.group_normal: the blocks of a group's normal equations from its observations'
compact Jacobians, and the frames-first elimination of the frames' blocks.

In numpy these were products of per-frame stacks padded with zeros (a frame's 2 n_obs x L Jacobian,
its L x (R + 3P) coupling) and most of a group adjustment's time (issue 40); here they are loops over
the observations and frames. The arithmetic is group_normal's docstring's; its numpy elimination
(`_frames_first_numpy`) and a dense solve are the references of tests/test_group_normal.py.

The frames-first elimination takes each frame's block A = Lf Lf^T (L x L, Cholesky) and its coupling W
(L x (R + 3P), the rig and the points): W^T A^-1 W = Y^T Y with Y = Lf^-1 W, summed over the frames by
one rank-(c L) update (BLAS dsyrk) per chunk of c frames' Y stacked: a frame's rows are a few dense
vectors, where numpy's products of zero-padded stacks were most of an adjustment's time.
Matrices are C-ordered doubles.
"""

from libc.math cimport sqrt
from libc.stdlib cimport free, malloc
from libc.string cimport memcpy, memset
from scipy.linalg.cython_blas cimport dsyrk


cdef bint cholesky(double *a, int n, int ld) noexcept nogil:
    """a (n x n, row stride ld) -> its lower Cholesky factor in place (above the diagonal untouched);
    False where a is not positive definite."""
    cdef int i, j, k
    cdef double pivot, value
    for j in range(n):
        pivot = a[j * ld + j]
        for k in range(j):
            pivot -= a[j * ld + k] * a[j * ld + k]
        if not pivot > 0.0:
            return False
        pivot = sqrt(pivot)
        a[j * ld + j] = pivot
        for i in range(j + 1, n):
            value = a[i * ld + j]
            for k in range(j):
                value -= a[i * ld + k] * a[j * ld + k]
            a[i * ld + j] = value / pivot
    return True


cdef void lower_solve(const double *l, int n, int ld, double *x, int cols, int ldx) noexcept nogil:
    """x (n x cols, row stride ldx) <- l^-1 x, l lower triangular (n x n, row stride ld)."""
    cdef int i, k, c
    cdef double factor
    for i in range(n):
        for k in range(i):
            factor = l[i * ld + k]
            for c in range(cols):
                x[i * ldx + c] -= factor * x[k * ldx + c]
        factor = l[i * ld + i]
        for c in range(cols):
            x[i * ldx + c] /= factor


cdef void upper_solve(const double *l, int n, int ld, double *x, int cols, int ldx) noexcept nogil:
    """x (n x cols, row stride ldx) <- l^-T x, l lower triangular (n x n, row stride ld)."""
    cdef int i, k, c
    cdef double factor
    for i in range(n - 1, -1, -1):
        for k in range(i + 1, n):
            factor = l[k * ld + i]
            for c in range(cols):
                x[i * ldx + c] -= factor * x[k * ldx + c]
        factor = l[i * ld + i]
        for c in range(cols):
            x[i * ldx + c] /= factor


def assemble(const Py_ssize_t[::1] frame, const Py_ssize_t[::1] point, const Py_ssize_t[:, ::1] local_cols,
             const Py_ssize_t[:, ::1] rig_cols, const double[:, :, ::1] local_J, const double[:, :, ::1] rig_J,
             const double[:, :, ::1] point_J, const double[:, ::1] e, double[:, :, ::1] A, double[:, :, ::1] Wr,
             double[:, ::1] b_local, double[:, ::1] Hrr, double[:, :, ::1] Hpp, double[:, :, ::1] Hpr,
             double[:, :, ::1] Wp, double[::1] b_rig, double[:, ::1] b_point) -> None:
    """Add J^T J and J^T e of N observations (group_normal.assemble's arguments, two residuals each) to the
    blocks A (F, L, L), Wr (F, L, R), b_local (F, L), Hrr (R, R), Hpp (P, 3, 3), Hpr (P, 3, R), b_rig (R,),
    b_point (P, 3), and write Wp (N, l, 3)."""
    cdef Py_ssize_t n = local_J.shape[0], i
    cdef int l = local_J.shape[2], r = rig_J.shape[2], L = A.shape[1], R = Hrr.shape[0], a, b
    cdef const double *jl
    cdef const double *jr
    cdef const double *jp
    cdef const double *ei
    cdef const Py_ssize_t *lc
    cdef const Py_ssize_t *rc
    cdef double *A_f
    cdef double *Wr_f
    cdef double *Hp
    cdef double *Hpr_p
    cdef double value
    with nogil:
        for i in range(n):
            jl, jr, jp, ei = &local_J[i, 0, 0], &rig_J[i, 0, 0], &point_J[i, 0, 0], &e[i, 0]
            lc, rc = &local_cols[i, 0], &rig_cols[i, 0]
            A_f, Wr_f = &A[frame[i], 0, 0], &Wr[frame[i], 0, 0]
            Hp, Hpr_p = &Hpp[point[i], 0, 0], &Hpr[point[i], 0, 0]
            for a in range(l):
                for b in range(a + 1):
                    value = jl[a] * jl[b] + jl[l + a] * jl[l + b]
                    A_f[lc[a] * L + lc[b]] += value
                    if b != a:
                        A_f[lc[b] * L + lc[a]] += value
                for b in range(r):
                    Wr_f[lc[a] * R + rc[b]] += jl[a] * jr[b] + jl[l + a] * jr[r + b]
                for b in range(3):
                    Wp[i, a, b] = jl[a] * jp[b] + jl[l + a] * jp[3 + b]
                b_local[frame[i], lc[a]] += jl[a] * ei[0] + jl[l + a] * ei[1]
            for a in range(r):
                for b in range(r):
                    Hrr[rc[a], rc[b]] += jr[a] * jr[b] + jr[r + a] * jr[r + b]
                b_rig[rc[a]] += jr[a] * ei[0] + jr[r + a] * ei[1]
            for a in range(3):
                for b in range(3):
                    Hp[3 * a + b] += jp[a] * jp[b] + jp[3 + a] * jp[3 + b]
                for b in range(r):
                    Hpr_p[a * R + rc[b]] += jp[a] * jr[b] + jp[3 + a] * jr[r + b]
                b_point[point[i], a] += jp[a] * ei[0] + jp[3 + a] * ei[1]


cdef void coupling(double *W, int L, int G, const double[:, :, ::1] Wr, const double[:, :, ::1] Wp,
                   const Py_ssize_t[::1] rows, const Py_ssize_t[:, ::1] local_cols, const Py_ssize_t[::1] point,
                   Py_ssize_t f, Py_ssize_t first, Py_ssize_t last) noexcept nogil:
    """W (L x G) <- frame f's rows of the normal matrix beside A: Wr, then its observations rows[first:last]'
    Wp at their points' columns."""
    cdef int R = Wr.shape[2], l = Wp.shape[1], a, c
    cdef Py_ssize_t j, i
    memset(W, 0, L * G * sizeof(double))
    for a in range(L):
        for c in range(R):
            W[a * G + c] = Wr[f, a, c]
    for j in range(first, last):
        i = rows[j]
        for a in range(l):
            for c in range(3):
                W[local_cols[i, a] * G + R + 3 * point[i] + c] += Wp[i, a, c]


def frames_first_reduction(double[:, :, ::1] factors, const double[:, :, ::1] Wr, const double[:, :, ::1] Wp,
                           const Py_ssize_t[::1] by_frame, const Py_ssize_t[::1] frame_starts,
                           const Py_ssize_t[:, ::1] local_cols, const Py_ssize_t[::1] point,
                           const double[:, :, ::1] r_local, double[:, ::1] system, double[:, ::1] y,
                           double[:, ::1] stacked) -> int:
    """Eliminate the frames: factors (F, L, L) the frames' blocks A, replaced by their lower Cholesky
    factors Lf; system (G, G) -= sum W^T A^-1 W (its lower triangle only), y (G, k) -= sum W^T A^-1
    r_local (F, L, k), as Y^T Y and Y^T Lf^-1 r with Y = Lf^-1 W; stacked (c L, G): room for the Y of c
    frames between two dsyrk calls. Wr, Wp, by_frame, frame_starts, local_cols, point: the normal's and
    its structure's. Returns -1, or the first frame whose block is not positive definite."""
    cdef int F = factors.shape[0], L = factors.shape[1], G = system.shape[0], k = y.shape[1]
    cdef int chunk = stacked.shape[0] // L, f, i, c, kk, in_chunk = 0, failed = -1
    cdef double *z = <double *> malloc(L * k * sizeof(double) + 1)
    cdef double *a
    cdef double *Y
    cdef double factor
    cdef char uplo = b'U', trans = b'N'
    cdef int rank, ld = G
    cdef double minus_one = -1.0, one = 1.0
    if z == NULL:
        raise MemoryError()
    with nogil:
        for f in range(F):
            a = &factors[f, 0, 0]
            if not cholesky(a, L, L):
                failed = f
                break
            Y = &stacked[in_chunk * L, 0]
            coupling(Y, L, G, Wr, Wp, by_frame, local_cols, point, f, frame_starts[f], frame_starts[f + 1])
            lower_solve(a, L, L, Y, G, G)
            memcpy(z, &r_local[f, 0, 0], L * k * sizeof(double))
            lower_solve(a, L, L, z, k, k)
            for i in range(L):
                for kk in range(k):
                    factor = z[i * k + kk]
                    for c in range(G):
                        y[c, kk] -= Y[i * G + c] * factor
            in_chunk += 1
            if in_chunk == chunk or f == F - 1:  # system -= Y^T Y: in Fortran's order, Y^T is G x (c L)
                rank = in_chunk * L
                dsyrk(&uplo, &trans, &ld, &rank, &minus_one, &stacked[0, 0], &ld, &one, &system[0, 0], &ld)
                in_chunk = 0
    free(z)
    return failed


def frames_first_back(const double[:, :, ::1] factors, const double[:, :, ::1] Wr, const double[:, :, ::1] Wp,
                      const Py_ssize_t[::1] by_frame, const Py_ssize_t[::1] frame_starts,
                      const Py_ssize_t[:, ::1] local_cols, const Py_ssize_t[::1] point,
                      const double[:, :, ::1] r_local, const double[:, ::1] x_global,
                      double[:, :, ::1] x_local) -> None:
    """x_local (F, L, k) <- A^-1 (r_local - W x_global) per frame, A's Cholesky factors from
    `frames_first_reduction`; x_global (G, k) the rig's and the points' solution."""
    cdef int F = factors.shape[0], L = factors.shape[1], k = x_global.shape[1], R = Wr.shape[2], l = Wp.shape[1]
    cdef int f, row, c, kk
    cdef Py_ssize_t j, obs, p
    cdef double value
    cdef double *x
    cdef const double *a
    with nogil:
        for f in range(F):
            a = &factors[f, 0, 0]
            x = &x_local[f, 0, 0]
            for row in range(L):
                for kk in range(k):
                    value = r_local[f, row, kk]
                    for c in range(R):
                        value -= Wr[f, row, c] * x_global[c, kk]
                    x[row * k + kk] = value
            for j in range(frame_starts[f], frame_starts[f + 1]):
                obs = by_frame[j]
                p = R + 3 * point[obs]
                for row in range(l):
                    for kk in range(k):
                        value = 0.0
                        for c in range(3):
                            value += Wp[obs, row, c] * x_global[p + c, kk]
                        x[local_cols[obs, row] * k + kk] -= value
            lower_solve(a, L, L, x, k, k)
            upper_solve(a, L, L, x, k, k)


cdef inline void cross_rows(const double *a, const double *b, double *out) noexcept nogil:
    """out (3,) = a x b."""
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]


def mounting_jacobians(const Py_ssize_t[::1] frame, const Py_ssize_t[::1] image, const Py_ssize_t[::1] slot,
                       const Py_ssize_t[::1] focal_slot, const double[:, :, ::1] J_e, const double[:, ::1] J_focal,
                       const double[:, ::1] x, const double[:, ::1] q, const double[:, :, ::1] cam_from_rig,
                       const double[:, :, ::1] delta_turn, const double[:, :, ::1] jitter_turn,
                       const double[:, :, ::1] R, double[:, :, ::1] local_J, double[:, :, ::1] global_J) -> None:
    """pose.mounting's compact Jacobians of its N observations (`mounting._jacobians_numpy`, the reference):
    local_J (N, 2, l) d e / d (the frame's omega, dt, then with l = 9 its camera's jitter), global_J
    (N, 2, g) d e / d (the camera's delta, with g = 7 its focal change, then the point); zeros for delta
    and jitter where slot < 0 (the reference camera), for the focal change where focal_slot < 0. J_e
    (N, 2, 3), J_focal (N, 2), x, q (N, 3), image (N,), the turns (F C, 3, 3), R (F, 3, 3): `_Forward`'s
    and the state's."""
    cdef Py_ssize_t n = J_e.shape[0], i, f, im
    cdef int l = local_J.shape[2], g = global_J.shape[2], k, a, b
    cdef double d_rig[3]
    cdef double e_cross_x[3]
    cdef double value
    with nogil:
        for i in range(n):
            f, im = frame[i], image[i]
            for k in range(2):
                for a in range(3):
                    value = 0.0
                    for b in range(3):
                        value += J_e[i, k, b] * cam_from_rig[im, b, a]
                    d_rig[a] = value
                cross_rows(&q[i, 0], d_rig, &local_J[i, k, 0])
                for a in range(3):
                    local_J[i, k, 3 + a] = d_rig[a]
                    value = 0.0
                    for b in range(3):
                        value += d_rig[b] * R[f, b, a]
                    global_J[i, k, g - 3 + a] = value
                cross_rows(&J_e[i, k, 0], &x[i, 0], e_cross_x)
                for a in range(3):
                    if slot[i] < 0:
                        global_J[i, k, a] = 0.0
                        if l > 6:
                            local_J[i, k, 6 + a] = 0.0
                        continue
                    value = 0.0
                    for b in range(3):
                        value -= e_cross_x[b] * delta_turn[im, b, a]
                    global_J[i, k, a] = value
                    if l > 6:
                        value = 0.0
                        for b in range(3):
                            value -= e_cross_x[b] * jitter_turn[im, b, a]
                        local_J[i, k, 6 + a] = value
                if g > 6:
                    global_J[i, k, 3] = J_focal[i, k] if focal_slot[i] >= 0 else 0.0


def scaled_couplings(const double[:, :, ::1] Wp, const Py_ssize_t[::1] frame, const Py_ssize_t[::1] point,
                     const Py_ssize_t[:, ::1] local_cols, const double[:, ::1] local_scale,
                     const double[:, ::1] point_scale, double[:, :, ::1] out) -> None:
    """out (N, l, 3) <- Wp (N, l, 3) scaled by its rows' local_scale (F, L) and its point's point_scale (P, 3)."""
    cdef Py_ssize_t n = Wp.shape[0], i
    cdef int l = Wp.shape[1], a, c
    cdef double row
    with nogil:
        for i in range(n):
            for a in range(l):
                row = local_scale[frame[i], local_cols[i, a]]
                for c in range(3):
                    out[i, a, c] = Wp[i, a, c] * row * point_scale[point[i], c]


def mounting_points_in_cameras(const Py_ssize_t[::1] frame, const Py_ssize_t[::1] point,
                               const Py_ssize_t[::1] image, const double[:, :, ::1] R, const double[:, ::1] t,
                               const double[:, ::1] points, const double[:, :, ::1] cam_from_rig,
                               const double[:, ::1] cam_t, double[:, ::1] x_rig, double[:, ::1] x) -> None:
    """pose.mounting's observations' points in the rig, x_rig (N, 3) = R_f M_p + t_f, and in their
    (jittered) camera, x (N, 3) = cam_from_rig_image x_rig + cam_t_image: R (F, 3, 3), t (F, 3), points
    (P, 3), cam_from_rig (F C, 3, 3), cam_t (F C, 3)."""
    cdef Py_ssize_t n = frame.shape[0], i, f, p, im
    cdef int a, b
    cdef double value
    with nogil:
        for i in range(n):
            f, p, im = frame[i], point[i], image[i]
            for a in range(3):
                value = R[f, a, 0] * points[p, 0] + R[f, a, 1] * points[p, 1] + R[f, a, 2] * points[p, 2]
                x_rig[i, a] = value + t[f, a]
            for a in range(3):
                value = cam_from_rig[im, a, 0] * x_rig[i, 0] + cam_from_rig[im, a, 1] * x_rig[i, 1] \
                    + cam_from_rig[im, a, 2] * x_rig[i, 2]
                x[i, a] = value + cam_t[im, a]


def add_row_products(const double[:, :, ::1] J, const Py_ssize_t[:, ::1] index, const double[:, ::1] M,
                     double[:, :, ::1] out) -> None:
    """out (N, k, m) += J[i] @ M[index[i]] per observation i: J (N, k, j), index (N, j) rows of M (n, m)."""
    cdef Py_ssize_t n = J.shape[0], i
    cdef int rows = J.shape[1], width = J.shape[2], m = M.shape[1], k, a, c
    cdef double factor
    cdef const double *M_row
    with nogil:
        for i in range(n):
            for a in range(width):
                M_row = &M[index[i, a], 0]
                for k in range(rows):
                    factor = J[i, k, a]
                    for c in range(m):
                        out[i, k, c] += factor * M_row[c]
