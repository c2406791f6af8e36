# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled core of the generalized pose solver: `statistics` and `Kernel.solve_rays` run the steps that
`statistics.py` and `solver.py` describe, without Python in between.

A solve is about a hundred operations on 3 x 3 to 158 x 118 matrices; as numpy calls each costs
a few microseconds of overhead, which dominated the solve. Matrices here are C-ordered doubles
(r = vec(R) row-major, as in `statistics.py`); LAPACK comes from SciPy's `cython_lapack`, which
takes column-major matrices. Every buffer is allocated per call and the solve runs without the
GIL, so one `Kernel` serves several threads at once.
"""

from libc.float cimport DBL_EPSILON, DBL_MIN
from libc.math cimport NAN, acos, fabs, isfinite, sqrt
from libc.stdlib cimport free, malloc
from libc.string cimport memcpy, memset
from scipy.linalg.cython_lapack cimport dsyev

from dmais_pipe.pose._small cimport det3, matmul3, nearest_rotation, solve_linear

import numpy as np

# Roots whose imaginary part is below this (relative to 1 + |q|) are polished as real ones:
# nearly real pairs are where a real double root lost to rounding reappears.
cdef double IMAGINARY_TOLERANCE = 1e-1
# Newton steps on the cost (on SO(3)) that polish every candidate rotation.
cdef int NEWTON_ITERATIONS = 2
# A polished rotation is stationary when its Riemannian gradient is below this fraction of
# trace(H) + |g|.
cdef double STATIONARY_TOLERANCE = 1e-8
# Rotations closer than this (max abs entry difference) are one candidate.
cdef double DUPLICATE_TOLERANCE = 1e-9
# Gauss-Newton steps at most that move the solving frame from its start to a minimum.
cdef int DESCENT_ITERATIONS = 30
# A root whose Newton polish fails is descended from its unpolished value by at most this many
# Gauss-Newton steps and polished again (`settle`), if its Riemannian gradient is below
# SETTLE_GRADIENT (trace H + |g|): in a cluster of nearly repeated roots (or a nearly real pair
# of them) the Hessian is nearly singular and Newton's steps overshoot, while starts far from any
# stationary point (complex pairs taken as real) are left to fail.
cdef int SETTLE_ITERATIONS = 10
cdef double SETTLE_GRADIENT = 1e-2
# Longest descent step (radians).
cdef double MAX_STEP = 0.5
# The descent stops after a step shorter than this (radians); Newton polishing continues.
cdef double STEP_TOLERANCE = 1e-3
# Relative rounding level of the cost evaluated as a quadratic form (of trace H + |g| + |c|).
cdef double COST_ROUNDING = 1e-12
# Front-facing candidates whose costs lie within this many rounding levels of the least are
# compared by their costs summed over the points (`exact_costs`): through a 0.5 deg camera the
# quadratic form is off by up to ~30 levels, as much as two minima may differ.
cdef double TIE_ROUNDINGS = 1e3
# Newton steps at most on the secular equation of the sphere relaxation, and their relative
# tolerance (the relaxed rotations only start the descent).
cdef int SPHERE_ITERATIONS = 30
cdef double SPHERE_TOLERANCE = 1e-6
# Points whose least spread is below this fraction of the middle one are (nearly) planar: the
# sphere relaxation then has a null space, and its planar version joins the starts (thickness
# below 1% of the width).
cdef double PLANAR_SPREAD = 1e-4
# Points whose least spread is below this fraction of the middle one (thickness below 10% of the
# width) are flat enough for the two-fold ambiguity of a plane seen through a narrow field of view:
# the flip of the solution (`flipped`) starts one more descent.
cdef double FLIP_SPREAD = 1e-2
# Beyond 120 deg (|q| > tan(60 deg)) in the solving frame, the problem is solved again in the
# frame of the winner: the cosine of that angle.
cdef double COS_MAX_FRAME_ANGLE = -0.5
# Points on which the solving frame and the candidates are first scored for being in front of
# their rays (every point when n < 2 FRONT_SAMPLE): at 500 points, counting all of them for the
# ~28 frames and ~25 candidates cost more than the template.
cdef int FRONT_SAMPLE = 64
# The dual certificate holds when the least eigenvalue of the Lagrangian's Hessian is above
# -this (trace H + |g| + |c|): the rounding of the quadratic form and of the polished solution.
cdef double CERTIFICATE_TOLERANCE = 1e-9
cdef enum:
    # Room for candidates: 1 frame + 40 roots + 1 descent, 40 more roots, mirrors of the first 42, 1 flip.
    CAPACITY = 256
    N_SOLUTIONS = 40


cdef struct Problem:
    const double *H  # (9, 9)
    const double *g  # (9,)
    double c
    const double *t_matrix  # (3, 9): centred translation t_c(r) = t_matrix r + t_offset
    const double *t_offset  # (3,)
    const double *centroid  # (3,)
    const double *v  # (n, 3) ray origins
    const double *f  # (n, 3) unit ray directions
    const double *M  # (n, 3) world points (not centred)
    int n


cdef struct Candidates:
    double *R  # (CAPACITY, 9) rotations
    double *t  # (CAPACITY, 3) centred translations
    double *cost  # (CAPACITY,)
    double *front  # (CAPACITY,) fraction of points in front


cdef struct Scratch:
    double *coefficients  # (6 * n_monomials,) of the equations
    double *template  # (m * n_columns,) row-major
    int *pivots  # (m,) template rows in pivot order
    int *lead  # (m,) per template row, a column before which the row is zero
    double *reductions  # (n_reducible * 40,) row-major: the reducible monomials in the basis
    double *action  # (40 * 40,) column-major
    Eigen *eigen


# ------------------------------------------------------------------------------ small matrices


cdef inline double trace_product_t(const double *A, const double *B) noexcept nogil:
    """trace(A @ B^T) for (3, 3) A, B."""
    cdef double s = 0.0
    cdef int i
    for i in range(9):
        s += A[i] * B[i]
    return s


cdef inline double angle_between(const double *A, const double *B) noexcept nogil:
    """Angle (rad) of the rotation A @ B^T."""
    cdef double cosine = 0.5 * (trace_product_t(A, B) - 1.0)
    return acos(min(1.0, max(-1.0, cosine)))


cdef void cayley_times(const double *q, const double *R, double *out) noexcept nogil:
    """out = Cayley(q) @ R, q (3,), R (3, 3) (geometry.rotation_from_cayley); out may alias R."""
    cdef double qq = q[0] * q[0] + q[1] * q[1] + q[2] * q[2]
    cdef double s = 1.0 / (1.0 + qq)
    cdef double C[9]
    cdef double tmp[9]
    C[0] = (1.0 - qq + 2.0 * q[0] * q[0]) * s
    C[4] = (1.0 - qq + 2.0 * q[1] * q[1]) * s
    C[8] = (1.0 - qq + 2.0 * q[2] * q[2]) * s
    C[1] = 2.0 * (q[0] * q[1] - q[2]) * s
    C[3] = 2.0 * (q[0] * q[1] + q[2]) * s
    C[2] = 2.0 * (q[0] * q[2] + q[1]) * s
    C[6] = 2.0 * (q[0] * q[2] - q[1]) * s
    C[5] = 2.0 * (q[1] * q[2] - q[0]) * s
    C[7] = 2.0 * (q[1] * q[2] + q[0]) * s
    matmul3(C, R, tmp)
    memcpy(out, tmp, 9 * sizeof(double))


# ------------------------------------------------------------------------------ cost on SO(3)


cdef double cost_of(const Problem *p, const double *R) noexcept nogil:
    """Eq. objfun3: r^T H r - 2 g^T r + c."""
    cdef double total = p.c, row
    cdef int i, j
    for i in range(9):
        row = -2.0 * p.g[i]
        for j in range(9):
            row += p.H[9 * i + j] * R[j]
        total += row * R[i]
    return total


cdef void centred_translation(const Problem *p, const double *R, double *t) noexcept nogil:
    """Optimal translation (eq. t) of the centred world points, t_c = t_matrix r + t_offset."""
    cdef int i, j
    for i in range(3):
        t[i] = p.t_offset[i]
        for j in range(9):
            t[i] += p.t_matrix[9 * i + j] * R[j]


cdef double front_fraction(const Problem *p, const double *R, const double *t, int stride) noexcept nogil:
    """Fraction of points in front of their rays, f_i . (R (M_i - m) + t_c - v_i) > 0, over every
    stride-th point (stride 1: all of them)."""
    cdef int i = 0, a, front = 0, total = 0
    cdef double m[3]
    cdef double depth, x
    while i < p.n:
        for a in range(3):
            m[a] = p.M[3 * i + a] - p.centroid[a]
        depth = 0.0
        for a in range(3):
            x = R[3 * a] * m[0] + R[3 * a + 1] * m[1] + R[3 * a + 2] * m[2] + t[a] - p.v[3 * i + a]
            depth += p.f[3 * i + a] * x
        front += depth > 0.0
        total += 1
        i += stride
    return front / <double> total


cdef double residual_cost(const Problem *p, const double *R, const double *t) noexcept nogil:
    """Eq. objfun at R (3, 3) and the centred translation t (3,), summed over the points, O(n): the
    cost without the rounding of the quadratic form r^T H r - 2 g^T r + c (`cost_of`)."""
    cdef int i, a
    cdef double m[3]
    cdef double x[3]
    cdef double total = 0.0
    for i in range(p.n):
        for a in range(3):
            m[a] = p.M[3 * i + a] - p.centroid[a]
        for a in range(3):
            x[a] = R[3 * a] * m[0] + R[3 * a + 1] * m[1] + R[3 * a + 2] * m[2] + t[a] - p.v[3 * i + a]
        total += ((p.f[3 * i + 1] * x[2] - p.f[3 * i + 2] * x[1]) ** 2 + (p.f[3 * i + 2] * x[0] - p.f[3 * i] * x[2]) ** 2
                  + (p.f[3 * i] * x[1] - p.f[3 * i + 1] * x[0]) ** 2)
    return total


cdef inline int sample_stride(const Problem *p) noexcept nogil:
    """Stride of the fixed subsample (at most 2 FRONT_SAMPLE - 1 points) on which the solving
    frame and the candidates are first scored; `exact_front` then counts every point where it
    decides the solution."""
    return max(1, p.n // FRONT_SAMPLE)


cdef void derivatives(const Problem *p, const double *R, bint newton, double *gradient, double *hessian) noexcept nogil:
    """Half gradient (3,) and half Hessian (3, 3) of w -> cost(exp([w]x) R) at w = 0.

    J_a = vec(G_a R) with G_a = [e_a]x; h = H r - g; gradient J h; Gauss-Newton matrix J H J^T;
    `newton` adds <(G_a G_b + G_b G_a) / 2, A> = (A_ab + A_ba) / 2 - delta_ab trace(A) with
    A = mat(h) R^T (since G_a G_b = e_b e_a^T - (e_a . e_b) I).
    """
    cdef double J[27]
    cdef double h[9]
    cdef double HJ[27]
    cdef double A[9]
    cdef int a, b, i, j
    cdef double s
    for j in range(3):  # rows of G_0 R = (0, -R_2, R_1), G_1 R = (R_2, 0, -R_0), G_2 R = (-R_1, R_0, 0)
        J[j] = 0.0;            J[3 + j] = -R[6 + j];  J[6 + j] = R[3 + j]
        J[9 + j] = R[6 + j];   J[12 + j] = 0.0;       J[15 + j] = -R[j]
        J[18 + j] = -R[3 + j]; J[21 + j] = R[j];      J[24 + j] = 0.0
    for i in range(9):
        s = -p.g[i]
        for j in range(9):
            s += p.H[9 * i + j] * R[j]
        h[i] = s
    for a in range(3):
        s = 0.0
        for i in range(9):
            s += J[9 * a + i] * h[i]
        gradient[a] = s
        for i in range(9):
            s = 0.0
            for j in range(9):
                s += p.H[9 * i + j] * J[9 * a + j]
            HJ[9 * a + i] = s
    for a in range(3):
        for b in range(3):
            s = 0.0
            for i in range(9):
                s += J[9 * a + i] * HJ[9 * b + i]
            hessian[3 * a + b] = s
    if newton:
        for i in range(3):
            for j in range(3):
                A[3 * i + j] = h[3 * i] * R[3 * j] + h[3 * i + 1] * R[3 * j + 1] + h[3 * i + 2] * R[3 * j + 2]
        s = A[0] + A[4] + A[8]
        for a in range(3):
            for b in range(3):
                hessian[3 * a + b] += 0.5 * (A[3 * a + b] + A[3 * b + a]) - (s if a == b else 0.0)


cdef double trace9(const double *H) noexcept nogil:
    cdef double s = 0.0
    cdef int i
    for i in range(9):
        s += H[10 * i]
    return s


cdef inline double statistics_size(const Problem *p) noexcept nogil:
    """trace H + |g|: the scale against which gradients and costs are small."""
    return trace9(p.H) + sqrt(sum_squares(p.g, 9))


cdef void descend(const Problem *p, double *R, int iterations) noexcept nogil:
    """Damped Gauss-Newton descent of the cost on SO(3), R <- exp([w]x) R, from R (3, 3) in place.

    The Gauss-Newton matrix J^T H J is positive semi-definite, so each damped step goes downhill
    even far from a minimum; steps are capped at MAX_STEP radians. Stops after a step shorter
    than STEP_TOLERANCE (`polish` finishes the job).
    """
    cdef double cost = cost_of(p, R), trial_cost, norm, factor
    cdef double damping = 1e-6, scale = trace9(p.H)
    cdef double gradient[3]
    cdef double hessian[9]
    cdef double step[3]
    cdef double trial[9]
    cdef int it, a
    for it in range(iterations):
        derivatives(p, R, False, gradient, hessian)
        for a in range(3):
            hessian[4 * a] += damping * scale
            step[a] = -gradient[a]
        if not solve_linear(hessian, step, 3):
            break
        norm = sqrt(sum_squares(step, 3))
        factor = min(0.5, 0.5 * MAX_STEP / max(norm, 1e-300))
        for a in range(3):
            step[a] *= factor
        cayley_times(step, R, trial)
        trial_cost = cost_of(p, trial)
        if trial_cost <= cost:
            memcpy(R, trial, 9 * sizeof(double))
            cost = trial_cost
            damping /= 10.0
            if norm < STEP_TOLERANCE:
                break
        else:
            damping *= 10.0
            if damping > 1e8:
                break


cdef bint polish(const Problem *p, double *R) noexcept nogil:
    """Newton's method on the cost on SO(3) from R (3, 3), in place: the nearby stationary point.

    Returns whether R is stationary: Riemannian gradient below STATIONARY_TOLERANCE (trace H + |g|)
    before the last step. Starts that are no roots (e.g. a complex pair taken as real) end
    elsewhere, usually not stationary, or on another candidate.
    """
    cdef double scale = statistics_size(p)
    cdef double gradient[3]
    cdef double hessian[9]
    cdef double step[3]
    cdef int it, a
    cdef bint stationary = False
    for it in range(NEWTON_ITERATIONS):
        derivatives(p, R, True, gradient, hessian)
        for a in range(3):
            hessian[4 * a] += 1e-14 * scale
            step[a] = -0.5 * gradient[a]
        stationary = sqrt(sum_squares(gradient, 3)) < STATIONARY_TOLERANCE * scale
        if solve_linear(hessian, step, 3):
            cayley_times(step, R, R)
    return stationary


cdef bint settle(const Problem *p, const double *start, double *R) noexcept nogil:
    """The fallback of a root start (3, 3) whose Newton polish failed: R (3, 3) <- start descended
    by at most SETTLE_ITERATIONS damped Gauss-Newton steps (`descend`, downhill whatever the
    curvature) and polished; returns whether R ends stationary. Starts with a gradient above
    SETTLE_GRADIENT (trace H + |g|) are no roots and are not tried.

    Newton's method converges only where the Hessian stays well away from singular, and between
    the nearly repeated roots of a cluster it is nearly singular: e.g. a minimum and a saddle
    0.02 rad apart that rounding merges into a nearly real complex pair (`real_roots` polishes its
    real part), from which Newton's first step lands 0.25 rad away, or a root 3e-3 rad off that
    needs more than NEWTON_ITERATIONS steps. Whether a cluster comes out as real roots or as such
    a pair depends on the last bits of the template (the solving frame, the BLAS kernel), so
    without this fallback the whole cluster, with the sought minimum, could be lost.
    """
    cdef double gradient[3]
    cdef double hessian[9]
    derivatives(p, start, False, gradient, hessian)
    if not sqrt(sum_squares(gradient, 3)) < SETTLE_GRADIENT * statistics_size(p):
        return False
    memcpy(R, start, 9 * sizeof(double))
    descend(p, R, SETTLE_ITERATIONS)
    return polish(p, R)


cdef inline double sum_squares(const double *x, int d) noexcept nogil:
    cdef double s = 0.0
    cdef int i
    for i in range(d):
        s += x[i] * x[i]
    return s


# ------------------------------------------------------------------------------ frames


cdef void sphere_minimiser(const double *H, const double *g, int d, double radius2, double *x) noexcept nogil:
    """The minimiser x (d,) of x^T H x - 2 g^T x on the sphere |x|^2 = radius2; H (d, d) symmetric.

    The trust-region subproblem: x = (H - mu I)^-1 g with mu below the least eigenvalue of H,
    found by Newton's method on 1/|x(mu)| (More and Sorensen), which is concave and so approached
    monotonically from mu's upper bound |b_0| / sqrt(radius2); in the hard case (g without weight
    on the least eigenvector) x is completed along that eigenvector.
    """
    cdef double V[81]
    cdef double eigenvalues[9]
    cdef double work[256]
    cdef double b[9]
    cdef double gap[9]
    cdef double y[9]
    cdef int lwork = 256, info = 0, i, j, it
    cdef double norm_b, shift, norm, change, denominator
    memcpy(V, H, d * d * sizeof(double))
    dsyev(b"V", b"L", &d, V, &d, eigenvalues, work, &lwork, &info)  # column j of V: vector j
    for j in range(d):
        b[j] = 0.0
        for i in range(d):
            b[j] += V[j * d + i] * g[i]
        gap[j] = eigenvalues[j] - eigenvalues[0]
    norm_b = sqrt(sum_squares(b, d))
    y[0] = 0.0
    for j in range(1, d):
        y[j] = b[j] / max(gap[j], 1e-300)
    if sum_squares(y, d) < radius2 and fabs(b[0]) <= 1e-12 * norm_b:
        y[0] = sqrt(radius2 - sum_squares(y, d))
    else:
        shift = max(fabs(b[0]), 1e-300) / sqrt(radius2)
        for it in range(SPHERE_ITERATIONS):
            denominator = 0.0
            for j in range(d):
                y[j] = b[j] / (gap[j] + shift)
                denominator += y[j] * y[j] / (gap[j] + shift)
            norm = sqrt(sum_squares(y, d))
            change = (1.0 / norm - 1.0 / sqrt(radius2)) * norm * norm * norm / denominator
            shift = max(shift - change, 0.5 * shift)
            if fabs(change) <= SPHERE_TOLERANCE * shift:
                break
        for j in range(d):
            y[j] = b[j] / (gap[j] + shift)
    for i in range(d):
        x[i] = 0.0
        for j in range(d):
            x[i] += V[j * d + i] * y[j]


cdef void in_frame(const double *H, const double *g, const double *P, double *H_out, double *g_out) noexcept nogil:
    """H', g' of the world M' = P M (R = R' P): blocks H'_ac = P H_ac P^T, g'_a = P g_a."""
    cdef int a, c, i, j, k, l
    cdef double s
    for a in range(3):
        for c in range(3):
            for j in range(3):
                for l in range(3):
                    s = 0.0
                    for i in range(3):
                        for k in range(3):
                            s += P[3 * j + i] * H[9 * (3 * a + i) + 3 * c + k] * P[3 * l + k]
                    H_out[9 * (3 * a + j) + 3 * c + l] = s
        for j in range(3):
            g_out[3 * a + j] = P[3 * j] * g[3 * a] + P[3 * j + 1] * g[3 * a + 1] + P[3 * j + 2] * g[3 * a + 2]


cdef int relaxed_rotations(const Problem *p, const double *axes, const double *spread, double *out) noexcept nogil:
    """Rotations (2 or 4, 3, 3) near the minimum, written to out; returns their count.

    From the sphere relaxation |vec R|^2 = 3 of eq. objfun3 and, for (nearly) planar points, from
    its planar version (R on the two widest principal axes of the points, which alone matter for
    planar points, |.|^2 = 2, completed by their cross product), each with its mirror. O(1).
    """
    cdef double trace = trace9(p.H)
    cdef double Hn[81]
    cdef double gn[9]
    cdef double Hf[81]
    cdef double gf[9]
    cdef double Hs[36]
    cdef double gs[6]
    cdef double x[9]
    cdef double axes_t[9]
    cdef double Rp[9]
    cdef double y[6]
    cdef int plane[6]
    cdef int i, j, k, sign, count = 2
    plane[:] = [1, 2, 4, 5, 7, 8]
    for i in range(81):
        Hn[i] = p.H[i] / trace
    for i in range(9):
        gn[i] = p.g[i] / trace
    sphere_minimiser(Hn, gn, 9, 3.0, x)
    for i in range(9):
        out[i] = x[i]
        out[9 + i] = -x[i]
    if spread[0] < PLANAR_SPREAD * spread[1]:
        for i in range(3):
            for j in range(3):
                axes_t[3 * i + j] = axes[3 * j + i]
        in_frame(Hn, gn, axes_t, Hf, gf)
        for i in range(6):
            gs[i] = gf[plane[i]]
            for j in range(6):
                Hs[6 * i + j] = Hf[9 * plane[i] + plane[j]]
        sphere_minimiser(Hs, gs, 6, 2.0, y)
        for k in range(2):
            sign = 1 - 2 * k
            for i in range(3):  # rows of R' = [a x b, a, b] with a = y[0::2], b = y[1::2]
                Rp[3 * i + 1] = sign * y[2 * i]
                Rp[3 * i + 2] = sign * y[2 * i + 1]
            Rp[0] = Rp[4] * Rp[8] - Rp[7] * Rp[5]
            Rp[3] = Rp[7] * Rp[2] - Rp[1] * Rp[8]
            Rp[6] = Rp[1] * Rp[5] - Rp[4] * Rp[2]
            matmul3(Rp, axes_t, out + 9 * (2 + k))
        count = 4
    for k in range(count):
        nearest_rotation(out + 9 * k)
    return count


cdef double rounding_level(const Problem *p) noexcept nogil:
    return COST_ROUNDING * (statistics_size(p) + fabs(p.c))


cdef void solving_frame(const Problem *p, const double *octahedral, const double *axes, const double *spread,
                       double *P) noexcept nogil:
    """Rotation P (3, 3) near the sought rotation: the most promising of the octahedral group and
    the relaxed rotations.

    The cost alone misleads: it ignores on which side of its ray origin a point lies, and a
    "mirror" pose with the points behind the cameras, about 180 deg from the truth, often costs
    less than the octahedral rotations near the truth. So each rotation's cost is weighted by the
    fraction of points it puts behind their rays (plus 0.05, so that cost still decides among
    rotations that put every point in front); costs below the rounding level of the quadratic
    form count as that level, so that an exact fit and its mirror are told apart. O(n).
    """
    cdef double starts[9 * 28]
    cdef double t[3]
    cdef int count = 24 + relaxed_rotations(p, axes, spread, starts + 9 * 24)
    cdef double rounding = rounding_level(p)
    cdef int stride = sample_stride(p)
    cdef double score, best_score = 0.0
    cdef int k, best = 0
    memcpy(starts, octahedral, 9 * 24 * sizeof(double))
    for k in range(count):
        centred_translation(p, starts + 9 * k, t)
        score = max(cost_of(p, starts + 9 * k), rounding) * (1.0 - front_fraction(p, starts + 9 * k, t, stride) + 0.05)
        if k == 0 or score < best_score:
            best, best_score = k, score
    memcpy(P, starts + 9 * best, 9 * sizeof(double))


# ------------------------------------------------------------------------------ the solver


cdef struct Eigen:
    double H[N_SOLUTIONS * N_SOLUTIONS]  # the balanced Hessenberg form, row-major
    double units[4 * N_SOLUTIONS]  # rows of the back-transformation at the unit monomials, (4, 40)
    double wr[N_SOLUTIONS]
    double wi[N_SOLUTIONS]
    double size  # the largest entry of H


cdef int action_eigenvalues(double *A, const long *unit_index, Eigen *e) noexcept nogil:
    """Eigenvalues e.wr + i e.wi of the column-major action matrix A (40, 40), which is overwritten,
    and what `eigenvector_units` needs: e.H, the Hessenberg form of the balanced A (A = D Q H Q^T
    D^-1, `balance`, `hessenberg`), and e.units, the rows of D Q at the monomials 1, qx, qy, qz.
    The QR iteration (`hessenberg_eigenvalues`) seeks eigenvalues alone. Returns 0 on success.

    Written out rather than LAPACK's dgebal, dgehrd and dhseqr: at n = 40 those spend about as
    much on their calls per element (dlarfg, dlapy2, dlamch, lsame) as on arithmetic."""
    cdef int n = N_SOLUTIONS, i, j, k
    cdef double scale[N_SOLUTIONS]
    cdef double tau[N_SOLUTIONS]
    cdef double reflectors[N_SOLUTIONS * N_SOLUTIONS]
    cdef double x[N_SOLUTIONS]
    cdef double dot
    balance(A, n, scale)
    hessenberg(A, n, reflectors, tau)
    e.size = 0.0
    for i in range(n):  # row-major, for the row operations of `eigenvector_units`
        for j in range(n):
            e.H[i * n + j] = A[j * n + i]
            e.size = max(e.size, fabs(A[j * n + i]))
    for i in range(4):  # row u of D Q is scale_u (Q^T e_u)^T, Q^T = H_{n-3} ... H_0
        memset(x, 0, n * sizeof(double))
        x[unit_index[i]] = 1.0
        for k in range(n - 2):
            dot = 0.0
            for j in range(k + 1, n):
                dot += reflectors[k * n + j] * x[j]
            dot *= tau[k]
            for j in range(k + 1, n):
                x[j] -= dot * reflectors[k * n + j]
        for j in range(n):
            e.units[i * n + j] = scale[unit_index[i]] * x[j]
    return hessenberg_eigenvalues(A, n, e.wr, e.wi)


cdef inline double strided_sum_squares(const double *x, int count, int stride) noexcept nogil:
    """Sum of x[k * stride]^2 over k < count, in four partial sums (a single sum waits on its
    additions' latency)."""
    cdef double s0 = 0.0, s1 = 0.0, s2 = 0.0, s3 = 0.0
    cdef int k = 0
    while k + 4 <= count:
        s0 += x[k * stride] * x[k * stride]
        s1 += x[(k + 1) * stride] * x[(k + 1) * stride]
        s2 += x[(k + 2) * stride] * x[(k + 2) * stride]
        s3 += x[(k + 3) * stride] * x[(k + 3) * stride]
        k += 4
    while k < count:
        s0 += x[k * stride] * x[k * stride]
        k += 1
    return (s0 + s1) + (s2 + s3)


cdef void balance(double *A, int n, double *scale) noexcept nogil:
    """Balance the column-major A (n, n) in place, A <- D^-1 A D with D = diag(scale) in powers of
    2, so that each row and column have similar off-diagonal 2-norms (Parlett and Reinsch 1969; the
    2-norms as in LAPACK's dgebal since 3.5.0, with which the roots here are ~5x more accurate than
    with 1-norms): eigenvalues are then computed to an accuracy relative to the balanced norm. The
    norms are summed in four parts (`strided_sum_squares`): they only choose powers of 2, which the
    order of the additions changes only at an exact tie."""
    cdef int i, j
    cdef double column, row, target, factor, total
    cdef bint converged = False
    cdef int sweeps = 0
    for i in range(n):
        scale[i] = 1.0
    while not converged and sweeps < 100:
        converged = True
        sweeps += 1
        for i in range(n):
            column = sqrt(strided_sum_squares(A + i * n, i, 1) + strided_sum_squares(A + i * n + i + 1, n - i - 1, 1))
            row = sqrt(strided_sum_squares(A + i, i, n) + strided_sum_squares(A + (i + 1) * n + i, n - i - 1, n))
            if column == 0.0 or row == 0.0:
                continue
            total = column + row
            factor = 1.0
            target = row / 2.0
            while column < target and factor < 1e100:
                factor *= 2.0
                column *= 4.0
            target = row * 2.0
            while column >= target and factor > 1e-100:
                factor /= 2.0
                column /= 4.0
            if (column + row) / factor < 0.95 * total:  # column scaled by f, row by 1/f
                converged = False
                scale[i] *= factor
                for j in range(n):
                    A[i * n + j] *= factor
                    A[j * n + i] /= factor


cdef void hessenberg(double *A, int n, double *reflectors, double *tau) noexcept nogil:
    """Reduce the column-major A (n, n) in place to upper Hessenberg form Q^T A Q by Householder
    reflections H_k = I - tau_k v_k v_k^T (k < n - 2), Q = H_0 ... H_{n-3}; column k of the
    column-major reflectors (n, n) holds v_k (zero above k + 1, 1 at k + 1). Below the
    subdiagonal, A ends exactly zero."""
    cdef int i, j, k
    cdef double alpha, tail, norm, beta, inverse, dot
    cdef double w[N_SOLUTIONS]
    cdef double *v
    cdef double *column
    for k in range(n - 2):
        v = reflectors + k * n
        memset(v, 0, n * sizeof(double))
        alpha = A[k * n + k + 1]
        tail = 0.0
        for i in range(k + 2, n):
            tail += A[k * n + i] * A[k * n + i]
        tau[k] = 0.0
        v[k + 1] = 1.0
        if tail == 0.0:
            continue
        norm = sqrt(alpha * alpha + tail)
        beta = -norm if alpha >= 0.0 else norm
        tau[k] = (beta - alpha) / beta
        inverse = 1.0 / (alpha - beta)
        for i in range(k + 2, n):
            v[i] = A[k * n + i] * inverse
            A[k * n + i] = 0.0
        A[k * n + k + 1] = beta
        j = k + 1
        while j + 4 <= n:  # A <- H_k A, four columns at a time: four independent sums, each in order
            update_four_columns(A + j * n, n, k + 1, v, tau[k])
            j += 4
        while j < n:  # the remaining columns
            column = A + j * n
            dot = 0.0
            for i in range(k + 1, n):
                dot += v[i] * column[i]
            dot *= tau[k]
            for i in range(k + 1, n):
                column[i] -= dot * v[i]
            j += 1
        memset(w, 0, n * sizeof(double))  # A <- A H_k: w = A v, A -= tau w v^T
        for j in range(k + 1, n):
            column = A + j * n
            for i in range(n):
                w[i] += column[i] * v[j]
        for j in range(k + 1, n):
            column = A + j * n
            dot = tau[k] * v[j]
            for i in range(n):
                column[i] -= dot * w[i]


cdef inline void update_four_columns(double *A, int n, int start, const double *v, double tau) noexcept nogil:
    """Columns c = 0..3 of the column-major A (n, 4) <- (I - tau v v^T) column, on rows start..n.
    The four dot products run side by side (each summed in order, so the roundings are those of
    one at a time): a single sum waits on its additions' latency."""
    cdef double *c0 = A
    cdef double *c1 = A + n
    cdef double *c2 = A + 2 * n
    cdef double *c3 = A + 3 * n
    cdef double d0 = 0.0, d1 = 0.0, d2 = 0.0, d3 = 0.0
    cdef int i
    for i in range(start, n):
        d0 += v[i] * c0[i]
        d1 += v[i] * c1[i]
        d2 += v[i] * c2[i]
        d3 += v[i] * c3[i]
    d0 *= tau
    d1 *= tau
    d2 *= tau
    d3 *= tau
    for i in range(start, n):
        c0[i] -= d0 * v[i]
        c1[i] -= d1 * v[i]
        c2[i] -= d2 * v[i]
        c3[i] -= d3 * v[i]


cdef int hessenberg_eigenvalues(double *A, int n, double *wr, double *wi) noexcept nogil:
    """Eigenvalues wr + i wi (n,) of the column-major upper Hessenberg A (n, n), destroyed: the
    Francis double-shift QR iteration on the unreduced trailing block, without accumulating the
    Schur form (Golub and Van Loan, Matrix Computations, 7.5), with exceptional shifts every 10th
    iteration. Complex pairs come with the positive imaginary part first. Returns 0, or -1 when
    an eigenvalue takes more than 30 iterations."""
    cdef int hi = n - 1, low, k, j, i, rows, its = 0
    cdef double norm = 0.0, s, trace, det, x, y, z, beta, tau, v1, v2, inverse, p, h11
    cdef double *column
    cdef double *next_column
    cdef double *third
    cdef double *entry
    for i in range(n * n):
        norm = max(norm, fabs(A[i]))
    while hi >= 0:
        low = hi
        while low > 0 and not negligible_subdiagonal(A, n, low, norm):  # the unreduced trailing block is low..hi
            low -= 1
        if low > 0:
            A[(low - 1) * n + low] = 0.0
        if low == hi:
            wr[hi], wi[hi] = A[hi * n + hi], 0.0
            hi -= 1
            its = 0
            continue
        if low == hi - 1:
            two_by_two_eigenvalues(A[(hi - 1) * n + hi - 1], A[hi * n + hi - 1], A[(hi - 1) * n + hi], A[hi * n + hi],
                                   wr + hi - 1, wi + hi - 1)
            hi -= 2
            its = 0
            continue
        if its == 30:
            return -1
        its += 1
        if its % 10 == 0:  # exceptional shift, as in EISPACK's hqr
            s = fabs(A[(hi - 1) * n + hi]) + fabs(A[(hi - 2) * n + hi - 1])
            h11 = 0.75 * s + A[hi * n + hi]
            trace = 2.0 * h11
            det = h11 * h11 + 0.4375 * s * s
        else:  # the eigenvalues of the trailing 2 x 2 block
            trace = A[(hi - 1) * n + hi - 1] + A[hi * n + hi]
            det = A[(hi - 1) * n + hi - 1] * A[hi * n + hi] - A[hi * n + hi - 1] * A[(hi - 1) * n + hi]
        # first column of (A - s1 I)(A - s2 I), then the bulge chased down to hi
        x = A[low * n + low] * A[low * n + low] + A[(low + 1) * n + low] * A[low * n + low + 1] - trace * A[low * n + low] + det
        y = A[low * n + low + 1] * (A[low * n + low] + A[(low + 1) * n + low + 1] - trace)
        z = A[low * n + low + 1] * A[(low + 1) * n + low + 2]
        for k in range(low, hi):
            rows = 3 if k + 2 <= hi else 2
            if k > low:
                x = A[(k - 1) * n + k]
                y = A[(k - 1) * n + k + 1]
                z = A[(k - 1) * n + k + 2] if rows == 3 else 0.0
            s = fabs(x) + fabs(y) + fabs(z)
            if s == 0.0:
                continue
            x, y, z = x / s, y / s, z / s
            beta = sqrt(x * x + y * y + z * z)
            if x >= 0.0:
                beta = -beta
            tau = (beta - x) / beta
            inverse = 1.0 / (x - beta)
            v1, v2 = y * inverse, z * inverse
            if k > low:
                A[(k - 1) * n + k] = beta * s
                A[(k - 1) * n + k + 1] = 0.0
                if rows == 3:
                    A[(k - 1) * n + k + 2] = 0.0
            # through pointers: indices computed in C int under -fwrapv keep GCC from vectorizing
            column = A + k * n
            if rows == 3:
                entry = column + k  # A[k, k]
                for j in range(k, hi + 1):  # rows k..k+2 <- (I - tau u u^T) rows, u = (1, v1, v2)
                    p = tau * (entry[0] + v1 * entry[1] + v2 * entry[2])
                    entry[0] -= p
                    entry[1] -= p * v1
                    entry[2] -= p * v2
                    entry += n
                next_column, third = column + n, column + 2 * n
                for i in range(low, min(k + 3, hi) + 1):  # columns k..k+2 <- columns (I - tau u u^T)
                    p = tau * (column[i] + v1 * next_column[i] + v2 * third[i])
                    column[i] -= p
                    next_column[i] -= p * v1
                    third[i] -= p * v2
            else:
                entry = column + k  # A[k, k]
                for j in range(k, hi + 1):
                    p = tau * (entry[0] + v1 * entry[1])
                    entry[0] -= p
                    entry[1] -= p * v1
                    entry += n
                next_column = column + n
                for i in range(low, hi + 1):
                    p = tau * (column[i] + v1 * next_column[i])
                    column[i] -= p
                    next_column[i] -= p * v1
    return 0


cdef inline bint negligible_subdiagonal(const double *A, int n, int k, double norm) noexcept nogil:
    """Whether the subdiagonal entry A[k, k - 1] of the column-major Hessenberg A (n, n) can be set to
    zero: below the rounding of its diagonal neighbours, and by the conservative test of Ahues and
    Tisseur (LAPACK Working Note 122, 1997), which keeps small eigenvalues of graded matrices (the
    action variable is small near the solving frame) to a relative accuracy."""
    cdef double sub = fabs(A[(k - 1) * n + k]), sup = fabs(A[k * n + k - 1])
    cdef double diagonal = fabs(A[(k - 1) * n + k - 1]) + fabs(A[k * n + k])
    cdef double ab, ba, aa, bb, difference
    if sub <= DBL_MIN:
        return True
    if diagonal == 0.0:
        diagonal = norm
    if sub > DBL_EPSILON * diagonal:
        return False
    difference = fabs(A[(k - 1) * n + k - 1] - A[k * n + k])
    ab, ba = max(sub, sup), min(sub, sup)
    aa, bb = max(fabs(A[k * n + k]), difference), min(fabs(A[k * n + k]), difference)
    return ba * (ab / (aa + ab)) <= max(DBL_MIN, DBL_EPSILON * (bb * (aa / (aa + ab))))


cdef void two_by_two_eigenvalues(double a, double b, double c, double d, double *wr, double *wi) noexcept nogil:
    """Eigenvalues wr + i wi (2,) of [[a, b], [c, d]]; a complex pair with the positive imaginary
    part first. The second of two real ones is formed from the product, without cancellation."""
    cdef double p = 0.5 * (a - d), q, z
    q = p * p + b * c
    if q >= 0.0:
        z = p + (sqrt(q) if p >= 0.0 else -sqrt(q))
        wr[0] = d + z
        wr[1] = d - b * c / z if z != 0.0 else d
        wi[0] = wi[1] = 0.0
    else:
        wr[0] = wr[1] = d + p
        wi[0] = sqrt(-q)
        wi[1] = -wi[0]


cdef void eigenvector_units(const Eigen *e, const double *shifts, int count, double *v) noexcept nogil:
    """v (count, 4): for each real shift (count,), the entries at 1, qx, qy, qz of the eigenvector
    of the action matrix for the eigenvalue nearest it, by one step of inverse iteration on the
    Hessenberg form, y = (H - shift I)^-1 1 (`shifted_lu`), mapped back by e.units.

    Four shifts go through the back substitution U^-1 y side by side: each is summed in order
    (the roundings of one at a time), but a single sum waits on its additions' latency. A last
    group of fewer than four repeats its first shift's factors (the same values, written twice).
    """
    cdef int n = N_SOLUTIONS, g, s, i, j, k, slot
    cdef double *factors[4]
    cdef double *vectors[4]
    cdef double U[4 * N_SOLUTIONS * N_SOLUTIONS]
    cdef double y[4 * N_SOLUTIONS]
    cdef double *u0
    cdef double *u1
    cdef double *u2
    cdef double *u3
    cdef double *y0
    cdef double *y1
    cdef double *y2
    cdef double *y3
    cdef double t0, t1, t2, t3
    for g in range(0, count, 4):
        for s in range(min(4, count - g)):
            shifted_lu(e, shifts[g + s], U + s * n * n, y + s * n)
        for s in range(4):
            slot = s if g + s < count else 0
            factors[s], vectors[s] = U + slot * n * n, y + slot * n
        u0, u1, u2, u3 = factors[0], factors[1], factors[2], factors[3]
        y0, y1, y2, y3 = vectors[0], vectors[1], vectors[2], vectors[3]
        for k in range(n - 1, -1, -1):  # U^-1 y
            t0, t1, t2, t3 = y0[k], y1[k], y2[k], y3[k]
            for j in range(k + 1, n):
                t0 -= u0[k * n + j] * y0[j]
                t1 -= u1[k * n + j] * y1[j]
                t2 -= u2[k * n + j] * y2[j]
                t3 -= u3[k * n + j] * y3[j]
            y0[k] = t0 / u0[k * n + k]
            y1[k] = t1 / u1[k * n + k]
            y2[k] = t2 / u2[k * n + k]
            y3[k] = t3 / u3[k * n + k]
        for s in range(min(4, count - g)):
            v[4 * (g + s)] = v[4 * (g + s) + 1] = v[4 * (g + s) + 2] = v[4 * (g + s) + 3] = 0.0
            for j in range(n):  # the four sums side by side, each in order
                for i in range(4):
                    v[4 * (g + s) + i] += e.units[i * n + j] * y[s * n + j]


cdef void shifted_lu(const Eigen *e, double shift, double *U, double *y) noexcept nogil:
    """U (40, 40) row-major upper triangular and y (40,) with U^-1 y = (H - shift I)^-1 1 for the
    Hessenberg form e.H (`eigenvector_units`).

    LU with partial pivoting of a Hessenberg matrix takes rows in order: at step k the pivot is
    either the row carried from step k - 1 or row k + 1 of H - shift I, and the other, minus a
    multiple of the pivot, is carried on; the pivot rows form U (row-major, O(40^2), contiguous
    row operations). A zero pivot is raised to 1e-30 of the largest entry of H: the least pivot is
    ~0 at an eigenvalue, and raising it to the rounding level (1e-15) would cost digits of the vector.
    """
    cdef int n = N_SOLUTIONS, i, j, k
    cdef double carry[N_SOLUTIONS]
    cdef const double *below
    cdef double *pivot
    cdef double tiny = max(e.size + fabs(shift), 1e-300) * 1e-30, factor, tmp
    memcpy(carry, e.H, n * sizeof(double))
    carry[0] -= shift
    for i in range(n):
        y[i] = 1.0
    for k in range(n):
        pivot = U + k * n
        if k + 1 < n:
            below = e.H + (k + 1) * n  # row k + 1 of H - shift I: zero before column k
            if fabs(below[k]) > fabs(carry[k]):
                for j in range(k, n):
                    pivot[j] = below[j]
                pivot[k + 1] -= shift
                if fabs(pivot[k]) < tiny:
                    pivot[k] = tiny
                factor = carry[k] / pivot[k]
                for j in range(k + 1, n):
                    carry[j] -= factor * pivot[j]
                tmp = y[k]; y[k] = y[k + 1]; y[k + 1] = tmp - factor * y[k]
                continue
            memcpy(pivot + k, carry + k, (n - k) * sizeof(double))
            if fabs(pivot[k]) < tiny:
                pivot[k] = tiny
            factor = below[k] / pivot[k]
            for j in range(k + 1, n):
                carry[j] = below[j] - factor * pivot[j]
            carry[k + 1] -= shift
            y[k + 1] -= factor * y[k]
        else:
            pivot[k] = carry[k] if fabs(carry[k]) >= tiny else tiny


cdef bint eliminate(double *T, int m, int n_columns, int *order, const int *lead) noexcept nogil:
    """Gaussian elimination with partial pivoting of the first m columns of the row-major template
    T (m, n_columns), in place; order (m,) receives the rows in pivot order (row order[k] has its
    pivot in column k and zeros before it). False if a column has no nonzero pivot. lead (m,):
    for each row, a column before which it is zero in T (the template's structure).

    The template is sparse (a fifth of its entries are nonzero, and rows end where their
    monomials do), so rows with a zero in the pivot column are skipped and fill-in stays small:
    about 1e5 multiply-adds instead of the 8e5 of a dense LU (dgetrf), for the same pivots.
    A row is not even read before column lead[row]: until then no row operation reaches it (those
    touch rows that are nonzero in the pivot column), so it stays zero there.
    """
    cdef int i, j, k, best, swap
    cdef double largest, size, factor
    cdef double *pivot_row
    cdef double *row
    for i in range(m):
        order[i] = i
    for k in range(m):
        best, largest = -1, 0.0
        for i in range(k, m):
            if lead[order[i]] > k:
                continue
            size = fabs(T[order[i] * n_columns + k])
            if size > largest:
                best, largest = i, size
        if best < 0 or not isfinite(largest):
            return False
        swap = order[k]; order[k] = order[best]; order[best] = swap
        pivot_row = T + order[k] * n_columns
        for i in range(k + 1, m):
            if lead[order[i]] > k:
                continue
            row = T + order[i] * n_columns
            if row[k] != 0.0:
                factor = row[k] / pivot_row[k]
                row[k] = 0.0
                for j in range(k + 1, n_columns):
                    row[j] -= factor * pivot_row[j]
    return True


cdef void reduce_to_basis(const double *T, int m, int n_columns, int n_reducible, const int *order,
                          double *X) noexcept nogil:
    """X (n_reducible, n_columns - m), row-major: the reducible monomials R in the basis B, from the
    last n_reducible pivot rows of the eliminated template T (`eliminate`), U_RR R + U_RB B = 0
    read as R = U_RR^-1 U_RB B (the sign is the caller's), by back substitution."""
    cdef int a, b, j, first = m - n_reducible, n_basis = n_columns - m
    cdef const double *row
    cdef double factor
    for a in range(n_reducible - 1, -1, -1):
        row = T + order[first + a] * n_columns
        memcpy(X + a * n_basis, row + m, n_basis * sizeof(double))
        for b in range(a + 1, n_reducible):
            factor = row[first + b]
            if factor != 0.0:
                for j in range(n_basis):
                    X[a * n_basis + j] -= factor * X[b * n_basis + j]
        factor = 1.0 / row[first + a]
        for j in range(n_basis):
            X[a * n_basis + j] *= factor


def action_matrix_eigen(const double[:, ::1] A, units=(0, 1, 2, 3)):
    """Eigenvalues (40,) complex of A (40, 40) by `action_eigenvalues`, and for each real shift in
    them the `eigenvector_units` at the rows `units` (4,), as (40, 4) (NaN where complex); None
    if the QR iteration fails. For tests: the solver calls these without Python."""
    cdef double M[N_SOLUTIONS * N_SOLUTIONS]
    cdef long rows[4]
    cdef Eigen e
    cdef double v[4]
    cdef int i, j
    if A.shape[0] != N_SOLUTIONS or A.shape[1] != N_SOLUTIONS:
        raise ValueError(f"A must be ({N_SOLUTIONS}, {N_SOLUTIONS})")
    for i in range(4):
        rows[i] = units[i]
    for i in range(N_SOLUTIONS):
        for j in range(N_SOLUTIONS):
            M[j * N_SOLUTIONS + i] = A[i, j]
    if action_eigenvalues(M, rows, &e) != 0:
        return None
    values = np.array([complex(e.wr[i], e.wi[i]) for i in range(N_SOLUTIONS)])
    vectors = np.full((N_SOLUTIONS, 4), np.nan)
    for i in range(N_SOLUTIONS):
        if e.wi[i] == 0.0:
            eigenvector_units(&e, &e.wr[i], 1, v)
            vectors[i] = [v[0], v[1], v[2], v[3]]
    return values, vectors


cdef bint unit_directions(const double *v, const double *d, const double *M, int n, double zero, double *f) noexcept nogil:
    """f (n, 3): the directions d (n, 3) scaled to unit length; False if any of v, d, M (n, 3) is not
    finite or a direction is shorter than zero."""
    cdef int i, a
    cdef double norm
    for i in range(3 * n):
        if not (isfinite(v[i]) and isfinite(M[i])):
            return False
    for i in range(n):
        norm = sqrt(d[3 * i] * d[3 * i] + d[3 * i + 1] * d[3 * i + 1] + d[3 * i + 2] * d[3 * i + 2])
        if not (isfinite(norm) and norm >= zero):
            return False
        for a in range(3):
            f[3 * i + a] = d[3 * i + a] / norm
    return True


cdef class Kernel:
    """The solver with its elimination template (`solver.runtime`); `solve_rays` runs the steps of
    `solver.py`. Holds only constants; every buffer is allocated per call."""

    cdef int m, n_columns, n_reducible, n_entries, n_monomials
    cdef long[::1] target, source, shift_rows, shift_columns, reduced_rows, reduced_index, unit_index, row_lead
    cdef long[:, ::1] entries
    cdef double[::1] octahedral

    def __init__(self, int m, int n_columns, int n_reducible, target, source, shift_rows, shift_columns,
                 reduced_rows, reduced_index, unit_index, entries, int n_monomials, octahedral):
        """Template shape and index arrays as in `solver._Runtime`; entries (k, 4): the
        (equation, monomial, parameter, value) of `_equations.ENTRIES`; octahedral (24, 3, 3)."""
        self.m, self.n_columns, self.n_reducible = m, n_columns, n_reducible
        self.target = np.ascontiguousarray(target, dtype=np.int64)
        self.source = np.ascontiguousarray(source, dtype=np.int64)
        self.shift_rows = np.ascontiguousarray(shift_rows, dtype=np.int64)
        self.shift_columns = np.ascontiguousarray(shift_columns, dtype=np.int64)
        self.reduced_rows = np.ascontiguousarray(reduced_rows, dtype=np.int64)
        self.reduced_index = np.ascontiguousarray(reduced_index, dtype=np.int64)
        self.unit_index = np.ascontiguousarray(unit_index, dtype=np.int64)
        self.entries = np.ascontiguousarray(entries, dtype=np.int64)
        self.n_entries = len(entries)
        self.n_monomials = n_monomials
        targets = np.asarray(self.target)
        lead = np.full(m, n_columns, dtype=np.int64)  # each row's first structurally nonzero column
        np.minimum.at(lead, targets // n_columns, targets % n_columns)
        self.row_lead = lead
        self.octahedral = np.ascontiguousarray(octahedral, dtype=float).reshape(-1)
        if self.octahedral.shape[0] != 9 * 24:
            raise ValueError("octahedral must be (24, 3, 3)")

    cdef int real_roots(self, const Problem *p, const double *P, double *rotations, Scratch *scratch) noexcept nogil:
        """Rotations Cayley(q) P (k, 3, 3) for the real and nearly real roots q of eq. EF6 in the
        frame P, written to rotations; returns k.

        Row i of the action matrix expresses x * b_i in the basis: x * B(q) = M B(q) at every
        solution q. Gaussian elimination of the whole template [C_E C_R | C_B] (`eliminate`) leaves
        the rows of the reducible monomials R alone at the bottom: U_RR R + U_RB B = 0.
        The eigenvalues come from `action_eigenvalues`, and of the eigenvectors B(q) only the
        entries at 1, qx, qy, qz, which give q (`eigenvector_units`).
        """
        cdef double Hf[81]
        cdef double gf[9]
        cdef double parameters[54]
        cdef double q[3]
        cdef int i, j, k, info = 0, count = 0
        cdef int m = self.m, n_columns = self.n_columns, n_red = self.n_reducible, n = N_SOLUTIONS
        cdef double trace
        cdef double *coefficients = scratch.coefficients
        cdef double *template = scratch.template
        cdef double *action = scratch.action
        cdef Eigen *eigen = scratch.eigen
        cdef double shifts[N_SOLUTIONS]
        cdef double v[4 * N_SOLUTIONS]
        cdef int n_shifts = 0
        in_frame(p.H, p.g, P, Hf, gf)
        trace = trace9(Hf)
        k = 0
        for i in range(9):
            for j in range(i, 9):
                parameters[k] = Hf[9 * i + j] / trace
                k += 1
        for i in range(9):
            parameters[45 + i] = gf[i] / trace
        memset(coefficients, 0, 6 * self.n_monomials * sizeof(double))
        for k in range(self.n_entries):
            coefficients[self.entries[k, 0] * self.n_monomials + self.entries[k, 1]] += \
                self.entries[k, 3] * parameters[self.entries[k, 2]]
        memset(template, 0, m * n_columns * sizeof(double))
        for k in range(self.target.shape[0]):
            template[self.target[k]] = coefficients[self.source[k]]
        for i in range(m):
            scratch.lead[i] = self.row_lead[i]
        if not eliminate(template, m, n_columns, scratch.pivots, scratch.lead):
            return 0
        reduce_to_basis(template, m, n_columns, n_red, scratch.pivots, scratch.reductions)
        memset(action, 0, n * n * sizeof(double))
        for k in range(self.shift_rows.shape[0]):  # action matrix, column-major
            action[self.shift_columns[k] * n + self.shift_rows[k]] = 1.0
        for k in range(self.reduced_rows.shape[0]):
            for j in range(n):
                action[j * n + self.reduced_rows[k]] = -scratch.reductions[self.reduced_index[k] * n + j]
        if action_eigenvalues(action, &self.unit_index[0], eigen) != 0:
            return 0
        for j in range(n):
            # nearly real roots, one of each conjugate pair, are polished as real ones
            if eigen.wi[j] >= 0 and fabs(eigen.wi[j]) < IMAGINARY_TOLERANCE * (1.0 + fabs(eigen.wr[j])):
                shifts[n_shifts] = eigen.wr[j]
                n_shifts += 1
        eigenvector_units(eigen, shifts, n_shifts, v)
        for j in range(n_shifts):
            for i in range(3):
                q[i] = v[4 * j + 1 + i] / v[4 * j]
            if isfinite(q[0]) and isfinite(q[1]) and isfinite(q[2]):
                cayley_times(q, P, rotations + 9 * count)
                count += 1
        return count

    cdef bint allocate(self, Scratch *scratch) noexcept nogil:
        """The buffers of `real_roots` (free them with `release`); False if memory is short."""
        scratch.coefficients = <double *> malloc(6 * self.n_monomials * sizeof(double))
        scratch.template = <double *> malloc(self.m * self.n_columns * sizeof(double))
        scratch.pivots = <int *> malloc(self.m * sizeof(int))
        scratch.lead = <int *> malloc(self.m * sizeof(int))
        scratch.reductions = <double *> malloc(self.n_reducible * N_SOLUTIONS * sizeof(double))
        scratch.action = <double *> malloc(N_SOLUTIONS * N_SOLUTIONS * sizeof(double))
        scratch.eigen = <Eigen *> malloc(sizeof(Eigen))
        return (scratch.coefficients != NULL and scratch.template != NULL and scratch.pivots != NULL and scratch.lead != NULL
                and scratch.reductions != NULL and scratch.action != NULL and scratch.eigen != NULL)

    def rotations_of_roots(self, const double[:, ::1] H, const double[::1] g, const double[:, ::1] P):
        """Rotations (k, 3, 3) of the real and nearly real roots of eq. EF6 for statistics H (9, 9),
        g (9,), solved in the frame P (3, 3) (`real_roots`)."""
        cdef Problem p
        cdef Scratch scratch
        cdef int k = 0
        memset(&scratch, 0, sizeof(Scratch))
        p.H, p.g = &H[0, 0], &g[0]
        rotations = np.empty((N_SOLUTIONS, 3, 3))
        cdef double[:, :, ::1] out = rotations
        try:
            if not self.allocate(&scratch):
                raise MemoryError("pose: no memory for the elimination template")
            k = self.real_roots(&p, &P[0, 0], &out[0, 0, 0], &scratch)
        finally:
            release(&scratch)
        return rotations[:k]

    def polish_rotations(self, const double[:, ::1] H, const double[::1] g, double c, const double[:, :, ::1] R):
        """The stationary points (k, 3, 3) that the rotations R (m, 3, 3) polish to (`polished`, as
        the roots are) for statistics H (9, 9), g (9,), c. For tests."""
        cdef Problem p
        p.H, p.g, p.c = &H[0, 0], &g[0], c
        out = np.array(R, dtype=float, order="C").reshape(-1, 9)
        cdef double[:, ::1] view = out
        cdef int k = 0
        if out.shape[0] > 0:
            k = self.polished(&p, &view[0, 0], 0, out.shape[0])
        return out[:k].reshape(k, 3, 3)

    def certify(self, const double[:, ::1] H, const double[::1] g, double c, const double[:, ::1] R):
        """`certified` for statistics H (9, 9), g (9,), c and a rotation R (3, 3)."""
        cdef Problem p
        p.H, p.g, p.c = &H[0, 0], &g[0], c
        return certified(&p, &R[0, 0])

    def solve_rays(self, const double[:, ::1] origins, const double[:, ::1] directions, const double[:, ::1] points,
                   double collinear_tolerance, double zero_direction):
        """All real stationary candidates and the solution (the steps of `solver.py`) from the rays:
        the checks of `statistics.validate_correspondences`, `statistics.statistics_of` and the
        solve in one compiled call, without the GIL: origins, directions (any length), points (n, 3).

        Returns R (k, 3, 3), t (k, 3), cost (k,), in_front (k,) sorted by cost without duplicate
        rotations, the index of the solution and whether it is certified (`certified`), or None when the input fails a check (fewer than 3 points,
        a wrong shape, a value not finite, a direction shorter than zero_direction, collinear
        points as `statistics_of` judges them with collinear_tolerance, all rays parallel): the
        Python checks then name the fault.
        """
        cdef int n = points.shape[0], k = 0
        if (n < 3 or origins.shape[0] != n or directions.shape[0] != n or points.shape[1] != 3
                or origins.shape[1] != 3 or directions.shape[1] != 3):
            return None
        cdef Candidates found
        cdef Statistics st
        cdef Problem p
        cdef Scratch scratch
        cdef bint valid = True, allocated = False
        # one block for the unit directions (n, 3) and the candidates' R, t, cost, front
        cdef double *buffer = <double *> malloc((3 * n + 14 * CAPACITY) * sizeof(double))
        cdef double *f = buffer
        memset(&scratch, 0, sizeof(Scratch))
        try:
            with nogil:
                if buffer != NULL:
                    found.R, found.t = buffer + 3 * n, buffer + 3 * n + 9 * CAPACITY
                    found.cost, found.front = found.t + 3 * CAPACITY, found.t + 4 * CAPACITY
                    valid = unit_directions(&origins[0, 0], &directions[0, 0], &points[0, 0], n, zero_direction, f)
                if buffer != NULL and valid:
                    accumulate(&origins[0, 0], f, &points[0, 0], n, &st)
                    valid = (st.spread[1] > collinear_tolerance * collinear_tolerance * st.spread[2]
                             and st.least_BtB > 1e-12 * n)
                if buffer != NULL and valid:
                    p.H, p.g, p.c, p.t_matrix, p.t_offset, p.centroid = st.H, st.g, st.c, st.t_matrix, st.t_offset, st.centroid
                    p.v, p.f, p.M, p.n = &origins[0, 0], f, &points[0, 0], n
                    allocated = self.allocate(&scratch)
                    if allocated:
                        k = self.candidates(&p, &found, &scratch, st.axes, st.spread)
            if not valid:
                return None
            if not allocated:
                raise MemoryError("pose: no memory for the elimination template")
            return distinct_candidates(&p, &found, k)
        finally:
            release(&scratch)
            free(buffer)

    cdef int candidates(self, const Problem *p, Candidates *c, Scratch *scratch, const double *point_axes,
                        const double *point_spread) noexcept nogil:
        """The steps of `solver.py` up to the candidates (rotation, centred t, cost, front) in c;
        returns their count."""
        cdef double P[9]
        cdef double step[9]
        cdef double mirror[9]
        cdef int i, j, k, best, before

        # Solving where the sought rotation is near q = 0 keeps it away from Cayley's blind spot.
        solving_frame(p, &self.octahedral[0], point_axes, point_spread, P)
        memcpy(c.R, P, 9 * sizeof(double))
        k = self.polished(p, c.R, 0, 1 + self.real_roots(p, P, c.R + 9, scratch))
        evaluate(p, c, 0, k)
        memcpy(step, P, 9 * sizeof(double))
        descend(p, step, 1)
        best = select(c, k)
        # A first step from P within a quarter of its distance to the solution found means P lies
        # in the solution's basin, where the descent would end; otherwise the local minimum it
        # ends at joins the candidates, in case the roots missed it.
        if k == 0 or angle_between(step, c.R + 9 * best) > 0.25 * angle_between(P, c.R + 9 * best):
            memcpy(c.R + 9 * k, step, 9 * sizeof(double))
            descend(p, c.R + 9 * k, DESCENT_ITERATIONS)
            polish(p, c.R + 9 * k)
            evaluate(p, c, k, k + 1)
            k += 1
        best = select(c, k)
        before = k
        if trace_product_t(c.R + 9 * best, P) < 1.0 + 2.0 * COS_MAX_FRAME_ANGLE:
            k = self.polished(p, c.R, k, k + self.real_roots(p, c.R + 9 * best, c.R + 9 * k, scratch))
        # A cheaper pose with the points behind the rays: its mirror (180 deg about the normal of
        # the points) is where the roots of an ill-conditioned planar scene may have missed the minimum.
        for i in range(3):
            for j in range(3):
                mirror[3 * i + j] = 2.0 * point_axes[3 * i] * point_axes[3 * j] - (1.0 if i == j else 0.0)
        j = k
        for i in range(before):
            if c.front[i] < 0.5 and c.cost[i] < c.cost[best]:
                matmul3(c.R + 9 * i, mirror, c.R + 9 * j)
                j += 1
        k = self.polished(p, c.R, k, j)
        evaluate(p, c, before, k)
        # A plane through a narrow field of view has two minima a few degrees apart, the solution
        # and its flip, where the template's roots are too inaccurate to tell them apart: descend
        # from the flip of the solution too.
        if point_spread[0] < FLIP_SPREAD * point_spread[1]:
            best = select(c, k)
            if flipped(p, c.R + 9 * best, point_axes, c.R + 9 * k):
                descend(p, c.R + 9 * k, DESCENT_ITERATIONS)
                polish(p, c.R + 9 * k)
                evaluate(p, c, k, k + 1)
                k += 1
        exact_costs(p, c, k)
        exact_front(p, c, k)
        return k

    cdef int polished(self, const Problem *p, double *R, int start, int stop) noexcept nogil:
        """Polish rotations start..stop of R (k, 9) and keep the stationary ones (compacted from
        start), those Newton's method misses settled by descent (`settle`); returns the new end."""
        cdef int i, end = start
        cdef double unpolished[9]
        for i in range(start, stop):
            memcpy(unpolished, R + 9 * i, 9 * sizeof(double))
            if polish(p, R + 9 * i) or settle(p, unpolished, R + 9 * i):
                if end != i:
                    memcpy(R + 9 * end, R + 9 * i, 9 * sizeof(double))
                end += 1
        return end


cdef bint flipped(const Problem *p, const double *R, const double *point_axes, double *out) noexcept nogil:
    """The flip of the rotation R (3, 3) for (nearly) planar points, in out (3, 3): R turned so that
    the plane's normal is mirrored about the line of sight, the line from the mean ray origin to
    the points' centroid (in the rig frame, at the optimal translation of R).

    Through a narrow field of view a plane and its flip look alike (exactly so under affine
    projection), so the cost has a second minimum near the flip of every minimum; the rotation
    about n x s by twice the angle between the normal n and the line of sight s is the Cayley
    rotation q = (n x s) / (n . s). False (out unset) when the plane is seen edge-on (n . s below
    1e-3 |n| |s|). point_axes: the principal axes of the points as columns, normal first.
    """
    cdef double t[3]
    cdef double s[3]
    cdef double n[3]
    cdef double q[3]
    cdef double dot = 0.0
    cdef int i, a
    centred_translation(p, R, t)
    for a in range(3):
        s[a] = t[a]
        for i in range(p.n):
            s[a] -= p.v[3 * i + a] / p.n
        n[a] = R[3 * a] * point_axes[0] + R[3 * a + 1] * point_axes[3] + R[3 * a + 2] * point_axes[6]
        dot += n[a] * s[a]
    if dot < 0.0:
        dot = -dot
        for a in range(3):
            n[a] = -n[a]
    if not dot > 1e-3 * sqrt(sum_squares(n, 3) * sum_squares(s, 3)):
        return False
    q[0] = (n[1] * s[2] - n[2] * s[1]) / dot
    q[1] = (n[2] * s[0] - n[0] * s[2]) / dot
    q[2] = (n[0] * s[1] - n[1] * s[0]) / dot
    memcpy(out, R, 9 * sizeof(double))
    cayley_times(q, out, out)
    return True


cdef void release(Scratch *scratch) noexcept nogil:
    """Free the buffers of `Kernel.allocate` (free ignores NULL)."""
    free(scratch.coefficients)
    free(scratch.template)
    free(scratch.pivots)
    free(scratch.lead)
    free(scratch.reductions)
    free(scratch.action)
    free(scratch.eigen)
    scratch.coefficients = scratch.template = scratch.reductions = scratch.action = NULL
    scratch.eigen = NULL
    scratch.pivots = NULL
    scratch.lead = NULL


cdef distinct_candidates(const Problem *p, const Candidates *c, int k):
    """The candidates 0..k of c sorted by cost, duplicate rotations (e.g. polished conjugate pairs)
    removed, t in the original world frame, cost clipped at 0: R (k', 3, 3), t (k', 3), cost (k',),
    front (k',) and the index of the solution, the cheapest with at least half the points in
    front, if any."""
    cdef int order[CAPACITY]
    cdef int i, j, a, b, count = 0, best = -1
    cdef double largest
    by_cost(c, k, order)
    for i in range(k):
        for j in range(count):
            largest = 0.0
            for a in range(9):
                largest = max(largest, fabs(c.R[9 * order[i] + a] - c.R[9 * order[j] + a]))
            if largest < DUPLICATE_TOLERANCE:
                break
        else:
            order[count] = order[i]
            count += 1
    R_out, t_out, cost_out, front_out = np.empty((count, 3, 3)), np.empty((count, 3)), np.empty(count), np.empty(count)
    cdef double[:, :, ::1] R_view = R_out
    cdef double[:, ::1] t_view = t_out
    cdef double[::1] cost_view = cost_out, front_view = front_out
    for i in range(count):
        j = order[i]
        for a in range(3):
            t_view[i, a] = c.t[3 * j + a]
            for b in range(3):
                R_view[i, a, b] = c.R[9 * j + 3 * a + b]
                t_view[i, a] -= c.R[9 * j + 3 * a + b] * p.centroid[b]
        cost_view[i] = max(c.cost[j], 0.0)
        front_view[i] = c.front[j]
        if best < 0 and c.front[j] >= 0.5:
            best = i
    best = max(best, 0)
    return R_out, t_out, cost_out, front_out, best, count > 0 and certified(p, c.R + 9 * order[best])


cdef bint certified(const Problem *p, const double *R) noexcept nogil:
    """Whether the Lagrangian dual certifies R (3, 3) as the global minimum of eq. objfun3 over
    O(3), hence over SO(3) (beyond the paper).

    With x = [r; y], the cost is x^T Q x, Q = [[H, -g], [-g^T, c]] (10, 10), under R^T R = I and
    y^2 = 1. Their Lagrangian x^T Q x - tr(L (R^T R - I)) - mu (y^2 - 1) has the Hessian
    S = Q - blockdiag(I3 kron L, mu) (r row-major, so tr(L R^T R) = r^T (I3 kron L) r). Its
    stationarity S x = 0 at x = [r; 1] fixes the multipliers: L = R^T mat(H r - g) (symmetric
    exactly when the gradient on SO(3) vanishes) and mu = c - g^T r. If S is positive
    semidefinite, every feasible x costs x^T S x + tr L + mu >= tr L + mu = cost(R): R is a global
    minimum (strong duality, as in Briales and Gonzalez-Jimenez, CVPR 2017, for registration).
    The test is the least eigenvalue of S against -CERTIFICATE_TOLERANCE (trace H + |g| + |c|).
    """
    cdef double h[9]
    cdef double L[9]
    cdef double S[100]
    cdef double eigenvalues[10]
    cdef double work[340]
    cdef int ten = 10, lwork = 340, info = 0, i, j, a, b
    cdef double gr = 0.0
    for i in range(9):
        h[i] = -p.g[i]
        gr += p.g[i] * R[i]
        for j in range(9):
            h[i] += p.H[9 * i + j] * R[j]
    for a in range(3):
        for b in range(3):
            L[3 * a + b] = 0.0
            for i in range(3):
                L[3 * a + b] += R[3 * i + a] * h[3 * i + b]
    for i in range(9):
        for j in range(9):
            S[10 * i + j] = p.H[9 * i + j]
        S[10 * i + 9] = S[90 + i] = -p.g[i]
    S[99] = gr  # c - mu
    for i in range(3):
        for a in range(3):
            for b in range(3):
                S[10 * (3 * i + a) + 3 * i + b] -= 0.5 * (L[3 * a + b] + L[3 * b + a])
    dsyev(b"N", b"L", &ten, S, &ten, eigenvalues, work, &lwork, &info)
    return info == 0 and eigenvalues[0] >= -CERTIFICATE_TOLERANCE * (statistics_size(p) + fabs(p.c))


cdef void evaluate(const Problem *p, Candidates *c, int start, int stop) noexcept nogil:
    """Cost, centred translation and fraction of points in front of rotations start..stop."""
    cdef int i
    for i in range(start, stop):
        c.cost[i] = cost_of(p, c.R + 9 * i)
        centred_translation(p, c.R + 9 * i, c.t + 3 * i)
        c.front[i] = front_fraction(p, c.R + 9 * i, c.t + 3 * i, sample_stride(p))


cdef void by_cost(const Candidates *c, int k, int *order) noexcept nogil:
    """order (k,): the indices of candidates 0..k by increasing cost (insertion sort, stable)."""
    cdef int i, j
    for i in range(k):
        j = i
        while j > 0 and c.cost[order[j - 1]] > c.cost[i]:
            order[j] = order[j - 1]
            j -= 1
        order[j] = i


cdef void exact_front(const Problem *p, Candidates *c, int k) noexcept nogil:
    """Count every point for the candidates 0..k in order of cost up to the first with at least
    half of them in front: the solution and the cheaper poses it is preferred to. The others keep
    the fraction of the subsample (`sample_stride`)."""
    cdef int order[CAPACITY]
    cdef int i
    if sample_stride(p) == 1:
        return
    by_cost(c, k, order)
    for i in range(k):
        c.front[order[i]] = front_fraction(p, c.R + 9 * order[i], c.t + 3 * order[i], 1)
        if c.front[order[i]] >= 0.5:
            break


cdef void exact_costs(const Problem *p, Candidates *c, int k) noexcept nogil:
    """Where two or more front-facing candidates 0..k cost within TIE_ROUNDINGS rounding levels of
    the cheapest front-facing one, replace their costs by `residual_cost`, so that the cheaper of
    two nearly equal minima wins (through a narrow field of view the quadratic form cannot tell)."""
    cdef int i, close = 0, best = select(c, k)
    cdef double band
    if k == 0 or c.front[best] < 0.5:
        return
    band = c.cost[best] + TIE_ROUNDINGS * rounding_level(p)
    for i in range(k):
        close += c.front[i] >= 0.5 and c.cost[i] <= band
    if close < 2:
        return
    for i in range(k):
        if c.front[i] >= 0.5 and c.cost[i] <= band:
            c.cost[i] = residual_cost(p, c.R + 9 * i, c.t + 3 * i)


cdef int select(const Candidates *c, int k) noexcept nogil:
    """Index of the solution: least cost among the poses with at least half the points in front,
    if any.

    Eq. objfun measures distances to lines, not rays, so a pose and its mirror that puts the
    points behind the cameras can cost the same: exactly so for a central camera and a planar
    scene (R and R Rz(180 deg) about the plane normal), nearly so for any almost-central rig.
    """
    cdef int i, best = -1
    cdef bint feasible = False
    for i in range(k):
        if c.front[i] >= 0.5 and not feasible:
            feasible, best = True, i
        elif (c.front[i] >= 0.5 or not feasible) and (best < 0 or c.cost[i] < c.cost[best]):
            best = i
    return max(best, 0)


cdef void symmetric_eigen(double *A, double *eigenvalues) noexcept nogil:
    """Eigenvalues (3,), ascending, of the symmetric A (3, 3), replaced by its eigenvectors as rows."""
    cdef int three = 3, lwork = 64, info = 0
    cdef double work[64]
    dsyev(b"V", b"L", &three, A, &three, eigenvalues, work, &lwork, &info)  # column-major: vectors as rows


cdef struct Statistics:
    double H[81]
    double g[9]
    double c
    double t_matrix[27]
    double t_offset[3]
    double centroid[3]
    double BtB[9]
    double axes[9]  # principal axes of the centred points as the columns of a rotation, least spread first
    double spread[3]  # their spreads, ascending
    double least_BtB  # the least eigenvalue of BtB


cdef void accumulate(const double *v, const double *f, const double *M, int n, Statistics *st) noexcept nogil:
    """The sums and Schur complements of `statistics.statistics_of` in st, O(n): v, unit f, M (n, 3),
    C-ordered. If BtB is singular (all rays parallel), t_matrix, t_offset, H, g and c are NaN."""
    cdef int i, a, b, k, l
    cdef double m[3]
    cdef double U[9]
    cdef double w[3]
    cdef double sum_m[3]
    cdef double scatter[9]
    cdef double AtA[81]
    cdef double AtB[27]
    cdef double AtD[9]
    cdef double BtD[3]
    cdef double DtD = 0.0, fv, s, sign
    cdef double system[9]
    cdef double btb_eigen[3]
    memset(scatter, 0, sizeof(scatter)); memset(AtA, 0, sizeof(AtA)); memset(AtB, 0, sizeof(AtB))
    memset(AtD, 0, sizeof(AtD)); memset(BtD, 0, sizeof(BtD)); memset(sum_m, 0, sizeof(sum_m))
    memset(st.BtB, 0, sizeof(st.BtB))
    for a in range(3):
        s = 0.0
        for i in range(n):
            s += M[3 * i + a]
        st.centroid[a] = s / n
    for i in range(n):
        for a in range(3):
            m[a] = M[3 * i + a] - st.centroid[a]
            sum_m[a] += m[a]
        fv = f[3 * i] * v[3 * i] + f[3 * i + 1] * v[3 * i + 1] + f[3 * i + 2] * v[3 * i + 2]
        for a in range(3):
            w[a] = v[3 * i + a] - f[3 * i + a] * fv  # (I - f f^T) v
            BtD[a] += w[a]
            DtD += v[3 * i + a] * w[a]
            for b in range(3):
                U[3 * a + b] = f[3 * i + a] * m[b]  # kron(f, m)
                scatter[3 * a + b] += m[a] * m[b]
                st.BtB[3 * a + b] -= f[3 * i + a] * f[3 * i + b]
                AtD[3 * a + b] += w[a] * m[b]
        for k in range(9):
            for l in range(k, 9):
                AtA[9 * k + l] -= U[k] * U[l]
            for b in range(3):
                AtB[3 * k + b] -= U[k] * f[3 * i + b]
    for a in range(3):  # the kron(I3, .) terms
        st.BtB[4 * a] += n
        for b in range(3):
            AtB[3 * (3 * a + b) + a] += sum_m[b]  # ~0 after centring, kept for exactness
            for l in range(b, 3):
                AtA[9 * (3 * a + b) + 3 * a + l] += scatter[3 * b + l]
    # t = -(B^T B)^-1 (B^T A r - B^T D): the 9 + 1 right-hand sides
    for k in range(10):
        for a in range(3):
            w[a] = AtB[3 * k + a] if k < 9 else BtD[a]
        memcpy(system, st.BtB, sizeof(system))
        if not solve_linear(system, w, 3):
            w[0] = w[1] = w[2] = NAN
        for a in range(3):
            if k < 9:
                st.t_matrix[9 * a + k] = -w[a]
            else:
                st.t_offset[a] = w[a]
    # H = A^T A + A^T B t_matrix (symmetric), g = A^T D - A^T B t_offset, c = D^T D - B^T D . t_offset
    for k in range(9):
        for l in range(k, 9):
            s = AtA[9 * k + l]
            for a in range(3):
                s += AtB[3 * k + a] * st.t_matrix[9 * a + l]
            st.H[9 * k + l] = s
            st.H[9 * l + k] = s
        s = AtD[k]
        for a in range(3):
            s -= AtB[3 * k + a] * st.t_offset[a]
        st.g[k] = s
    st.c = DtD - (BtD[0] * st.t_offset[0] + BtD[1] * st.t_offset[1] + BtD[2] * st.t_offset[2])
    symmetric_eigen(scatter, st.spread)  # squared singular values of the centred points
    sign = -1.0 if det3(scatter) < 0 else 1.0  # axes as the columns of a rotation
    for a in range(3):
        for b in range(3):
            st.axes[3 * b + a] = scatter[3 * a + b] * (sign if a == 0 else 1.0)
    memcpy(system, st.BtB, sizeof(system))
    symmetric_eigen(system, btb_eigen)
    st.least_BtB = btb_eigen[0]


def statistics(const double[:, ::1] v, const double[:, ::1] f, const double[:, ::1] M):
    """The sums and Schur complements of `statistics.statistics_of`, O(n): v, unit f, M (n, 3).

    Returns H (9, 9), g (9,), c, t_matrix (3, 9), t_offset (3,), centroid (3,), BtB (3, 3), the
    principal axes (3, 3) of the centred points as the columns of a rotation, least spread first,
    their spreads (3,) (ascending eigenvalues of the scatter matrix) and the least eigenvalue of
    BtB. If BtB is singular (all rays parallel), t_matrix, t_offset, H, g and c are NaN.
    """
    cdef Statistics st
    accumulate(&v[0, 0], &f[0, 0], &M[0, 0], M.shape[0], &st)
    return (array_of(st.H, 9, 9), array_of(st.g, 9, 0), st.c, array_of(st.t_matrix, 3, 9),
            array_of(st.t_offset, 3, 0), array_of(st.centroid, 3, 0), array_of(st.BtB, 3, 3),
            array_of(st.axes, 3, 3), array_of(st.spread, 3, 0), st.least_BtB)


cdef array_of(const double *x, int rows, int columns):
    """A new numpy array (rows, columns), or (rows,) if columns is 0, holding the C-ordered x."""
    out = np.empty((rows, columns)) if columns else np.empty(rows)
    cdef double[::1] flat = out.reshape(-1)
    memcpy(&flat[0], x, rows * max(columns, 1) * sizeof(double))
    return out
