# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled `certificate.tight_certified`: the multipliers' family and the barrier search of certificate.py's
docstring in one call, with LAPACK (SciPy's `cython_lapack`) on the 10 x 10 and 9 x 9 matrices instead of a
few dozen numpy calls of ~10 microseconds each. The steps are certificate.py's, in its order; the bases of
x's complement and of the multipliers' free directions are other orthonormal bases of the same spaces (the
search is the same in any), so the numbers differ from numpy's by roundings and the answer is the same
(tests/test_pose_fallback.py compares both on certified and refused frames). Only the answer is used: where
it says no, the global fallback searches, and it finds the same pose where the pose is the global minimum.
"""

from libc.math cimport NAN, fabs, isfinite, sqrt
from libc.string cimport memset
from scipy.linalg.cython_lapack cimport dgesv, dgesvd, dsyev

cdef enum:
    N_FORMS = 31  # the constraints' quadratic forms (certificate.CONSTRAINTS)
    WORK = 4096

cdef double EPSILON = 2.220446049250313e-16


cdef double least_eigenvalue(const double *A, int n) noexcept nogil:
    """The least eigenvalue of the symmetric A (n, n), n <= 10 (its lower triangle); NaN where LAPACK fails."""
    cdef double copy[100]
    cdef double values[10]
    cdef double work[WORK]
    cdef int i, lwork = WORK, info = 0
    for i in range(n * n):
        copy[i] = A[i]
    dsyev(b"N", b"L", &n, copy, &n, values, work, &lwork, &info)
    return values[0] if info == 0 else NAN


cdef void congruence(const double *P, const double *S, double *out) noexcept nogil:
    """out (9, 9) = P^T S P of S (10, 10) and P (10, 9) (row-major)."""
    cdef double SP[90]
    cdef int i, j, k
    cdef double total
    for i in range(10):
        for j in range(9):
            total = 0.0
            for k in range(10):
                total += S[10 * i + k] * P[9 * k + j]
            SP[9 * i + j] = total
    for i in range(9):
        for j in range(9):
            total = 0.0
            for k in range(10):
                total += P[9 * k + i] * SP[9 * k + j]
            out[9 * i + j] = total


cdef void complement_basis(const double *x, double *P) noexcept nogil:
    """P (10, 9) row-major: an orthonormal basis of x's complement (x (10,), not 0), the last nine columns
    of the Householder reflection that maps e0 to -+x / |x|."""
    cdef double v[10]
    cdef double norm = 0.0, vv = 0.0
    cdef int i, j
    for i in range(10):
        norm += x[i] * x[i]
    norm = sqrt(norm)
    for i in range(10):
        v[i] = x[i] / norm
    v[0] += 1.0 if v[0] >= 0 else -1.0
    for i in range(10):
        vv += v[i] * v[i]
    for i in range(10):
        for j in range(1, 10):
            P[9 * i + j - 1] = (1.0 if i == j else 0.0) - 2.0 * v[i] * v[j] / vv


def tight_certified(const double[:, ::1] H, const double[::1] g, double c, const double[:, ::1] R,
                    const double[:, ::1] constraints, double relative_tolerance, int iterations):
    """certificate.tight_certified of H (9, 9), g (9,), c, R (3, 3); constraints (31, 100) the flattened
    quadratic forms (certificate._FLAT), relative_tolerance CERTIFICATE_TOLERANCE, iterations ITERATIONS."""
    if H.shape[0] != 9 or H.shape[1] != 9 or g.shape[0] != 9 or R.shape[0] != 3 or R.shape[1] != 3 \
            or constraints.shape[0] != N_FORMS or constraints.shape[1] != 100:
        raise ValueError("tight_certified: H (9, 9), g (9,), R (3, 3) and constraints (31, 100) expected")
    cdef bint answer
    with nogil:
        answer = certified(&H[0, 0], &g[0], c, &R[0, 0], &constraints[0, 0], relative_tolerance, iterations)
    return answer


cdef bint certified(const double *H, const double *g, double c, const double *R, const double *A,
                    double relative_tolerance, int iterations) noexcept nogil:
    """certificate.tight_certified's steps (see it and `_multiplier_family`, `_independent_changes`,
    `_least_eigenvalue_search`); A (31, 100) the constraints' forms."""
    cdef double x[10]
    cdef double Q[100]
    cdef double whole[100]
    cdef double P[90]
    cdef double base[N_FORMS]
    cdef double free_changes[N_FORMS * 100]  # (d, 100) the free directions' changes of S
    cdef double changes[N_FORMS * 100]  # (e, 100) those of the kept combinations
    cdef double ends[(N_FORMS + 1) * 81]  # (e + 1) 9 x 9: the combinations' changes of P^T S P, then -I
    cdef int d, n_kept, i
    cdef double tolerance, trace_H = 0.0, norm_g = 0.0
    for i in range(9):
        x[i] = R[i]
        trace_H += H[10 * i]
        norm_g += g[i] * g[i]
    x[9] = 1.0
    tolerance = relative_tolerance * (trace_H + sqrt(norm_g) + fabs(c))
    stacked(H, g, c, Q)
    d = multiplier_family(Q, x, A, base, free_changes)
    if d < 0:
        return False
    whole_hessian(Q, base, A, whole)
    complement_basis(x, P)
    n_kept = independent_changes(free_changes, d, P, changes, ends)
    if n_kept < 0:
        return False
    if n_kept == 0:
        return least_eigenvalue(whole, 10) >= -tolerance
    return barrier_search(whole, P, changes, ends, n_kept, tolerance, iterations)


cdef void stacked(const double *H, const double *g, double c, double *Q) noexcept nogil:
    """Q (10, 10) = [[H, -g], [-g^T, c]]."""
    cdef int i, j
    for i in range(9):
        for j in range(9):
            Q[10 * i + j] = H[9 * i + j]
        Q[10 * i + 9] = -g[i]
        Q[90 + i] = -g[i]
    Q[99] = c


cdef int multiplier_family(const double *Q, const double *x, const double *A, double *base,
                           double *free_changes) noexcept nogil:
    """The multipliers with S(lambda) x = 0 (B lambda = Q x, B (10, 31) of columns A_k x): base (31,), the
    least-norm least-squares solution at numpy.linalg.lstsq's rank (singular values above eps max(10, 31)
    of the largest), and free_changes (d, 100) the changes -sum_k v_k A_k of S along each vector v of B's
    null space; returns d, or -1 where a number is not finite or LAPACK fails."""
    cdef double B[10 * N_FORMS]  # column-major
    cdef double Qx[10]
    cdef double singular[10]
    cdef double U[100]
    cdef double Vt[N_FORMS * N_FORMS]  # column-major: Vt[N_FORMS * k + i] is row i's entry k
    cdef double work[WORK]
    cdef int i, j, k, e, m = 10, n = N_FORMS, lwork = WORK, info = 0, rank = 0
    cdef double total
    for k in range(N_FORMS):
        for i in range(10):
            total = 0.0
            for j in range(10):
                total += A[100 * k + 10 * i + j] * x[j]
            B[10 * k + i] = total
    for i in range(10):
        total = 0.0
        for j in range(10):
            total += Q[10 * i + j] * x[j]
        Qx[i] = total
    for i in range(10 * N_FORMS):
        if not isfinite(B[i]):
            return -1
    for i in range(10):
        if not isfinite(Qx[i]):
            return -1
    dgesvd(b"A", b"A", &m, &n, B, &m, singular, U, &m, Vt, &n, work, &lwork, &info)
    if info != 0:
        return -1
    for i in range(10):
        if singular[i] > EPSILON * N_FORMS * singular[0]:
            rank += 1
    memset(base, 0, N_FORMS * sizeof(double))
    for i in range(rank):
        total = 0.0
        for j in range(10):
            total += U[10 * i + j] * Qx[j]
        total /= singular[i]
        for k in range(N_FORMS):
            base[k] += Vt[N_FORMS * k + i] * total
    for k in range(N_FORMS):
        if not isfinite(base[k]):
            return -1
    for e in range(N_FORMS - rank):
        for i in range(100):
            total = 0.0
            for k in range(N_FORMS):
                total += Vt[N_FORMS * k + rank + e] * A[100 * k + i]
            free_changes[100 * e + i] = -total
    return N_FORMS - rank


cdef void whole_hessian(const double *Q, const double *base, const double *A, double *whole) noexcept nogil:
    """whole (10, 10) = Q - sum_k base_k A_k."""
    cdef int i, k
    cdef double total
    for i in range(100):
        total = Q[i]
        for k in range(N_FORMS):
            total -= base[k] * A[100 * k + i]
        whole[i] = total


cdef int independent_changes(const double *free_changes, int d, const double *P, double *changes,
                             double *ends) noexcept nogil:
    """certificate._independent_changes: combinations of the d free directions whose changes of P^T S P are
    orthonormal (singular values above 1e-12 of the largest kept); changes (e, 100) their changes of S, ends
    (e + 1, 81) their changes of P^T S P and then -I (the barrier's variable s). Returns e (0: none), -1
    where LAPACK fails."""
    cdef double forms[N_FORMS * 81]  # column-major (d, 81)
    cdef double singular[N_FORMS]
    cdef double U[N_FORMS * N_FORMS]  # column-major (d, d)
    cdef double Vt[N_FORMS * 81]  # column-major (d, 81)
    cdef double form[81]
    cdef double work[WORK]
    cdef int i, j, e, kept = 0, columns = 81, lwork = WORK, info = 0
    cdef double scale
    if d == 0:
        return 0
    for e in range(d):
        congruence(P, &free_changes[100 * e], form)
        for i in range(81):
            forms[d * i + e] = form[i]
    dgesvd(b"S", b"S", &d, &columns, forms, &d, singular, U, &d, Vt, &d, work, &lwork, &info)
    if info != 0:
        return -1
    if not singular[0] > 0:
        return 0
    for i in range(d):
        if singular[i] > 1e-12 * singular[0]:
            kept += 1
    for e in range(kept):
        scale = 1.0 / singular[e]
        for i in range(100):
            changes[100 * e + i] = 0.0
            for j in range(d):
                changes[100 * e + i] -= U[d * e + j] * scale * free_changes[100 * j + i]
        for i in range(81):
            ends[81 * e + i] = Vt[d * i + e]
    for i in range(81):
        ends[81 * kept + i] = -1.0 if i % 10 == 0 else 0.0
    return kept


cdef bint barrier_search(const double *whole, const double *P, const double *changes, const double *ends,
                         int n_kept, double tolerance, int iterations) noexcept nogil:
    """certificate._least_eigenvalue_search: Newton steps on -log det(P^T S P - s I) - weight s over (w, s),
    S = whole - sum_e w_e changes_e, until S's least eigenvalue is above -tolerance (True) or the search
    fails (False)."""
    cdef double w[N_FORMS]
    cdef double S[100]
    cdef double X[81]
    cdef double LU[81]
    cdef double Y[(N_FORMS + 1) * 81]  # column-major X^-1 E_e of each end
    cdef double gradient[N_FORMS + 1]
    cdef double hessian[(N_FORMS + 1) * (N_FORMS + 1)]
    cdef double step[N_FORMS + 1]
    cdef double trial[81]
    cdef int pivots[9]
    cdef int n_ends = n_kept + 1, i, j, e, f, iteration, nine = 9, nrhs, info = 0
    cdef double s, weight = 1.0, length, total, decrement
    memset(w, 0, N_FORMS * sizeof(double))
    congruence(P, whole, X)
    s = least_eigenvalue(X, 9)
    s -= 1e-3 * fabs(s) + tolerance  # strictly inside
    for iteration in range(iterations):
        for i in range(100):
            total = whole[i]
            for e in range(n_kept):
                total -= w[e] * changes[100 * e + i]
            S[i] = total
        if least_eigenvalue(S, 10) >= -tolerance:
            return True
        congruence(P, S, X)
        for i in range(9):
            X[10 * i] -= s
        for i in range(81):
            LU[i] = X[i]
        for i in range(n_ends * 81):  # the ends are symmetric: as column-major, themselves
            Y[i] = ends[i]
        nrhs = 9 * n_ends
        dgesv(&nine, &nrhs, LU, &nine, pivots, Y, &nine, &info)
        if info != 0:
            return False
        for e in range(n_ends):
            total = 0.0
            for i in range(9):
                total += Y[81 * e + 10 * i]
            gradient[e] = -total
        gradient[n_kept] -= weight
        for e in range(n_ends):
            for f in range(n_ends):  # tr(X^-1 E_e X^-1 E_f)
                total = 0.0
                for i in range(9):
                    for j in range(9):
                        total += Y[81 * e + 9 * j + i] * Y[81 * f + 9 * i + j]
                hessian[n_ends * f + e] = total
            step[e] = -gradient[e]
        if not solved(hessian, step, n_ends):
            return False
        length = 1.0
        while True:
            for i in range(81):
                total = X[i]
                for e in range(n_ends):
                    total += length * step[e] * ends[81 * e + i]
                trial[i] = total
            if not least_eigenvalue(trial, 9) <= 0:
                break
            length /= 2
            if length < 1e-8:
                return False
        for e in range(n_kept):
            w[e] += 0.95 * length * step[e]
        s += 0.95 * length * step[n_kept]
        decrement = 0.0
        for e in range(n_ends):
            for f in range(n_ends):
                decrement += step[e] * hessian[n_ends * f + e] * step[f]
        if decrement < 0.25:  # the Newton decrement below 1/2: the barrier's weight grows
            weight *= 4.0
    return False


cdef bint solved(const double *matrix, double *right, int n) noexcept nogil:
    """right (n,) <- matrix^-1 right, matrix (n, n) column-major (kept); False where it is singular."""
    cdef double copy[(N_FORMS + 1) * (N_FORMS + 1)]
    cdef int pivots[N_FORMS + 1]
    cdef int i, one = 1, info = 0
    for i in range(n * n):
        copy[i] = matrix[i]
    dgesv(&n, &one, copy, &n, pivots, right, &n, &info)
    return info == 0
