# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled steps of markers.centring's gradient condition (`centring._refine_fixed`): per point, the
window's central-difference gradients read once, then the Gaussian-weighted least-squares steps, without
numpy's (n, k) arrays per step (the shadow start's centrings and the refinement's seeds, ~10 ms of a
12 MP image).

Every number is made as `centring._refine_fixed_numpy` makes it: the same operations in the same order,
the window's sums in np.sum's pairwise order (`pairwise_sum`), exp and hypot libm's (numpy's own where
it has no SIMD loop for float64 exp, as on x86-64 without AVX-512); tests/test_marker_sampling.py
compares the two. The image is read as `rings.ImageParts` reads it (a plain image: one part).
"""

from libc.math cimport exp, hypot, isfinite, rint
from libc.stdlib cimport free, malloc

from dmais_pipe.markers._sums cimport pairwise_sum

import numpy as np




cdef struct Parts:
    const void *buffer
    int kind  # of its pixels: 0 float32, 1 uint16, 2 uint8 (read as float32, exactly)
    const Py_ssize_t *strides  # per part, its rows' stride (pixels)
    const Py_ssize_t *bases
    const Py_ssize_t *lefts
    const Py_ssize_t *tops
    const Py_ssize_t *widths
    const Py_ssize_t *heights
    const Py_ssize_t *cells
    Py_ssize_t rows, cols, cell_px


cdef inline Py_ssize_t floor_div(Py_ssize_t a, Py_ssize_t b) noexcept nogil:
    """a // b rounded down (b > 0), as numpy's floor_divide of integers."""
    cdef Py_ssize_t q = a / b
    return q - 1 if (a % b != 0 and a < 0) else q


cdef inline Py_ssize_t within(Py_ssize_t value, Py_ssize_t low, Py_ssize_t high) noexcept nogil:
    return low if value < low else (high if value > high else value)


cdef inline double pixel(const Parts *p, Py_ssize_t x, Py_ssize_t y) noexcept nogil:
    """The value at integer pixel x, y as `ImageParts.__getitem__` reads it (its part's border beyond it)."""
    cdef Py_ssize_t k = p.cells[within(floor_div(y, p.cell_px), 0, p.rows - 1) * p.cols
                                + within(floor_div(x, p.cell_px), 0, p.cols - 1)]
    cdef Py_ssize_t row = within(y - p.tops[k], 0, p.heights[k] - 1)
    cdef Py_ssize_t column = within(x - p.lefts[k], 0, p.widths[k] - 1)
    cdef Py_ssize_t at = p.bases[k] + row * p.strides[k] + column
    if p.kind == 0:
        return (<const float *> p.buffer)[at]
    if p.kind == 1:
        return <float> (<const unsigned short *> p.buffer)[at]
    return <float> (<const unsigned char *> p.buffer)[at]


cdef int _rings_kind(buffer) except -1:
    """0, 1, 2: a flat C-ordered buffer of float32, uint16 or uint8 pixels (`_rings.pixel_kind`'s)."""
    if buffer.ndim != 1 or not buffer.flags.c_contiguous:
        raise ValueError("the parts' pixels must be one flat C-ordered buffer")
    for kind, dtype in enumerate((np.float32, np.uint16, np.uint8)):
        if buffer.dtype == dtype:
            return kind
    raise TypeError(f"parts of {buffer.dtype} pixels (float32, uint16 or uint8 only)")


def gradient_steps(buffer, bases, lefts, tops, widths, heights, rows, cells, Py_ssize_t cell_px, Py_ssize_t height,
                   Py_ssize_t width, start, Py_ssize_t half, double radius, double sigma2, Py_ssize_t steps,
                   double eps, max_shift, bint converge):
    """`centring._refine_fixed`'s result (n, 2) from start (n, 2) (NaN rows stay NaN), in an image of
    (height, width) px given as parts (`rings.ImageParts`' flat buffer of float32, uint16 or uint8 pixels,
    per part its offset, left, top, width, height and row stride, and the map `cells` (rows, cols) of the
    part each cell of cell_px reads):
    the window of (2 half + 1)^2 px about each rounded start, the taper `radius`, the Gaussian's
    2 sigma^2 = sigma2, at most `steps` steps, converged below `eps` px, each start's max_shift (n,)."""
    cdef int kind = _rings_kind(buffer)
    cdef const unsigned char[::1] data = buffer.view(np.uint8)
    cdef const Py_ssize_t[::1] stride = np.ascontiguousarray(rows, dtype=np.intp)
    cdef const Py_ssize_t[::1] base = np.ascontiguousarray(bases, dtype=np.intp)
    cdef const Py_ssize_t[::1] left = np.ascontiguousarray(lefts, dtype=np.intp)
    cdef const Py_ssize_t[::1] top = np.ascontiguousarray(tops, dtype=np.intp)
    cdef const Py_ssize_t[::1] wide = np.ascontiguousarray(widths, dtype=np.intp)
    cdef const Py_ssize_t[::1] high = np.ascontiguousarray(heights, dtype=np.intp)
    cdef const Py_ssize_t[:, ::1] cell = np.ascontiguousarray(cells, dtype=np.intp)
    cdef const double[:, ::1] s = np.ascontiguousarray(start, dtype=np.float64)
    cdef const double[::1] shift = np.ascontiguousarray(max_shift, dtype=np.float64)
    cdef Parts parts = Parts(&data[0], kind, &stride[0], &base[0], &left[0], &top[0], &wide[0], &high[0], &cell[0, 0],
                             cell.shape[0], cell.shape[1], cell_px)
    cdef Py_ssize_t n = s.shape[0], side = 2 * half + 1, k = side * side, i
    out = np.full((n, 2), np.nan)
    cdef double[:, ::1] o = out
    cdef double *work = <double *> malloc(8 * k * sizeof(double))
    if work == NULL:
        raise MemoryError()
    try:
        with nogil:
            for i in range(n):
                if isfinite(s[i, 0]) and isfinite(s[i, 1]):
                    one_point(&parts, height, width, s[i, 0], s[i, 1], half, radius, sigma2, steps, eps, shift[i],
                              converge, work, &o[i, 0])
    finally:
        free(work)
    return out


cdef void one_point(const Parts *parts, Py_ssize_t height, Py_ssize_t width, double sx, double sy, Py_ssize_t half,
                    double radius, double sigma2, Py_ssize_t steps, double eps, double max_shift, bint converge,
                    double *work, double *out) noexcept nogil:
    """`gradient_steps` of one start sx, sy into out (2), NaN where it fails; work: 8 k doubles."""
    cdef Py_ssize_t side = 2 * half + 1, k = side * side, j, step
    cdef double *xs = work
    cdef double *ys = work + k
    cdef double *gx = work + 2 * k
    cdef double *gy = work + 3 * k
    cdef double *kept = work + 4 * k
    cdef double *w = work + 5 * k
    cdef double *t = work + 6 * k
    cdef Py_ssize_t cx = <Py_ssize_t> rint(sx), cy = <Py_ssize_t> rint(sy), x, y, xc, yc
    for j in range(k):
        x, y = cx + j % side - half, cy + j // side - half
        xc, yc = within(x, 1, width - 2), within(y, 1, height - 2)
        xs[j], ys[j] = <double> x, <double> y
        gx[j] = 0.5 * (pixel(parts, xc + 1, yc) - pixel(parts, xc - 1, yc))
        gy[j] = 0.5 * (pixel(parts, xc, yc + 1) - pixel(parts, xc, yc - 1))
        kept[j] = 1.0 if (x == xc and y == yc) else 0.0
    cdef double qx = sx, qy = sy, rx, ry, d2, taper, wxx, wxy, wyy, bx, by, det, trace, nx, ny
    cdef bint inside, ok
    cdef double square = radius * radius
    for step in range(steps):
        inside = qx >= 0 and qx <= width - 1 and qy >= 0 and qy <= height - 1
        if not inside:
            qx, qy = 0.0, 0.0
        for j in range(k):
            rx, ry = xs[j] - qx, ys[j] - qy
            d2 = rx * rx + ry * ry
            taper = 1.0 - d2 / square
            taper = taper if taper > 0.0 else (taper if taper != taper else 0.0)
            if taper == 0.0 or kept[j] == 0.0:
                # exp(-d2 / sigma2) (finite, >= 0) times a zero: +0.0 exactly, without the exp
                # (the pixels beyond the taper's radius: ~80% of the window).
                w[j] = 0.0
            else:
                w[j] = exp(-d2 / sigma2) * (taper * taper) * kept[j]
        for j in range(k):
            t[j] = w[j] * gx[j] * gx[j]
        wxx = pairwise_sum(t, k)
        for j in range(k):
            t[j] = w[j] * gx[j] * gy[j]
        wxy = pairwise_sum(t, k)
        for j in range(k):
            t[j] = w[j] * gy[j] * gy[j]
        wyy = pairwise_sum(t, k)
        for j in range(k):
            t[j] = w[j] * (gx[j] * gx[j] * xs[j] + gx[j] * gy[j] * ys[j])
        bx = pairwise_sum(t, k)
        for j in range(k):
            t[j] = w[j] * (gx[j] * gy[j] * xs[j] + gy[j] * gy[j] * ys[j])
        by = pairwise_sum(t, k)
        det = wxx * wyy - wxy * wxy
        trace = wxx + wyy
        ok = inside and trace > 0 and det > 1e-6 * (trace * trace)
        nx, ny = (wyy * bx - wxy * by) / det, (wxx * by - wxy * bx) / det
        ok = ok and isfinite(nx) and isfinite(ny) and hypot(nx - sx, ny - sy) <= max_shift
        if ok and hypot(nx - qx, ny - qy) < eps:
            out[0], out[1] = nx, ny
            return
        if not ok:
            return
        if not converge:
            out[0], out[1] = nx, ny
        qx, qy = nx, ny
