# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled loops of pose.group_normal: the blocks of a group's normal equations from its observations'
compact Jacobians, and the frames-first elimination of the frames' blocks.

In numpy these were products of per-frame stacks padded with zeros (a frame's 2 n_obs x L Jacobian,
its L x (R + 3P) coupling) and most of a group adjustment's time (issue 40); here they are loops over
the observations and frames. The arithmetic is group_normal's docstring's; its numpy elimination
(`_frames_first_numpy`) and a dense solve are the references of tests/test_group_normal.py. pose.mounting's
model and Jacobians are here too (`mounting_assemble` forms each observation's Jacobian and adds it to the
blocks at once: an iteration's Jacobians are never stored).

The frames-first elimination factorises each frame's block as A = M M^T, M = [[Ls, G], [0, Lb]]: its
unknowns are n_shared ones every observation of the frame touches (the pose), then blocks of `width` that
only some touch (a camera's jitter), not tied to each other in A (`local_layout`; otherwise one dense
Cholesky factor, n_shared = L); Lb the blocks' Cholesky factors, G = A_sb Lb^-T, Ls that of A_ss - G G^T.
The frame's coupling W (L x (R + 3P), the rig and the points) reduces to Y = M^-1 W, and W^T A^-1 W =
Y^T Y: the shared rows of Y are dense, summed by one dsyrk per chunk of frames; a block's rows are zero
beyond a few columns (its camera's rig unknowns and points), kept over the frames whose block has the
same columns and summed by one small dsyrk on those. In numpy, products of zero-padded stacks were most
of a group adjustment's time (issue 40). Matrices are C-ordered doubles.
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


cdef enum:
    MAX_ROW = 32  # an observation's Jacobian columns: local, rig and point


cdef inline void add_observation(const double *j, int w, int l, int r, const int *lc, const int *rc,
                                 const double *ei, double *A_f, double *Wr_f, double *b_f, int L, int R,
                                 double *Hrr, double *b_rig, double *Hp, double *Hpr_p, double *b_p,
                                 double *Wp_i) noexcept nogil:
    """Add one observation's J^T J and J^T e to its blocks (`assemble`'s): j its two rows (row stride w) of l
    local, r rig and 3 point columns, at local columns lc and rig columns rc; A_f (L x L, its lower triangle),
    Wr_f (L x R), b_f (L,) its frame's, Hrr (R x R), b_rig (R,), Hp (3 x 3), Hpr_p (3 x R), b_p (3,) its
    point's; Wp_i (l x 3) written. The row's factors are held in locals: a store into a block cannot change
    them, so they are not read again after each."""
    cdef int a, b, row, col
    cdef double j0, j1, e0 = ei[0], e1 = ei[1]
    cdef const double *jr = j + l
    cdef const double *jp = j + l + r
    for a in range(l):
        j0, j1, row = j[a], j[w + a], <int> lc[a]
        for b in range(a + 1):  # A's lower triangle, mirrored below
            col = <int> lc[b]
            A_f[max(row, col) * L + min(row, col)] += j0 * j[b] + j1 * j[w + b]
        for b in range(r):
            Wr_f[row * R + rc[b]] += j0 * jr[b] + j1 * jr[w + b]
        for b in range(3):
            Wp_i[3 * a + b] = j0 * jp[b] + j1 * jp[w + b]
        b_f[row] += j0 * e0 + j1 * e1
    for a in range(r):
        j0, j1, row = jr[a], jr[w + a], <int> rc[a]
        for b in range(r):
            Hrr[row * R + rc[b]] += j0 * jr[b] + j1 * jr[w + b]
        b_rig[row] += j0 * e0 + j1 * e1
    for a in range(3):
        j0, j1 = jp[a], jp[w + a]
        for b in range(3):
            Hp[3 * a + b] += j0 * jp[b] + j1 * jp[w + b]
        for b in range(r):
            Hpr_p[a * R + rc[b]] += j0 * jr[b] + j1 * jr[w + b]
        b_p[a] += j0 * e0 + j1 * e1


cdef void mirrored(double[:, :, ::1] A) noexcept nogil:
    """Each block of A (F, L, L) made symmetric from its lower triangle."""
    cdef int L = A.shape[1], a, b
    cdef Py_ssize_t f
    cdef double *A_f
    for f in range(A.shape[0]):
        A_f = &A[f, 0, 0]
        for a in range(L):
            for b in range(a):
                A_f[b * L + a] = A_f[a * L + b]


def assemble(const Py_ssize_t[::1] frame, const Py_ssize_t[::1] point, const int[:, ::1] local_cols,
             const int[:, ::1] rig_cols, const double[:, :, ::1] local_J, const double[:, :, ::1] rig_J,
             const double[:, :, ::1] point_J, const double[:, ::1] e, double[:, :, ::1] A, double[:, :, ::1] Wr,
             double[:, ::1] b_local, double[:, ::1] Hrr, double[:, :, ::1] Hpp, double[:, :, ::1] Hpr,
             double[:, :, ::1] Wp, double[::1] b_rig, double[:, ::1] b_point) -> None:
    """Add J^T J and J^T e of N observations (group_normal.assemble's arguments, two residuals each) to the
    blocks A (F, L, L), Wr (F, L, R), b_local (F, L), Hrr (R, R), Hpp (P, 3, 3), Hpr (P, 3, R), b_rig (R,),
    b_point (P, 3), and write Wp (N, l, 3)."""
    cdef Py_ssize_t n = local_J.shape[0], i
    cdef int l = local_J.shape[2], r = rig_J.shape[2], w = l + r + 3, k, a
    cdef double j[2 * MAX_ROW]
    if w > MAX_ROW:
        raise ValueError(f"at most {MAX_ROW} columns per observation, got {w}")
    with nogil:
        for i in range(n):
            for k in range(2):
                for a in range(l):
                    j[k * w + a] = local_J[i, k, a]
                for a in range(r):
                    j[k * w + l + a] = rig_J[i, k, a]
                for a in range(3):
                    j[k * w + l + r + a] = point_J[i, k, a]
            add_observation(j, w, l, r, &local_cols[i, 0], &rig_cols[i, 0], &e[i, 0], &A[frame[i], 0, 0],
                            &Wr[frame[i], 0, 0], &b_local[frame[i], 0], A.shape[1], Hrr.shape[0], &Hrr[0, 0],
                            &b_rig[0], &Hpp[point[i], 0, 0], &Hpr[point[i], 0, 0], &b_point[point[i], 0],
                            &Wp[i, 0, 0])
        mirrored(A)


cdef void coupling(double *W, int L, int G, const double[:, :, ::1] Wr, const double[:, :, ::1] Wp,
                   const Py_ssize_t[::1] rows, const int[:, ::1] local_cols, const Py_ssize_t[::1] point,
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


def local_layout(const int[:, ::1] local_cols, const double[:, :, ::1] A) -> tuple:
    """(n_shared, width) of the frames' blocks (module docstring): the first n_shared local columns (at
    least 1) every observation touches in order, then blocks of `width` each observation touches one of
    whole, not tied to each other in A (F, L, L); (L, 0) where the blocks are not so (a dense factor)."""
    cdef Py_ssize_t n = local_cols.shape[0], i
    cdef int l = local_cols.shape[1], L = A.shape[1], n_shared = l, width, a
    with nogil:
        for i in range(n):
            for a in range(n_shared):
                if local_cols[i, a] != a:
                    n_shared = a
                    break
    width = l - n_shared
    if n_shared == 0 or width == 0 or (L - n_shared) % width or not blocks_apart(local_cols, A, n_shared, width):
        return L, 0
    return n_shared, width


cdef bint blocks_apart(const int[:, ::1] local_cols, const double[:, :, ::1] A, int n_shared,
                       int width) noexcept nogil:
    """Whether every observation's columns after the n_shared are one block of `width` whole and A (F, L,
    L) ties no two blocks."""
    cdef Py_ssize_t i, f
    cdef int L = A.shape[1], a, b, start
    for i in range(local_cols.shape[0]):
        start = local_cols[i, n_shared]
        if (start - n_shared) % width:
            return False
        for a in range(width):
            if local_cols[i, n_shared + a] != start + a:
                return False
    for f in range(A.shape[0]):
        for a in range(n_shared, L):
            for b in range(n_shared, L):
                if (a - n_shared) // width != (b - n_shared) // width and A[f, a, b] != 0.0:
                    return False
    return True


cdef bint factorised(double *a, int L, int n_shared, int width) noexcept nogil:
    """A frame's block a (L x L) -> its factors M (module docstring) in place: Lb on the blocks' diagonal,
    G in the shared rows' block columns, Ls in the shared rows' first n_shared; False where a is not
    positive definite."""
    cdef int n_blocks = (L - n_shared) // width if width else 0, b, i, j, t, j0
    for b in range(n_blocks):
        j0 = n_shared + b * width
        if not cholesky(a + j0 * L + j0, width, L):
            return False
        for i in range(n_shared):  # G's row i: Lb g = A_sb's row i
            for t in range(width):
                for j in range(t):
                    a[i * L + j0 + t] -= a[(j0 + t) * L + j0 + j] * a[i * L + j0 + j]
                a[i * L + j0 + t] /= a[(j0 + t) * L + j0 + t]
    for i in range(n_shared):
        for j in range(i + 1):
            for t in range(n_shared, L):
                a[i * L + j] -= a[i * L + t] * a[j * L + t]
    return cholesky(a, n_shared, L)


cdef void syrk_rows(double *rows, int n_rows, int n_cols, double *out) noexcept nogil:
    """out (n_cols x n_cols) <- rows^T rows of rows (n_rows x n_cols, C order), its lower triangle (C order)."""
    cdef char uplo = b'U', trans = b'N'
    cdef double one = 1.0, zero = 0.0
    dsyrk(&uplo, &trans, &n_cols, &n_rows, &one, rows, &n_cols, &zero, out, &n_cols)


cdef struct BlockStack:
    # one block's rows of Y = M^-1 W over the frames whose block has the same columns, kept for one dsyrk
    int n_rows
    int n_cols
    int *cols
    double *rows


cdef void flushed(BlockStack *stack, double[:, ::1] system, double *product) noexcept nogil:
    """system's lower triangle -= the stack's rows^T rows at its columns; the stack emptied."""
    cdef int a, b, ra, rb
    if stack.n_rows:
        syrk_rows(stack.rows, stack.n_rows, stack.n_cols, product)
        for a in range(stack.n_cols):
            for b in range(a + 1):
                ra, rb = stack.cols[a], stack.cols[b]
                if ra >= rb:
                    system[ra, rb] -= product[a * stack.n_cols + b]
                else:
                    system[rb, ra] -= product[a * stack.n_cols + b]
    stack.n_rows = 0


def frames_first_reduction(double[:, :, ::1] factors, const double[:, :, ::1] Wr, const double[:, :, ::1] Wp,
                           const Py_ssize_t[::1] by_frame, const Py_ssize_t[::1] frame_starts,
                           const int[:, ::1] local_cols, const Py_ssize_t[::1] point, int n_shared,
                           int width, const double[:, :, ::1] r_local, double[:, ::1] system, double[:, ::1] y,
                           double[:, ::1] stacked) -> int:
    """Eliminate the frames: factors (F, L, L) the frames' blocks A, replaced by their factors M (module
    docstring, layout (n_shared, width) from `local_layout`); system (G, G) -= sum W^T A^-1 W (its lower
    triangle only), y (G, k) -= sum W^T A^-1 r_local (F, L, k), as Y^T Y and Y^T M^-1 r with Y = M^-1 W;
    stacked (c n_shared, G): room for the shared rows of Y of c frames between two dsyrk calls. Wr, Wp,
    by_frame, frame_starts, local_cols, point: the normal's and its structure's. Returns -1, or the first
    frame whose block is not positive definite."""
    cdef int F = factors.shape[0], L = factors.shape[1], G = system.shape[0], k = y.shape[1], R = Wr.shape[2]
    cdef int n_blocks = (L - n_shared) // width if width else 0, chunk = stacked.shape[0] // n_shared
    cdef int capacity = width * chunk, f, b, j0, t, i, c, kk, n_cols, in_chunk = 0, failed = -1, same, q
    cdef Py_ssize_t j, obs
    cdef double value
    cdef double *W = <double *> malloc(L * G * sizeof(double))
    cdef double *z = <double *> malloc(L * k * sizeof(double) + 1)
    cdef int most = 0, block_cols  # a block's columns: at most the rig's and 3 per observation of a frame
    for f in range(F):
        most = max(most, <int> (frame_starts[f + 1] - frame_starts[f]))
    block_cols = min(G, R + 3 * most)
    cdef double *product = <double *> malloc(block_cols * block_cols * sizeof(double))
    cdef int *cols = <int *> malloc(G * sizeof(int))
    cdef int *seen = <int *> malloc(G * sizeof(int))
    cdef BlockStack *stacks = <BlockStack *> malloc(n_blocks * sizeof(BlockStack) + 1)
    cdef BlockStack *stack
    cdef double *a
    cdef double *Ys
    cdef double *Yb
    cdef char uplo = b'U', trans = b'N'
    cdef int rank, ld = G
    cdef double minus_one = -1.0, one = 1.0
    if W == NULL or z == NULL or product == NULL or cols == NULL or seen == NULL or stacks == NULL:
        free(W); free(z); free(product); free(cols); free(seen); free(stacks)
        raise MemoryError()
    for b in range(n_blocks):
        stacks[b].n_rows, stacks[b].n_cols = 0, 0
        stacks[b].cols = <int *> malloc(G * sizeof(int))
        stacks[b].rows = <double *> malloc(capacity * block_cols * sizeof(double))
    with nogil:
        for c in range(G):
            seen[c] = -1
        for f in range(F):
            a = &factors[f, 0, 0]
            if not factorised(a, L, n_shared, width):
                failed = f
                break
            coupling(W, L, G, Wr, Wp, by_frame, local_cols, point, f, frame_starts[f], frame_starts[f + 1])
            memcpy(z, &r_local[f, 0, 0], L * k * sizeof(double))
            Ys = &stacked[in_chunk * n_shared, 0]
            memcpy(Ys, W, n_shared * G * sizeof(double))
            for b in range(n_blocks):
                j0, stack = n_shared + b * width, &stacks[b]
                n_cols = 0  # the columns where the block's rows of W are not zero
                for c in range(R):
                    for t in range(width):
                        if W[(j0 + t) * G + c] != 0.0:
                            cols[n_cols] = c
                            n_cols += 1
                            break
                for j in range(frame_starts[f], frame_starts[f + 1]):
                    obs = by_frame[j]
                    q = R + 3 * point[obs]
                    if local_cols[obs, n_shared] != j0 or seen[q] == f * n_blocks + b:
                        continue
                    seen[q] = f * n_blocks + b
                    for t in range(width):
                        if W[(j0 + t) * G + q] != 0.0 or W[(j0 + t) * G + q + 1] != 0.0 \
                                or W[(j0 + t) * G + q + 2] != 0.0:
                            for c in range(3):
                                cols[n_cols] = q + c
                                n_cols += 1
                            break
                lower_solve(a + j0 * L + j0, width, L, z + j0 * k, k, k)  # zb = Lb^-1 r_b
                for i in range(n_shared):  # r_s - G zb
                    for t in range(width):
                        for kk in range(k):
                            z[i * k + kk] -= a[i * L + j0 + t] * z[(j0 + t) * k + kk]
                if n_cols == 0:
                    continue
                same = stack.n_cols == n_cols and stack.n_rows + width <= capacity
                for c in range(n_cols):
                    if not same:
                        break
                    same = stack.cols[c] == cols[c]
                if not same:
                    flushed(stack, system, product)
                    stack.n_cols = n_cols
                    memcpy(stack.cols, cols, n_cols * sizeof(int))
                Yb = stack.rows + stack.n_rows * n_cols
                stack.n_rows += width
                for t in range(width):
                    for c in range(n_cols):
                        Yb[t * n_cols + c] = W[(j0 + t) * G + cols[c]]
                lower_solve(a + j0 * L + j0, width, L, Yb, n_cols, n_cols)  # Yb = Lb^-1 Wb
                for c in range(n_cols):
                    for kk in range(k):
                        value = 0.0
                        for t in range(width):
                            value += Yb[t * n_cols + c] * z[(j0 + t) * k + kk]
                        y[cols[c], kk] -= value
                for i in range(n_shared):  # Ws - G Yb: an entry's subtractions in t's order, in a register
                    for c in range(n_cols):
                        value = Ys[i * G + cols[c]]
                        for t in range(width):
                            value -= a[i * L + j0 + t] * Yb[t * n_cols + c]
                        Ys[i * G + cols[c]] = value
            lower_solve(a, n_shared, L, Ys, G, G)  # Ys = Ls^-1 (Ws - G Yb)
            lower_solve(a, n_shared, L, z, k, k)
            for i in range(n_shared):
                for kk in range(k):
                    value = z[i * k + kk]
                    for c in range(G):
                        y[c, kk] -= Ys[i * G + c] * value
            in_chunk += 1
            if in_chunk == chunk or f == F - 1:  # system -= Ys^T Ys: in Fortran's order, Ys^T is G x (c n_shared)
                rank = in_chunk * n_shared
                dsyrk(&uplo, &trans, &ld, &rank, &minus_one, &stacked[0, 0], &ld, &one, &system[0, 0], &ld)
                in_chunk = 0
        for b in range(n_blocks):
            if failed < 0:
                flushed(&stacks[b], system, product)
    for b in range(n_blocks):
        free(stacks[b].cols); free(stacks[b].rows)
    free(W); free(z); free(product); free(cols); free(seen); free(stacks)
    return failed


def frames_first_back(const double[:, :, ::1] factors, const double[:, :, ::1] Wr, const double[:, :, ::1] Wp,
                      const Py_ssize_t[::1] by_frame, const Py_ssize_t[::1] frame_starts,
                      const int[:, ::1] local_cols, const Py_ssize_t[::1] point, int n_shared, int width,
                      const double[:, :, ::1] r_local, const double[:, ::1] x_global,
                      double[:, :, ::1] x_local) -> None:
    """x_local (F, L, k) <- A^-1 (r_local - W x_global) per frame, A's factors M from
    `frames_first_reduction`; x_global (G, k) the rig's and the points' solution."""
    cdef int F = factors.shape[0], L = factors.shape[1], k = x_global.shape[1], R = Wr.shape[2], l = Wp.shape[1]
    cdef int n_blocks = (L - n_shared) // width if width else 0, f, b, j0, row, c, kk, i, t
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
            for b in range(n_blocks):  # v = M^-1 u
                j0 = n_shared + b * width
                lower_solve(a + j0 * L + j0, width, L, x + j0 * k, k, k)
                for i in range(n_shared):
                    for t in range(width):
                        for kk in range(k):
                            x[i * k + kk] -= a[i * L + j0 + t] * x[(j0 + t) * k + kk]
            lower_solve(a, n_shared, L, x, k, k)
            upper_solve(a, n_shared, L, x, k, k)  # x = M^-T v
            for b in range(n_blocks):
                j0 = n_shared + b * width
                for t in range(width):
                    for kk in range(k):
                        value = 0.0
                        for i in range(n_shared):
                            value += a[i * L + j0 + t] * x[i * k + kk]
                        x[(j0 + t) * k + kk] -= value
                upper_solve(a + j0 * L + j0, width, L, x + j0 * k, k, k)


cdef inline void cross_rows(const double *a, const double *b, double *out) noexcept nogil:
    """out (3,) = a x b."""
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]


cdef inline void observation_jacobian(Py_ssize_t i, const Py_ssize_t[::1] frame, const Py_ssize_t[::1] image,
                                      const Py_ssize_t[::1] slot, const Py_ssize_t[::1] focal_slot,
                                      const double[:, :, ::1] J_e, const double[:, ::1] J_focal,
                                      const double[:, ::1] x, const double[:, ::1] q,
                                      const double[:, :, ::1] cam_from_rig, const double[:, :, ::1] delta_turn,
                                      const double[:, :, ::1] jitter_turn, const double[:, :, ::1] R, int l, int g,
                                      double *local_row, double *global_row, int stride) noexcept nogil:
    """Observation i's two rows of `mounting_jacobians`' local_J (l columns) and global_J (g) into local_row
    and global_row (row stride `stride`)."""
    cdef Py_ssize_t f = frame[i], im = image[i]
    cdef int k, a, b
    cdef double d_rig[3]
    cdef double e_cross_x[3]
    cdef double value
    cdef double *lr
    cdef double *gr
    for k in range(2):
        lr, gr = local_row + k * stride, global_row + k * stride
        for a in range(3):
            value = 0.0
            for b in range(3):
                value += J_e[i, k, b] * cam_from_rig[im, b, a]
            d_rig[a] = value
        cross_rows(&q[i, 0], d_rig, lr)
        for a in range(3):
            lr[3 + a] = d_rig[a]
            value = 0.0
            for b in range(3):
                value += d_rig[b] * R[f, b, a]
            gr[g - 3 + a] = value
        cross_rows(&J_e[i, k, 0], &x[i, 0], e_cross_x)
        for a in range(3):
            if slot[i] < 0:
                gr[a] = 0.0
                if l > 6:
                    lr[6 + a] = 0.0
                continue
            value = 0.0
            for b in range(3):
                value -= e_cross_x[b] * delta_turn[im, b, a]
            gr[a] = value
            if l > 6:
                value = 0.0
                for b in range(3):
                    value -= e_cross_x[b] * jitter_turn[im, b, a]
                lr[6 + a] = value
        if g > 6:
            gr[3] = J_focal[i, k] if focal_slot[i] >= 0 else 0.0


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
    cdef Py_ssize_t n = J_e.shape[0], i
    cdef int l = local_J.shape[2], g = global_J.shape[2]
    cdef double rows[2 * MAX_ROW]
    with nogil:
        for i in range(n):  # each row pair through a buffer: local_J and global_J have strides of their own
            observation_jacobian(i, frame, image, slot, focal_slot, J_e, J_focal, x, q, cam_from_rig, delta_turn,
                                 jitter_turn, R, l, g, rows, rows + l, l + g)
            memcpy(&local_J[i, 0, 0], rows, l * sizeof(double))
            memcpy(&global_J[i, 0, 0], rows + l, g * sizeof(double))
            memcpy(&local_J[i, 1, 0], rows + l + g, l * sizeof(double))
            memcpy(&global_J[i, 1, 0], rows + 2 * l + g, g * sizeof(double))


def mounting_assemble(const Py_ssize_t[::1] frame, const Py_ssize_t[::1] image, const Py_ssize_t[::1] slot,
                      const Py_ssize_t[::1] focal_slot, const double[:, :, ::1] J_e, const double[:, ::1] J_focal,
                      const double[:, ::1] x, const double[:, ::1] q, const double[:, :, ::1] cam_from_rig,
                      const double[:, :, ::1] delta_turn, const double[:, :, ::1] jitter_turn,
                      const double[:, :, ::1] R, const Py_ssize_t[::1] point, const int[:, ::1] local_cols,
                      const int[:, ::1] rig_cols, const double[:, ::1] e, double[:, :, ::1] A,
                      double[:, :, ::1] Wr, double[:, ::1] b_local, double[:, ::1] Hrr, double[:, :, ::1] Hpp,
                      double[:, :, ::1] Hpr, double[:, :, ::1] Wp, double[::1] b_rig, double[:, ::1] b_point) -> None:
    """`assemble` of pose.mounting's Jacobians (`mounting_jacobians`' arguments, then assemble's but the
    Jacobians), each observation's formed in a buffer and added to the blocks at once."""
    cdef Py_ssize_t n = J_e.shape[0], i
    cdef int l = local_cols.shape[1], r = rig_cols.shape[1], w = l + r + 3
    cdef double j[2 * MAX_ROW]
    if w > MAX_ROW:
        raise ValueError(f"at most {MAX_ROW} columns per observation, got {w}")
    with nogil:
        for i in range(n):
            observation_jacobian(i, frame, image, slot, focal_slot, J_e, J_focal, x, q, cam_from_rig, delta_turn,
                                 jitter_turn, R, l, r + 3, j, j + l, w)
            add_observation(j, w, l, r, &local_cols[i, 0], &rig_cols[i, 0], &e[i, 0], &A[frame[i], 0, 0],
                            &Wr[frame[i], 0, 0], &b_local[frame[i], 0], A.shape[1], Hrr.shape[0], &Hrr[0, 0],
                            &b_rig[0], &Hpp[point[i], 0, 0], &Hpr[point[i], 0, 0], &b_point[point[i], 0],
                            &Wp[i, 0, 0])
        mirrored(A)


def mounting_points_in_cameras(const Py_ssize_t[::1] frame, const Py_ssize_t[::1] point,
                               const Py_ssize_t[::1] image, const double[:, :, ::1] R, const double[:, ::1] t,
                               const double[:, ::1] points, const double[:, :, ::1] cam_from_rig,
                               const double[:, ::1] cam_t, double[:, ::1] x_rig, double[:, ::1] x,
                               const double[:, ::1] centre=None, double[:, ::1] q=None) -> None:
    """pose.mounting's observations' points in the rig, x_rig (N, 3) = R_f M_p + t_f, and in their
    (jittered) camera, x (N, 3) = cam_from_rig_image x_rig + cam_t_image: R (F, 3, 3), t (F, 3), points
    (P, 3), cam_from_rig (F C, 3, 3), cam_t (F C, 3); given their frames' centres (F, 3), also q (N, 3) =
    x_rig - centre_f."""
    cdef Py_ssize_t n = frame.shape[0], i, f, p, im
    cdef int a, b
    cdef double value
    cdef bint with_q = q is not None
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
            if with_q:
                for a in range(3):
                    q[i, a] = x_rig[i, a] - centre[f, a]


def mounting_transposed_products(const Py_ssize_t[::1] rows, const Py_ssize_t[::1] frame,
                                 const Py_ssize_t[::1] image, const Py_ssize_t[::1] slot,
                                 const Py_ssize_t[::1] focal_slot, const double[:, :, ::1] J_e,
                                 const double[:, ::1] J_focal, const double[:, ::1] x, const double[:, ::1] q,
                                 const double[:, :, ::1] cam_from_rig, const double[:, :, ::1] delta_turn,
                                 const double[:, :, ::1] jitter_turn, const double[:, :, ::1] R,
                                 const Py_ssize_t[::1] point, const int[:, ::1] local_cols,
                                 const int[:, ::1] rig_cols, int L, int n_rig, const double[:, :, ::1] P,
                                 double[:, ::1] B) -> None:
    """B (F L + n_rig + 3P', m) += J_i^T P[j] for the observations i = rows[j] (n,): J_i the whole Jacobian's two
    rows of observation i (`mounting_jacobians`' arguments; formed here, at its frame's local columns, its rig
    columns and its point's), P (n, 2, m)."""
    cdef Py_ssize_t n = rows.shape[0], first = R.shape[0] * L, j, i, target  # R (F, 3, 3): the frames
    cdef int l = local_cols.shape[1], r = rig_cols.shape[1], w = l + r + 3, m = P.shape[2], a, c
    cdef double row[2 * MAX_ROW]
    cdef double j0, j1
    cdef double *out
    cdef const double *p
    if w > MAX_ROW:
        raise ValueError(f"at most {MAX_ROW} columns per observation, got {w}")
    with nogil:
        for j in range(n):
            i = rows[j]
            observation_jacobian(i, frame, image, slot, focal_slot, J_e, J_focal, x, q, cam_from_rig, delta_turn,
                                 jitter_turn, R, l, r + 3, row, row + l, w)
            p = &P[j, 0, 0]
            for a in range(w):
                if a < l:
                    target = frame[i] * L + local_cols[i, a]
                elif a < l + r:
                    target = first + rig_cols[i, a - l]
                else:
                    target = first + n_rig + 3 * point[i] + a - l - r
                j0, j1, out = row[a], row[w + a], &B[target, 0]
                for c in range(m):
                    out[c] += j0 * p[c] + j1 * p[m + c]


def radial1_residuals(const double[:, ::1] x, const Py_ssize_t[::1] camera, const double[:, ::1] lens,
                      const double[:, ::1] uv, const double[::1] weight, double[:, ::1] e, double[:, :, ::1] J_e,
                      double[:, ::1] J_focal, bint jacobians) -> None:
    """pose.mounting's whitened residuals of points x (N, 3) in their cameras by the radial1 model
    (camera.project_unmasked, its reference): e (N, 2) = (pixel - uv) weight; with `jacobians`, J_e (N, 2,
    3) d e / d x and J_focal (N, 2) d e / d (the relative focal change). lens (C, 7) per camera in rig order:
    fx, fy (with the focal change), cx, cy, d, and fx, fy (without)."""
    cdef Py_ssize_t n = x.shape[0], i
    cdef double xn, yn, inverse_z, r2, s, fx, fy, d, w, j00, j01, j10, j11
    cdef const double *c
    with nogil:
        for i in range(n):
            c = &lens[camera[i], 0]
            fx, fy, d, w = c[0], c[1], c[4], weight[i]
            xn, yn = x[i, 0] / x[i, 2], x[i, 1] / x[i, 2]
            r2 = xn * xn + yn * yn
            s = 1.0 + d * r2
            e[i, 0] = (fx * xn * s + c[2] - uv[i, 0]) * w
            e[i, 1] = (fy * yn * s + c[3] - uv[i, 1]) * w
            if not jacobians:
                continue
            j00, j01 = fx * (s + 2.0 * d * xn * xn), fx * 2.0 * d * xn * yn
            j10, j11 = fy * 2.0 * d * xn * yn, fy * (s + 2.0 * d * yn * yn)
            inverse_z = 1.0 / x[i, 2]
            J_e[i, 0, 0], J_e[i, 0, 1] = j00 * inverse_z * w, j01 * inverse_z * w
            J_e[i, 0, 2] = (j00 * (-xn / x[i, 2]) + j01 * (-yn / x[i, 2])) * w
            J_e[i, 1, 0], J_e[i, 1, 1] = j10 * inverse_z * w, j11 * inverse_z * w
            J_e[i, 1, 2] = (j10 * (-xn / x[i, 2]) + j11 * (-yn / x[i, 2])) * w
            J_focal[i, 0], J_focal[i, 1] = xn * s * c[5] * w, yn * s * c[6] * w


# ------------------------------------------------------------------------------ the points-first tied frames


def frames_band_subtract(const int[::1] pair_left, const int[::1] pair_right,
                         const Py_ssize_t[::1] runs, Py_ssize_t first_run, Py_ssize_t last_run,
                         const Py_ssize_t[::1] frame, const Py_ssize_t[::1] point, const int[:, ::1] local_cols,
                         const double[:, :, ::1] Wp, const double[:, :, ::1] Hpp_inv, const Py_ssize_t[:, ::1] rows,
                         double[:, ::1] band) -> None:
    """Subtract from `band` (S, u + 1; LAPACK's lower band storage transposed: band[r, d] holds (r + d, r)) the
    sums over the runs first_run to last_run (group_normal.GroupStructure's pair_runs `runs`) of Wp_i Hpp_inv_p
    Wp_j^T over their pairs (i, j) = (pair_left, pair_right) of observations of a point p: at the rows
    rows[frame_i, local_cols_i] and the columns rows[frame_j, local_cols_j] (rows (F, L), counted from band's
    first), where the column is not before the row. Wp (N, l, 3), Hpp_inv (P, 3, 3)."""
    cdef int l = Wp.shape[1], a, b, c
    cdef Py_ssize_t run, q, i, j, p, row, column
    cdef double V[3 * MAX_ROW]
    cdef double summed[MAX_ROW * MAX_ROW]
    if l > MAX_ROW:
        raise ValueError(f"at most {MAX_ROW} local columns per observation, got {l}")
    with nogil:
        for run in range(first_run, last_run):
            memset(summed, 0, l * l * sizeof(double))
            for q in range(runs[run], runs[run + 1]):
                i, j, p = pair_left[q], pair_right[q], point[pair_left[q]]
                for a in range(l):
                    for c in range(3):
                        V[3 * a + c] = (Wp[i, a, 0] * Hpp_inv[p, 0, c] + Wp[i, a, 1] * Hpp_inv[p, 1, c]
                                        + Wp[i, a, 2] * Hpp_inv[p, 2, c])
                for a in range(l):
                    for b in range(l):
                        summed[a * l + b] += V[3 * a] * Wp[j, b, 0] + V[3 * a + 1] * Wp[j, b, 1] \
                            + V[3 * a + 2] * Wp[j, b, 2]
            i, j = pair_left[runs[run]], pair_right[runs[run]]
            for a in range(l):
                row = rows[frame[i], local_cols[i, a]]
                for b in range(l):
                    column = rows[frame[j], local_cols[j, b]]
                    if column >= row:
                        band[row, column - row] -= summed[a * l + b]


def frames_from_points(const Py_ssize_t[::1] frame, const Py_ssize_t[::1] point, const int[:, ::1] local_cols,
                       const double[:, :, ::1] Wp, const double[:, :, ::1] Hpp_inv, const double[:, :, ::1] coupled,
                       double[:, :, ::1] out) -> None:
    """Add to out (F, L, q), for every observation i of a point p, Wp_i Hpp_inv_p coupled_p at the rows of its
    local columns; Wp (N, l, 3), Hpp_inv (P, 3, 3), coupled (P, 3, q)."""
    cdef Py_ssize_t n = Wp.shape[0], i, p, f
    cdef int l = Wp.shape[1], q = coupled.shape[2], a, b, c
    cdef double V[3]
    with nogil:
        for i in range(n):
            p, f = point[i], frame[i]
            for a in range(l):
                for c in range(3):
                    V[c] = Wp[i, a, 0] * Hpp_inv[p, 0, c] + Wp[i, a, 1] * Hpp_inv[p, 1, c] \
                        + Wp[i, a, 2] * Hpp_inv[p, 2, c]
                for b in range(q):
                    out[f, local_cols[i, a], b] += V[0] * coupled[p, 0, b] + V[1] * coupled[p, 1, b] \
                        + V[2] * coupled[p, 2, b]


def points_from_frames(const Py_ssize_t[::1] frame, const Py_ssize_t[::1] point, const int[:, ::1] local_cols,
                       const double[:, :, ::1] Wp, const double[:, :, ::1] x_local, double[:, :, ::1] out) -> None:
    """Add to out (P, 3, k), for every observation i of a point p, Wp_i^T x_local at the rows of its local
    columns; Wp (N, l, 3), x_local (F, L, k)."""
    cdef Py_ssize_t n = Wp.shape[0], i, p, f
    cdef int l = Wp.shape[1], k = x_local.shape[2], a, b, c
    cdef double w
    with nogil:
        for i in range(n):
            p, f = point[i], frame[i]
            for a in range(l):
                for c in range(3):
                    w = Wp[i, a, c]
                    for b in range(k):
                        out[p, c, b] += w * x_local[f, local_cols[i, a], b]
