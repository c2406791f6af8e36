# Small dense linear algebra shared by the compiled modules (_kernels.pyx, _refine.pyx): inline
# definitions, compiled into each module that cimports them. Matrices are row-major double[9]
# (3, 3) or double[d * d].

from libc.math cimport fabs
from libc.string cimport memcpy
from scipy.linalg.cython_lapack cimport dgesvd


cdef inline void matmul3(const double *A, const double *B, double *out) noexcept nogil:
    """out = A @ B, all (3, 3); out must not alias A or B."""
    cdef int i, j
    for i in range(3):
        for j in range(3):
            out[3 * i + j] = A[3 * i] * B[j] + A[3 * i + 1] * B[3 + j] + A[3 * i + 2] * B[6 + j]


cdef inline double det3(const double *A) noexcept nogil:
    """Determinant of A (3, 3) (either storage order)."""
    return (A[0] * (A[4] * A[8] - A[7] * A[5]) - A[3] * (A[1] * A[8] - A[7] * A[2])
            + A[6] * (A[1] * A[5] - A[4] * A[2]))


cdef inline bint solve_linear(double *A, double *b, int d) noexcept nogil:
    """Solve A x = b in place (x in b) for A (d, d), by Gaussian elimination with partial
    pivoting; A is overwritten. False (b unchanged in meaning) if A is singular."""
    cdef int i, j, k, p
    cdef double best, tmp, factor
    for k in range(d):
        p = k
        best = fabs(A[k * d + k])
        for i in range(k + 1, d):
            if fabs(A[i * d + k]) > best:
                best, p = fabs(A[i * d + k]), i
        if best == 0.0:
            return False
        if p != k:
            for j in range(d):
                tmp = A[k * d + j]; A[k * d + j] = A[p * d + j]; A[p * d + j] = tmp
            tmp = b[k]; b[k] = b[p]; b[p] = tmp
        for i in range(k + 1, d):
            factor = A[i * d + k] / A[k * d + k]
            for j in range(k, d):
                A[i * d + j] -= factor * A[k * d + j]
            b[i] -= factor * b[k]
    for k in range(d - 1, -1, -1):
        for j in range(k + 1, d):
            b[k] -= A[k * d + j] * b[j]
        b[k] /= A[k * d + k]
    return True


cdef inline void nearest_rotation(double *X) noexcept nogil:
    """Replace X (3, 3) by the nearest rotation (Frobenius): U diag(1, 1, det U V^T) V^T."""
    cdef int three = 3, lwork = 64, info = 0
    cdef double s[3]
    cdef double U[9]
    cdef double Vt[9]
    cdef double work[64]
    cdef double Q[9]
    cdef int i, j
    # X read column-major is X^T = U S Vt; its nearest rotation U D Vt read row-major is nearest(X).
    dgesvd(b"A", b"A", &three, &three, X, &three, s, U, &three, Vt, &three, work, &lwork, &info)
    for i in range(3):  # Q = U Vt (column-major)
        for j in range(3):
            Q[i + 3 * j] = U[i] * Vt[3 * j] + U[i + 3] * Vt[1 + 3 * j] + U[i + 6] * Vt[2 + 3 * j]
    if det3(Q) < 0:
        for i in range(3):
            for j in range(3):
                Q[i + 3 * j] -= 2.0 * U[i + 6] * Vt[2 + 3 * j]
    memcpy(X, Q, 9 * sizeof(double))
