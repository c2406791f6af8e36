# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled refinement and RANSAC steps: `refine.refine_pose`'s Levenberg-Marquardt iteration, the
MSAC scoring of `robust`, and `gp3p` for RANSAC's minimal samples, each in one call.

As numpy calls, one refinement iteration on 10-500 points is ~30 operations of a few microseconds
of overhead each, and one gP3P solve ~150; here they run on plain loops over the points. The
arithmetic is that of the Python modules' docstrings (`refine.py`, `robust.py`, `gp3p.py`), which
stay the reference: tests compare the two. Matrices are C-ordered doubles; LAPACK (scipy's
`cython_lapack`) takes column-major ones. Everything runs on stack buffers or per-call
allocations, so the functions are safe in threads. `refine` reads its arrays in place (the buffer
protocol, no memoryviews or numpy indexing) and returns the covariance from the same call: at 10
points the call's own overhead, not the iteration, was most of its time (issue 31).
"""

from cpython.buffer cimport (PyBUF_C_CONTIGUOUS, PyBUF_FORMAT, PyBUF_STRIDES, PyBUF_WRITABLE, PyBuffer_Release,
                            PyObject_CheckBuffer, PyObject_GetBuffer)
from libc.math cimport INFINITY, NAN, cos, fabs, isfinite, sin, sqrt
from libc.stdlib cimport free, malloc
from libc.string cimport memcpy, memset
from scipy.linalg.cython_lapack cimport dgebal, dlahqr, dsyev

from dmais_pipe.pose._small cimport det3, matmul3, nearest_rotation, solve_linear

import numpy as np

# Levenberg-Marquardt (refine.py): initial damping, its bounds, and the stopping tolerances.
cdef double INITIAL_DAMPING = 1e-6
cdef double MIN_DAMPING = 1e-12
cdef double MAX_DAMPING = 1e12
# Largest condition number of the unit-diagonal normal matrix for a finite covariance.
cdef double MAX_CONDITION = 1e12
# gp3p.py's tolerances (same names).
cdef int NEWTON_STEPS = 3
cdef double RESIDUAL_TOLERANCE = 1e-6
cdef double IMAG_TOLERANCE = 1e-4
cdef double DEGENERATE_AREA = 1e-10
cdef double SMALL_DIVISOR = 1e-8
cdef double UNIQUE_TOLERANCE = 1e-9
cdef enum:
    MAX_TRIPLES = 32  # 8 roots x 2 values of y x 2 values of l1


# ------------------------------------------------------------------------------ small helpers


cdef void exp_so3(const double *w, double *R) noexcept nogil:
    """R (3, 3) = exp([w]x) through the unit quaternion (cos(theta/2), sin(theta/2) w / theta)."""
    cdef double theta2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    cdef double theta = sqrt(theta2)
    cdef double s, qw, x, y, z
    if theta < 1e-3:  # sin(theta/2)/theta and cos(theta/2) by their Taylor series
        s = 0.5 - theta2 / 48.0 + theta2 * theta2 / 3840.0
        qw = 1.0 - theta2 / 8.0 + theta2 * theta2 / 384.0
    else:
        s = sin(0.5 * theta) / theta
        qw = cos(0.5 * theta)
    x, y, z = s * w[0], s * w[1], s * w[2]
    R[0] = 1.0 - 2.0 * (y * y + z * z)
    R[1] = 2.0 * (x * y - z * qw)
    R[2] = 2.0 * (x * z + y * qw)
    R[3] = 2.0 * (x * y + z * qw)
    R[4] = 1.0 - 2.0 * (x * x + z * z)
    R[5] = 2.0 * (y * z - x * qw)
    R[6] = 2.0 * (x * z - y * qw)
    R[7] = 2.0 * (y * z + x * qw)
    R[8] = 1.0 - 2.0 * (x * x + y * y)


# ------------------------------------------------------------------------------ refinement


cdef void tangent_bases(const double *f, int n, double *B) noexcept nogil:
    """B (n, 6): rows b1, b2 of refine.tangent_bases for unit directions f (n, 3)."""
    cdef int i, k, a
    cdef double b1[3]
    cdef double norm
    for i in range(n):
        a = 0
        for k in range(1, 3):
            if fabs(f[3 * i + k]) < fabs(f[3 * i + a]):
                a = k
        # b1 = f x e_a
        if a == 0:
            b1[0], b1[1], b1[2] = 0.0, f[3 * i + 2], -f[3 * i + 1]
        elif a == 1:
            b1[0], b1[1], b1[2] = -f[3 * i + 2], 0.0, f[3 * i]
        else:
            b1[0], b1[1], b1[2] = f[3 * i + 1], -f[3 * i], 0.0
        norm = sqrt(b1[0] * b1[0] + b1[1] * b1[1] + b1[2] * b1[2])
        for k in range(3):
            B[6 * i + k] = b1[k] / norm
        B[6 * i + 3] = f[3 * i + 1] * B[6 * i + 2] - f[3 * i + 2] * B[6 * i + 1]
        B[6 * i + 4] = f[3 * i + 2] * B[6 * i] - f[3 * i] * B[6 * i + 2]
        B[6 * i + 5] = f[3 * i] * B[6 * i + 1] - f[3 * i + 1] * B[6 * i]


cdef double evaluate(const double *v, const double *B, const double *M, int n, const double *R, const double *t,
                     double *JtJ, double *Jtr) noexcept nogil:
    """Cost sum_i ||r_i||^2 at (R, t) and, when JtJ is given, J^T J (6, 6) and J^T r (6,) of
    refine.py's residuals and analytic Jacobian (with respect to (omega, delta_t)). The sums run
    in local arrays, not through the output pointers, which may alias the inputs as far as the
    compiler knows (it would store every addition: ~8% of a 500-point refinement)."""
    cdef int i, a, j, k
    cdef double cost = 0.0
    cdef double q[3]
    cdef double p[3]
    cdef double u[3]
    cdef double d[3]
    cdef double row[6]
    cdef double normal[36]
    cdef double gradient[6]
    cdef double norm, r
    cdef const double *b
    memset(normal, 0, 36 * sizeof(double))
    memset(gradient, 0, 6 * sizeof(double))
    for i in range(n):
        for k in range(3):
            q[k] = R[3 * k] * M[3 * i] + R[3 * k + 1] * M[3 * i + 1] + R[3 * k + 2] * M[3 * i + 2]
            p[k] = q[k] + t[k] - v[3 * i + k]
        norm = sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2])
        for k in range(3):
            u[k] = p[k] / norm
        for a in range(2):
            b = B + 6 * i + 3 * a
            r = b[0] * u[0] + b[1] * u[1] + b[2] * u[2]
            cost += r * r
            if JtJ == NULL:
                continue
            # d r / d p = (b - r u) / ||p||; d r / d omega = q x (d r / d p)
            for k in range(3):
                d[k] = (b[k] - r * u[k]) / norm
            row[0] = q[1] * d[2] - q[2] * d[1]
            row[1] = q[2] * d[0] - q[0] * d[2]
            row[2] = q[0] * d[1] - q[1] * d[0]
            row[3], row[4], row[5] = d[0], d[1], d[2]
            for j in range(6):
                gradient[j] += row[j] * r
                for k in range(j, 6):
                    normal[6 * j + k] += row[j] * row[k]
    if JtJ != NULL:
        for j in range(6):
            Jtr[j] = gradient[j]
            for k in range(j, 6):
                JtJ[6 * j + k] = normal[6 * j + k]
                JtJ[6 * k + j] = normal[6 * j + k]
    return cost


cdef int levenberg_marquardt(const double *v, const double *B, const double *M, int n, double *R, double *t,
                             int max_iterations, double step_tolerance, double cost_tolerance,
                             double *JtJ, double *cost_out, bint *converged) noexcept nogil:
    """refine.py's iteration from (R, t) (updated in place) on centred points M; JtJ (6, 6) at the
    solution, its cost, and whether a tolerance was met. Returns the iterations performed.

    Each iteration first asks the Gauss-Newton model: when its least value lies less than
    cost_tolerance x cost below the cost (0.5 g^T (J^T J)^-1 g, g = J^T r), the iteration has
    converged. Otherwise trial steps: A = J^T J + damping diag(J^T J), step = -A^-1 g,
    R <- exp(omega) R, t <- t + delta_t; a trial that does not lower the cost multiplies the damping
    by 10 (up to 1e12), an accepted one divides it by 10 (down to 1e-12). It also stops when no
    descent is left, when the step is below step_tolerance (radians; relative to the scene size
    for t) or when the cost decreased by less than cost_tolerance of it. J^T J is accumulated with
    the first trial's cost (usually accepted); later trials evaluate the cost alone."""
    cdef double Jtr[6]
    cdef double JtJ_new[36]
    cdef double Jtr_new[6]
    cdef double A[36]
    cdef double step[6]
    cdef double gn[6]
    cdef double dR[9]
    cdef double R_new[9]
    cdef double t_new[3]
    cdef double damping = INITIAL_DAMPING, cost, cost_new = 0.0, decrease, size, largest, centre, mx, predicted
    cdef int iteration, j, k, trial
    cdef bint have_jacobian = False
    # size = 1 + max |M - mean M| + max |t|
    largest = 0.0
    for k in range(3):
        centre = 0.0
        for j in range(n):
            centre += M[3 * j + k]
        centre /= n
        for j in range(n):
            largest = max(largest, fabs(M[3 * j + k] - centre))
    size = 1.0 + largest + max(fabs(t[0]), max(fabs(t[1]), fabs(t[2])))
    cost = evaluate(v, B, M, n, R, t, JtJ, Jtr)
    converged[0] = False
    cost_out[0] = cost
    for iteration in range(1, max_iterations + 1):
        memcpy(A, JtJ, 36 * sizeof(double))
        for k in range(6):
            gn[k] = -Jtr[k]
        if solve_linear(A, gn, 6):
            predicted = 0.0
            for k in range(6):
                predicted -= 0.5 * gn[k] * Jtr[k]
            if predicted <= cost_tolerance * cost:
                converged[0] = True
                return iteration
        trial = 0
        while True:
            memcpy(A, JtJ, 36 * sizeof(double))
            for k in range(6):
                A[7 * k] += damping * max(JtJ[7 * k], 1e-300)
                step[k] = -Jtr[k]
            if not solve_linear(A, step, 6):
                memset(step, 0, 6 * sizeof(double))
            exp_so3(step, dR)
            matmul3(dR, R, R_new)
            for k in range(3):
                t_new[k] = t[k] + step[3 + k]
            have_jacobian = trial == 0
            if have_jacobian:
                cost_new = evaluate(v, B, M, n, R_new, t_new, JtJ_new, Jtr_new)
            else:
                cost_new = evaluate(v, B, M, n, R_new, t_new, NULL, NULL)
            trial += 1
            if cost_new <= cost or damping > MAX_DAMPING:
                break
            damping *= 10.0
        if not cost_new <= cost:
            converged[0] = True  # no descent left: at the minimum up to rounding
            return iteration
        decrease = cost - cost_new
        memcpy(R, R_new, 9 * sizeof(double))
        memcpy(t, t_new, 3 * sizeof(double))
        if have_jacobian:
            memcpy(JtJ, JtJ_new, 36 * sizeof(double))
            memcpy(Jtr, Jtr_new, 6 * sizeof(double))
        else:
            evaluate(v, B, M, n, R, t, JtJ, Jtr)
        cost = cost_new
        cost_out[0] = cost
        damping = max(damping / 10.0, MIN_DAMPING)
        mx = max(fabs(step[0]), max(fabs(step[1]), fabs(step[2])))
        mx = max(mx, max(fabs(step[3]), max(fabs(step[4]), fabs(step[5]))) / size)
        if mx < step_tolerance or decrease <= cost_tolerance * cost:
            converged[0] = True
            return iteration
    return max_iterations


cdef bint cholesky_inverse(const double *N, double *inverse, double *condition) noexcept nogil:
    """inverse (6, 6) of a symmetric positive definite N (6, 6) through its Cholesky factor
    (N = L L^T, N^-1 = L^-T L^-1) and condition = ||N||_F ||N^-1||_F, which lies between N's
    2-norm condition number and 6 times it; False when a pivot is not positive."""
    cdef double L[36]
    cdef double Li[36]  # L^-1, lower triangular
    cdef double s, norm = 0.0, inverse_norm = 0.0
    cdef int i, j, k
    memset(L, 0, 36 * sizeof(double))
    memset(Li, 0, 36 * sizeof(double))
    for j in range(6):
        s = N[7 * j]
        for k in range(j):
            s -= L[6 * j + k] * L[6 * j + k]
        if not s > 0:
            return False
        L[7 * j] = sqrt(s)
        for i in range(j + 1, 6):
            s = N[6 * i + j]
            for k in range(j):
                s -= L[6 * i + k] * L[6 * j + k]
            L[6 * i + j] = s / L[7 * j]
    for j in range(6):
        Li[7 * j] = 1.0 / L[7 * j]
        for i in range(j + 1, 6):
            s = 0.0
            for k in range(j, i):
                s -= L[6 * i + k] * Li[6 * k + j]
            Li[6 * i + j] = s / L[7 * i]
    for i in range(6):
        for j in range(i, 6):
            s = 0.0
            for k in range(j, 6):
                s += Li[6 * k + i] * Li[6 * k + j]
            inverse[6 * i + j] = s
            inverse[6 * j + i] = s
    for k in range(36):
        norm += N[k] * N[k]
        inverse_norm += inverse[k] * inverse[k]
    condition[0] = sqrt(norm * inverse_norm)
    return True


cdef void inverse_normal_matrix(const double *JtJ, double *out) noexcept nogil:
    """(J^T J)^-1 (6, 6), or NaN if its unit-diagonal version has a condition number above
    MAX_CONDITION (the pose is not observable).

    A Cholesky inverse where the Frobenius condition bound (at least the 2-norm condition number)
    is below MAX_CONDITION / 100, as for every pose observed well; otherwise the eigenvalues decide
    (LAPACK's dsyev, which costs several times the whole 10-point refinement)."""
    cdef double scale[6]
    cdef double N[36]
    cdef double inverse[36]
    cdef double w[6]
    cdef double work[256]
    cdef int six = 6, lwork = 256, info = 0, i, j, k
    cdef double s, condition = INFINITY
    for i in range(6):
        scale[i] = sqrt(JtJ[7 * i])
        if not scale[i] > 0:
            for j in range(36):
                out[j] = NAN
            return
    for i in range(6):
        for j in range(6):
            N[6 * i + j] = JtJ[6 * i + j] / (scale[i] * scale[j])
    if cholesky_inverse(N, inverse, &condition) and condition <= MAX_CONDITION / 100:
        for i in range(6):
            for j in range(6):
                out[6 * i + j] = inverse[6 * i + j] / (scale[i] * scale[j])
        return
    dsyev(b"V", b"L", &six, N, &six, w, work, &lwork, &info)  # eigenvectors as rows of N (symmetric input)
    if info != 0 or not (fabs(w[0]) > 0) or fabs(w[5]) / fabs(w[0]) > MAX_CONDITION:
        for j in range(36):
            out[j] = NAN
        return
    for i in range(6):
        for j in range(i, 6):
            s = 0.0
            for k in range(6):
                s += N[6 * k + i] * N[6 * k + j] / w[k]
            out[6 * i + j] = s / (scale[i] * scale[j])
            out[6 * j + i] = out[6 * i + j]


cdef int prepare(const double *v, const double *f_in, const double *P, int n, double zero_direction,
                 double *f, double *B, double *Mc, double *m) noexcept nogil:
    """Unit directions f (n, 3), their tangent bases B (n, 6), the centroid m (3,) of the points
    P (n, 3) and the centred points Mc (n, 3); False when an input is not finite or a direction is
    shorter than zero_direction."""
    cdef int i, k
    cdef double norm
    for i in range(n):
        norm = sqrt(f_in[3 * i] * f_in[3 * i] + f_in[3 * i + 1] * f_in[3 * i + 1] + f_in[3 * i + 2] * f_in[3 * i + 2])
        if not (norm >= zero_direction and isfinite(norm)):
            return False
        for k in range(3):
            if not (isfinite(v[3 * i + k]) and isfinite(P[3 * i + k])):
                return False
            f[3 * i + k] = f_in[3 * i + k] / norm
    for k in range(3):
        m[k] = 0.0
        for i in range(n):
            m[k] += P[3 * i + k]
        m[k] /= n
    for i in range(n):
        for k in range(3):
            Mc[3 * i + k] = P[3 * i + k] - m[k]
    tangent_bases(f, n, B)
    return True


cdef double objective(const double *v, const double *f, const double *M, int n, const double *R,
                      const double *t) noexcept nogil:
    """The paper's eq. objfun at (R, t): sum_i ||f_i x (R M_i + t - v_i)||^2 (unit f (n, 3))."""
    cdef int i, k
    cdef double p[3]
    cdef double cx, cy, cz, total = 0.0
    for i in range(n):
        for k in range(3):
            p[k] = R[3 * k] * M[3 * i] + R[3 * k + 1] * M[3 * i + 1] + R[3 * k + 2] * M[3 * i + 2] + t[k] - v[3 * i + k]
        cx = f[3 * i + 1] * p[2] - f[3 * i + 2] * p[1]
        cy = f[3 * i + 2] * p[0] - f[3 * i] * p[2]
        cz = f[3 * i] * p[1] - f[3 * i + 1] * p[0]
        total += cx * cx + cy * cy + cz * cz
    return total


cdef void pose_covariance(const double *JtJ, const double *Rm, double variance, double *cov) noexcept nogil:
    """cov (6, 6) of (omega, t) = variance T (J^T J)^-1 T^T, J^T J (6, 6) of the centred parameters
    (omega, t' = t + R m): delta_t = delta_t' + [R m]x omega, i.e. T = [[I, 0], [[R m]x, I]]."""
    cdef double inverse[36]
    cdef double T[36]
    cdef double s
    cdef int i, j, k, l
    inverse_normal_matrix(JtJ, inverse)
    memset(T, 0, 36 * sizeof(double))
    for k in range(6):
        T[7 * k] = 1.0
    T[6 * 3 + 1], T[6 * 3 + 2] = -Rm[2], Rm[1]
    T[6 * 4 + 0], T[6 * 4 + 2] = Rm[2], -Rm[0]
    T[6 * 5 + 0], T[6 * 5 + 1] = -Rm[1], Rm[0]
    for i in range(6):
        for j in range(6):
            s = 0.0
            for k in range(6):
                if T[6 * i + k] == 0.0:  # a zero term leaves the sum as it is
                    continue
                for l in range(6):
                    s += T[6 * i + k] * inverse[6 * k + l] * T[6 * j + l]
            cov[6 * i + j] = variance * s


cdef struct Refined:
    double R[9]
    double t[3]
    double covariance[36]
    double cost           # sum_i ||r_i||^2 at (R, t)
    double objective      # eq. objfun at (R, t)
    int iterations
    bint converged


cdef int refine_arrays(const double *v, const double *f_in, const double *P, int n, const double *R0,
                       const double *t0, int max_iterations, double step_tolerance, double cost_tolerance,
                       double sigma, double zero_direction, bint covariance, Refined *out) noexcept nogil:
    """`refine`'s work on raw C-ordered arrays: v, f_in, P (n, 3), R0 (3, 3), t0 (3,); the result
    in out. Returns 1 when refined, 0 when the input fails a check, -1 when memory runs out."""
    cdef double m[3]
    cdef double Rm[3]
    cdef double JtJ[36]
    cdef double variance
    cdef int k
    memcpy(out.R, R0, 9 * sizeof(double))
    memcpy(out.t, t0, 3 * sizeof(double))
    if not rotation_within_tolerance(out.R, out.t):
        return 0
    cdef double *work = <double *> malloc(12 * n * sizeof(double))  # f (n, 3), B (n, 6), Mc (n, 3)
    if work == NULL:
        return -1
    cdef double *f = work
    cdef double *B = work + 3 * n
    cdef double *Mc = work + 9 * n
    if not prepare(v, f_in, P, n, zero_direction, f, B, Mc, m):
        free(work)
        return 0
    nearest_rotation(out.R)
    for k in range(3):
        out.t[k] = out.t[k] + out.R[3 * k] * m[0] + out.R[3 * k + 1] * m[1] + out.R[3 * k + 2] * m[2]
    out.iterations = levenberg_marquardt(v, B, Mc, n, out.R, out.t, max_iterations, step_tolerance, cost_tolerance,
                                         JtJ, &out.cost, &out.converged)
    out.objective = objective(v, f, Mc, n, out.R, out.t)
    free(work)
    for k in range(3):
        Rm[k] = out.R[3 * k] * m[0] + out.R[3 * k + 1] * m[1] + out.R[3 * k + 2] * m[2]
        out.t[k] -= Rm[k]
    if covariance:
        if isfinite(sigma):
            variance = sigma * sigma
        else:
            variance = out.cost / (2 * n - 6) if n > 3 else NAN
        pose_covariance(JtJ, Rm, variance, out.covariance)
    return 1


cdef bint acquire(object x, Py_buffer *view, int flags, Py_ssize_t rows, Py_ssize_t columns):
    """Hold x's buffer (PyObject_GetBuffer with flags) in view when x is a float64 array of shape
    (rows, columns), rows -1 for any, or (rows,) for columns 0; else False, nothing held."""
    if not PyObject_CheckBuffer(x):
        return False
    try:
        PyObject_GetBuffer(x, view, flags | PyBUF_FORMAT)
    except (BufferError, ValueError):  # e.g. not C-contiguous
        return False
    if (view.ndim == (2 if columns else 1) and view.itemsize == 8 and view.format[0] == b"d"
            and view.format[1] == 0 and (rows < 0 or view.shape[0] == rows) and (not columns or view.shape[1] == columns)):
        return True
    PyBuffer_Release(view)
    return False


cdef bint read_doubles(object x, double *out, Py_ssize_t rows, Py_ssize_t columns):
    """Copy x, a float64 array of shape (rows, columns) ((rows,) for columns 0) in any memory
    layout, to out in C order; False if x is not one."""
    cdef Py_buffer view
    cdef Py_ssize_t i, j, width = max(columns, 1)
    if not acquire(x, &view, PyBUF_STRIDES, rows, columns):
        return False
    for i in range(rows):
        for j in range(width):
            out[width * i + j] = (<double *> (<char *> view.buf + i * view.strides[0]
                                               + (j * view.strides[1] if columns else 0)))[0]
    PyBuffer_Release(&view)
    return True


cdef object new_array(const double *data, shape):
    """A new float64 array of shape holding data (C order)."""
    array = np.empty(shape)
    cdef Py_buffer view
    PyObject_GetBuffer(array, &view, PyBUF_C_CONTIGUOUS | PyBUF_WRITABLE)
    memcpy(view.buf, data, view.len)
    PyBuffer_Release(&view)
    return array


def refine(origins, directions, points, R0, t0, int max_iterations, double step_tolerance, double cost_tolerance,
           double sigma, double zero_direction, bint covariance=True):
    """refine.refine_pose compiled: (R, t, covariance or None, cost, n_iterations, converged,
    objective), or None when the input fails a check (refine_pose's Python checks then name the
    fault). objective: the paper's eq. objfun at (R, t).

    origins, directions, points: float64 C-contiguous (n, 3), n >= 3, finite, no direction shorter
    than zero_direction (they are normalized here); R0 (3, 3) a rotation within refine_pose's
    tolerance (re-orthonormalized here), t0 (3,). The points are centred (t' = t + R m) while
    iterating. covariance (6, 6) of (omega, t): sigma^2 (J^T J)^-1, with the a-posteriori
    cost / (2 n - 6) for sigma NaN (NaN for n = 3 then, and where the pose is not observable).
    The arrays are read in place through the buffer protocol; the work runs without the GIL."""
    cdef Py_buffer views[3]  # points, origins, directions
    cdef double R_start[9]
    cdef double t_start[3]
    cdef int held = 0, status = 0, n = 0, k
    cdef Refined out
    if not (read_doubles(R0, R_start, 3, 3) and read_doubles(t0, t_start, 3, 0)):
        return None
    try:
        held += acquire(points, &views[0], PyBUF_C_CONTIGUOUS, -1, 3)
        if held == 1:
            n = <int> views[0].shape[0]
            held += acquire(origins, &views[1], PyBUF_C_CONTIGUOUS, n, 3)
        if held == 2:
            held += acquire(directions, &views[2], PyBUF_C_CONTIGUOUS, n, 3)
        if held < 3 or n < 3:
            return None
        with nogil:
            status = refine_arrays(<double *> views[1].buf, <double *> views[2].buf, <double *> views[0].buf, n,
                                   R_start, t_start, max_iterations, step_tolerance, cost_tolerance, sigma,
                                   zero_direction, covariance, &out)
    finally:
        for k in range(held):
            PyBuffer_Release(&views[k])
    if status < 0:
        raise MemoryError()
    if status == 0:
        return None
    return (new_array(out.R, (3, 3)), new_array(out.t, 3), new_array(out.covariance, (6, 6)) if covariance else None,
            out.cost, out.iterations, out.converged, out.objective)


cdef bint rotation_within_tolerance(const double *R, const double *t) noexcept nogil:
    """Finite R, t with R^T R = I within numpy.allclose(atol=1e-6) and det R > 0 (refine_pose's check)."""
    cdef int i, j, k
    cdef double s
    for i in range(3):
        if not isfinite(t[i]):
            return False
        for j in range(3):
            if not isfinite(R[3 * i + j]):
                return False
    for i in range(3):
        for j in range(3):
            s = 0.0
            for k in range(3):
                s += R[3 * k + i] * R[3 * k + j]
            if not fabs(s - (1.0 if i == j else 0.0)) <= 1e-6 + 1e-5 * (1.0 if i == j else 0.0):
                return False
    return det3(R) > 0


# ------------------------------------------------------------------------------ RANSAC scoring


cdef double msac(const double *v, const double *f, const double *M, int n, const double *R, const double *t,
                 const double *threshold, double *errors, double wide, int *wide_count) noexcept nogil:
    """MSAC cost sum_i min(e_i / theta_i, 1)^2 of a pose, with the angular errors e_i of
    refine.ray_errors (inf behind the ray) written to errors (n,) when given, and the count of
    e_i < wide theta_i to wide_count when given."""
    cdef int i, k
    cdef double p[3]
    cdef double cx, cy, cz, norm, alpha, e, capped, cost = 0.0
    for i in range(n):
        for k in range(3):
            p[k] = R[3 * k] * M[3 * i] + R[3 * k + 1] * M[3 * i + 1] + R[3 * k + 2] * M[3 * i + 2] + t[k] - v[3 * i + k]
        norm = sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2])
        alpha = p[0] * f[3 * i] + p[1] * f[3 * i + 1] + p[2] * f[3 * i + 2]
        if alpha > 0 and norm > 0:
            cx = p[1] * f[3 * i + 2] - p[2] * f[3 * i + 1]
            cy = p[2] * f[3 * i] - p[0] * f[3 * i + 2]
            cz = p[0] * f[3 * i + 1] - p[1] * f[3 * i]
            e = sqrt(cx * cx + cy * cy + cz * cz) / norm
        else:
            e = INFINITY
        if errors != NULL:
            errors[i] = e
        capped = e / threshold[i]
        if wide_count != NULL and capped < wide:
            wide_count[0] += 1
        capped = min(capped, 1.0)
        cost += capped * capped
    return cost


def score(const double[:, ::1] origins, const double[:, ::1] directions, const double[:, ::1] points,
          const double[:, ::1] R, const double[::1] t, const double[::1] threshold):
    """(errors (n,), MSAC cost) of the pose (R, t); directions unit."""
    cdef int n = points.shape[0]
    errors = np.empty(n)
    cdef double[::1] e = errors
    cdef double cost
    with nogil:
        cost = msac(&origins[0, 0], &directions[0, 0], &points[0, 0], n, &R[0, 0], &t[0], &threshold[0], &e[0], 1.0,
                    NULL)
    return errors, cost


# ------------------------------------------------------------------------------ gP3P


cdef inline void poly_mul(const double *a, int na, const double *b, int nb, double *out) noexcept nogil:
    """out (na + nb - 1) = a * b, univariate, low order first."""
    cdef int i, j
    for i in range(na + nb - 1):
        out[i] = 0.0
    for i in range(na):
        for j in range(nb):
            out[i + j] += a[i] * b[j]


cdef inline double poly_val(const double *a, int na, double x) noexcept nogil:
    cdef double s = 0.0
    cdef int i
    for i in range(na - 1, -1, -1):
        s = s * x + a[i]
    return s


# Bivariate polynomials of degree < 5 in x and in y: C[5 * i + j] is the coefficient of x^i y^j.
cdef void bi_mul(const double *a, const double *b, double *out) noexcept nogil:
    cdef int i, j, k, l
    for i in range(25):
        out[i] = 0.0
    for i in range(5):
        for j in range(5):
            if a[5 * i + j] == 0.0:
                continue
            for k in range(5 - i):
                for l in range(5 - j):
                    out[5 * (i + k) + j + l] += a[5 * i + j] * b[5 * k + l]


cdef int univariate(const double *c, double *F, double *alpha, double *beta) noexcept nogil:
    """gp3p._univariate: F (17,), alpha (9,), beta (9,) low order first; returns len(F) (17)."""
    cdef double a12 = c[0], b12 = c[1], c12 = c[2], e12 = c[3]
    cdef double a13 = c[4], b13 = c[5], c13 = c[6], e13 = c[7]
    cdef double a23 = c[8], b23 = c[9], c23 = c[10], e23 = c[11]
    cdef double dp[25]
    cdef double dq[25]
    cdef double q1[25]
    cdef double p1[25]
    cdef double t1[25]
    cdef double t2[25]
    cdef double G[25]
    cdef double columns[5 * 9]  # coefficient of y^k: a polynomial in x of length 9
    cdef double P[2]
    cdef double S[3]
    cdef double tmp[17]
    cdef double tmp2[17]
    cdef int i, k
    memset(dp, 0, 25 * sizeof(double)); memset(dq, 0, 25 * sizeof(double))
    memset(q1, 0, 25 * sizeof(double)); memset(p1, 0, 25 * sizeof(double))
    p1[0], p1[5] = 2 * a12, -2 * c12
    q1[0], q1[5], q1[10] = e12, -2 * b12, 1.0
    # dp = p2 - p1, p2 = 2 a13 - 2 c13 y; dq = q2 - q1, q2 = e13 - 2 b13 y + y^2
    dp[0], dp[1], dp[5] = 2 * a13 - 2 * a12, -2 * c13, 2 * c12
    dq[0], dq[1], dq[2], dq[5], dq[10] = e13 - e12, -2 * b13, 1.0, 2 * b12, -1.0
    # G = dp^2 q1 - dp dq p1 + dq^2
    bi_mul(dp, dp, t1)
    bi_mul(t1, q1, G)
    bi_mul(dp, dq, t1)
    bi_mul(t1, p1, t2)
    for i in range(25):
        G[i] -= t2[i]
    bi_mul(dq, dq, t1)
    for i in range(25):
        G[i] += t1[i]
    P[0], P[1] = -2 * b23, -2 * c23
    S[0], S[1], S[2] = e23, 2 * a23, 1.0
    memset(columns, 0, 45 * sizeof(double))
    for k in range(5):
        for i in range(5):
            columns[9 * k + i] = G[5 * i + k]
    for k in range(4, 1, -1):  # y^k -> -(P y + S) y^(k-2)
        poly_mul(&columns[9 * k], 7, P, 2, tmp)
        for i in range(8):
            columns[9 * (k - 1) + i] -= tmp[i]
        poly_mul(&columns[9 * k], 7, S, 3, tmp)
        for i in range(9):
            columns[9 * (k - 2) + i] -= tmp[i]
    memcpy(alpha, &columns[9], 9 * sizeof(double))
    memcpy(beta, columns, 9 * sizeof(double))
    # F = beta^2 - P alpha beta + S alpha^2
    poly_mul(beta, 9, beta, 9, F)
    poly_mul(alpha, 9, beta, 9, tmp)
    poly_mul(tmp, 16, P, 2, tmp2)  # length 17 (tmp[16] unused: lengths add to 17)
    for i in range(17):
        F[i] -= tmp2[i]
    poly_mul(alpha, 9, alpha, 9, tmp)
    poly_mul(tmp, 15, S, 3, tmp2)
    for i in range(17):
        F[i] += tmp2[i]
    return 17


cdef int real_roots(const double *F_in, int length, double *roots) noexcept nogil:
    """Real (and nearly real: |imag| <= IMAG_TOLERANCE (1 + |root|)) roots of F, as numpy's
    polyroots (eigenvalues of the companion matrix) after trimming trailing zeros."""
    cdef int d, i, info = 0, ilo = 0, ihi = 0, one = 1, count = 0
    cdef bint no = False
    cdef double F[17]
    cdef double C[16 * 16]
    cdef double scale[16]
    cdef double wr[16]
    cdef double wi[16]
    cdef double largest = 0.0
    while length > 0 and F_in[length - 1] == 0.0:
        length -= 1
    if length < 2:
        return 0
    for i in range(length):
        if not isfinite(F_in[i]):
            return 0
        largest = max(largest, fabs(F_in[i]))
    for i in range(length):
        F[i] = F_in[i] / largest
    d = length - 1
    if d == 1:
        roots[0] = -F[0] / F[1]
        return 1
    memset(C, 0, d * d * sizeof(double))  # column-major companion matrix
    for i in range(1, d):
        C[(i - 1) * d + i] = 1.0  # subdiagonal
    for i in range(d):
        C[(d - 1) * d + i] = -F[i] / F[d]
    # The companion matrix is upper Hessenberg already: balance it by scaling alone (which keeps that
    # form; numpy's eigvals balances too) and run LAPACK's small-matrix QR iteration on it directly.
    dgebal(b"S", &d, C, &d, &ilo, &ihi, scale, &info)
    dlahqr(&no, &no, &d, &ilo, &ihi, C, &d, wr, wi, &one, &d, NULL, &d, &info)
    if info != 0:
        return 0
    for i in range(d):
        if fabs(wi[i]) <= IMAG_TOLERANCE * (1.0 + sqrt(wr[i] * wr[i] + wi[i] * wi[i])):
            roots[count] = wr[i]
            count += 1
    return count


cdef int quadratic_roots(double p, double q, double *out) noexcept nogil:
    cdef double disc = p * p / 4.0 - q, root
    if disc < -IMAG_TOLERANCE * (1.0 + p * p):
        return 0
    root = sqrt(max(disc, 0.0))
    out[0] = -p / 2.0 + root
    out[1] = -p / 2.0 - root
    return 2


cdef void depth_equations(const double *c, const double *l, double *out) noexcept nogil:
    """E12, E13, E23 at depths l (3,)."""
    cdef int k, i, j
    cdef double li, lj
    for k in range(3):
        i = 0 if k < 2 else 1
        j = 1 if k == 0 else 2
        li, lj = l[i], l[j]
        out[k] = li * li + lj * lj - 2 * c[4 * k + 2] * li * lj + 2 * c[4 * k] * li - 2 * c[4 * k + 1] * lj + c[4 * k + 3]


cdef void newton(const double *c, double *l) noexcept nogil:
    """gp3p._newton on one depth triple (singular steps skipped)."""
    cdef double J[9]
    cdef double value[3]
    cdef int step, k, i, j
    cdef double li, lj, largest
    for step in range(NEWTON_STEPS):
        memset(J, 0, 9 * sizeof(double))
        for k in range(3):
            i = 0 if k < 2 else 1
            j = 1 if k == 0 else 2
            li, lj = l[i], l[j]
            J[3 * k + i] = 2 * li - 2 * c[4 * k + 2] * lj + 2 * c[4 * k]
            J[3 * k + j] = 2 * lj - 2 * c[4 * k + 2] * li - 2 * c[4 * k + 1]
        depth_equations(c, l, value)
        largest = 0.0
        for k in range(9):
            largest = max(largest, fabs(J[k]))
        if not fabs(det3(J)) > 1e-14 * largest * largest * largest:
            return
        if not solve_linear(J, value, 3):
            return
        for k in range(3):
            l[k] -= value[k]


cdef int gp3p_depths(const double *v, const double *f, const double *M, double *scale_out, double *depths) noexcept nogil:
    """Positive depth triples (m, 3) of gp3p_unchecked and the world scale; returns m."""
    cdef double sides[9]
    cdef double cr[3]
    cdef double vs[9]
    cdef double Ms[9]
    cdef double vc[3]
    cdef double c[12]
    cdef double F[17]
    cdef double alpha[9]
    cdef double beta[9]
    cdef double roots[16]
    cdef double ys[2]
    cdef double l1s[2]
    cdef double triples[3 * MAX_TRIPLES]
    cdef double value[3]
    cdef double w[3]
    cdef double longest2 = 0.0, longest, area, scale, x, y, ax, bx, p1, q1, p2, q2, size, residual, diff, top
    cdef int i, j, k, r, n_roots, n_y, n_l1, a, b, count = 0, kept = 0
    cdef bint unique
    for k in range(3):
        sides[k] = M[3 + k] - M[k]
        sides[3 + k] = M[6 + k] - M[k]
        sides[6 + k] = M[6 + k] - M[3 + k]
    for i in range(3):
        longest2 = max(longest2, sides[3 * i] ** 2 + sides[3 * i + 1] ** 2 + sides[3 * i + 2] ** 2)
    longest = sqrt(longest2)
    cr[0] = sides[1] * sides[5] - sides[2] * sides[4]
    cr[1] = sides[2] * sides[3] - sides[0] * sides[5]
    cr[2] = sides[0] * sides[4] - sides[1] * sides[3]
    area = 0.5 * sqrt(cr[0] * cr[0] + cr[1] * cr[1] + cr[2] * cr[2])
    if not longest > 0 or area < DEGENERATE_AREA * longest * longest:
        return 0
    scale = longest
    scale_out[0] = scale
    for k in range(3):
        vc[k] = (v[k] + v[3 + k] + v[6 + k]) / 3.0
    for i in range(3):
        for k in range(3):
            vs[3 * i + k] = (v[3 * i + k] - vc[k]) / scale
            Ms[3 * i + k] = M[3 * i + k] / scale
    for r in range(3):
        a = 0 if r < 2 else 1
        b = 1 if r == 0 else 2
        for k in range(3):
            w[k] = vs[3 * a + k] - vs[3 * b + k]
        c[4 * r] = f[3 * a] * w[0] + f[3 * a + 1] * w[1] + f[3 * a + 2] * w[2]
        c[4 * r + 1] = f[3 * b] * w[0] + f[3 * b + 1] * w[1] + f[3 * b + 2] * w[2]
        c[4 * r + 2] = f[3 * a] * f[3 * b] + f[3 * a + 1] * f[3 * b + 1] + f[3 * a + 2] * f[3 * b + 2]
        c[4 * r + 3] = (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
                        - ((Ms[3 * a] - Ms[3 * b]) ** 2 + (Ms[3 * a + 1] - Ms[3 * b + 1]) ** 2
                           + (Ms[3 * a + 2] - Ms[3 * b + 2]) ** 2))
    univariate(c, F, alpha, beta)
    n_roots = real_roots(F, 17, roots)
    for r in range(n_roots):
        x = roots[r]
        ax, bx = poly_val(alpha, 9, x), poly_val(beta, 9, x)
        if fabs(ax) > SMALL_DIVISOR * (fabs(bx) + 1.0):
            ys[0] = -bx / ax
            n_y = 1
        else:
            n_y = quadratic_roots(-2 * c[10] * x - 2 * c[9], x * x + 2 * c[8] * x + c[11], ys)
        for j in range(n_y):
            y = ys[j]
            p1, q1 = 2 * c[0] - 2 * c[2] * x, x * x - 2 * c[1] * x + c[3]
            p2, q2 = 2 * c[4] - 2 * c[6] * y, y * y - 2 * c[5] * y + c[7]
            if fabs(p2 - p1) > SMALL_DIVISOR * (fabs(p1) + fabs(p2) + 1.0):
                l1s[0] = -(q2 - q1) / (p2 - p1)
                n_l1 = 1
            else:
                n_l1 = quadratic_roots(p1, q1, l1s)
            for i in range(n_l1):
                if count < MAX_TRIPLES:
                    triples[3 * count], triples[3 * count + 1], triples[3 * count + 2] = l1s[i], x, y
                    count += 1
    for i in range(count):
        newton(c, &triples[3 * i])
        depth_equations(c, &triples[3 * i], value)
        residual = max(fabs(value[0]), max(fabs(value[1]), fabs(value[2])))
        size = 1.0 + triples[3 * i] ** 2 + triples[3 * i + 1] ** 2 + triples[3 * i + 2] ** 2
        if not (isfinite(residual) and residual <= RESIDUAL_TOLERANCE * size):
            continue
        unique = True
        for j in range(kept):
            diff = 0.0
            top = 0.0
            for k in range(3):
                diff = max(diff, fabs(triples[3 * i + k] - depths[3 * j + k]))
                top = max(top, fabs(depths[3 * j + k]))
            if not diff > UNIQUE_TOLERANCE * (1.0 + top):
                unique = False
                break
        if unique:
            depths[3 * kept], depths[3 * kept + 1], depths[3 * kept + 2] = (
                triples[3 * i], triples[3 * i + 1], triples[3 * i + 2])
            kept += 1
    count = 0
    for i in range(kept):  # positive depths only
        if depths[3 * i] > 0 and depths[3 * i + 1] > 0 and depths[3 * i + 2] > 0:
            for k in range(3):
                depths[3 * count + k] = depths[3 * i + k]
            count += 1
    return count


cdef void absolute_orientation3(const double *M, const double *P, double *R, double *t) noexcept nogil:
    """gp3p.absolute_orientation for three point pairs: R, t with P ~ R M + t."""
    cdef double wm[3]
    cdef double pm[3]
    cdef double X[9]
    cdef int i, j, k
    for k in range(3):
        wm[k] = (M[k] + M[3 + k] + M[6 + k]) / 3.0
        pm[k] = (P[k] + P[3 + k] + P[6 + k]) / 3.0
    for i in range(3):
        for j in range(3):
            X[3 * i + j] = 0.0
            for k in range(3):
                X[3 * i + j] += (P[3 * k + i] - pm[i]) * (M[3 * k + j] - wm[j])
    nearest_rotation(X)
    memcpy(R, X, 9 * sizeof(double))
    for k in range(3):
        t[k] = pm[k] - (R[3 * k] * wm[0] + R[3 * k + 1] * wm[1] + R[3 * k + 2] * wm[2])


cdef int gp3p_poses(const double *v, const double *f, const double *M, double *R, double *t) noexcept nogil:
    """Poses (m, 3, 3), (m, 3) of three correspondences (unit f), positive depths; returns m <= 8."""
    cdef double depths[3 * MAX_TRIPLES]
    cdef double P[9]
    cdef double scale = 1.0
    cdef int m, i, j, k
    m = gp3p_depths(v, f, M, &scale, depths)
    m = min(m, 8)
    for i in range(m):
        for j in range(3):
            for k in range(3):
                P[3 * j + k] = v[3 * j + k] + scale * depths[3 * i + j] * f[3 * j + k]
        absolute_orientation3(M, P, &R[9 * i], &t[3 * i])
    return m


def gp3p(const double[:, ::1] origins, const double[:, ::1] directions, const double[:, ::1] points):
    """gp3p.gp3p_unchecked (positive depths) compiled: rotations (m, 3, 3), translations (m, 3)."""
    R = np.empty((8, 3, 3))
    t = np.empty((8, 3))
    cdef double[:, :, ::1] R_view = R
    cdef double[:, ::1] t_view = t
    cdef int m
    with nogil:
        m = gp3p_poses(&origins[0, 0], &directions[0, 0], &points[0, 0], &R_view[0, 0, 0], &t_view[0, 0])
    return R[:m], t[:m]


def sample_hypotheses(const double[:, ::1] origins, const double[:, ::1] directions, const double[:, ::1] points,
                      const double[::1] threshold, double wide, long i0, long i1, long i2):
    """The gP3P poses of correspondences (i0, i1, i2), their MSAC costs over all correspondences and
    how many of these lie within wide x their threshold: rotations (m, 3, 3), translations (m, 3),
    costs (m,), wide counts (m,)."""
    cdef double v[9]
    cdef double f[9]
    cdef double M[9]
    cdef long idx[3]
    cdef int m, i, k, n = points.shape[0]
    R = np.empty((8, 3, 3))
    t = np.empty((8, 3))
    costs = np.empty(8)
    counts = np.empty(8, dtype=np.intp)
    cdef double[:, :, ::1] R_view = R
    cdef double[:, ::1] t_view = t
    cdef double[::1] cost_view = costs
    cdef Py_ssize_t[::1] count_view = counts
    cdef int count = 0
    idx[0], idx[1], idx[2] = i0, i1, i2
    with nogil:
        for i in range(3):
            for k in range(3):
                v[3 * i + k] = origins[idx[i], k]
                f[3 * i + k] = directions[idx[i], k]
                M[3 * i + k] = points[idx[i], k]
        m = gp3p_poses(v, f, M, &R_view[0, 0, 0], &t_view[0, 0])
        for i in range(m):
            count = 0
            cost_view[i] = msac(&origins[0, 0], &directions[0, 0], &points[0, 0], n, &R_view[i, 0, 0],
                                &t_view[i, 0], &threshold[0], NULL, wide, &count)
            count_view[i] = count
    return R[:m], t[:m], costs[:m], counts[:m]
