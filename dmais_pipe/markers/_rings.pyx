# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled loops of markers.rings: bilinear samples of float32 images (`rings.sample`: the ring tests'
and starts' reads, ~10^5 positions a 12 MP image, without cv2.remap's per-call map copies and its
30,000-row chunks) and the statistics of rings of samples (`rings.ring_stats`, ~25 calls an image).

The arithmetic is cv2.remap's (OpenCV 5, INTER_LINEAR, BORDER_REPLICATE, float32) to the last bit where
OpenCV's remap runs with fused multiply-adds (x86-64 with FMA, as here): per position, a = x - floor(x),
b = y - floor(y) in float32, the four neighbours at the indexes clamped into the image, then
t0 = fma(a, p01 - p00, p00), t1 = fma(a, p11 - p10, p10), value = fma(b, t1 - t0, t0) (fmaf: one
rounding each, on any CPU); NaN where a coordinate is not finite. The ring statistics make every
number as numpy's expressions (`rings._ring_stats`) do, the sums in np.sum's pairwise order, to the
last bit. tests/test_marker_sampling.py compares both with what they replace.
"""

from libc.math cimport floorf, fmaf, isfinite, NAN

import numpy as np


cdef inline float bilinear(const float *image, Py_ssize_t height, Py_ssize_t width, Py_ssize_t row,
                           Py_ssize_t column, float x, float y) noexcept nogil:
    """The sample at x, y (its own pixel coordinates) of an image (height, width) whose pixel i, j is
    image[i row + j column]."""
    if not (isfinite(x) and isfinite(y)):
        return NAN
    cdef float fx = floor_of(x), fy = floor_of(y)
    cdef float a = x - fx, b = y - fy
    cdef Py_ssize_t x0 = clamp(fx, width) * column, y0 = clamp(fy, height) * row
    cdef Py_ssize_t x1 = clamp(fx + 1.0, width) * column, y1 = clamp(fy + 1.0, height) * row
    cdef float p00 = image[y0 + x0], p01 = image[y0 + x1], p10 = image[y1 + x0], p11 = image[y1 + x1]
    cdef float t0 = fmaf(a, p01 - p00, p00), t1 = fmaf(a, p11 - p10, p10)
    return fmaf(b, t1 - t0, t0)


cdef inline float floor_of(float x) noexcept nogil:
    """floorf(x) of a finite x, by a truncating conversion where |x| < 2^30 (no libm call)."""
    cdef float t
    if -1073741824.0 < x < 1073741824.0:
        t = <float><int>x
        return t - 1.0 if t > x else t
    return floorf(x)


cdef inline Py_ssize_t clamp(double index, Py_ssize_t size) noexcept nogil:
    """index (an integral value) clamped into 0..size - 1."""
    if index <= 0.0:
        return 0
    if index >= size - 1:
        return size - 1
    return <Py_ssize_t>index


def sample(image, xy):
    """(n,) float32 samples of the float32 image (h, w) at float32 positions xy (n, 2)."""
    cdef const float[:, :] img = image
    cdef const float[:, ::1] p = np.ascontiguousarray(xy, dtype=np.float32)
    out = np.empty(p.shape[0], dtype=np.float32)
    cdef float[::1] o = out
    cdef Py_ssize_t i, row = img.strides[0] // 4, column = img.strides[1] // 4
    with nogil:
        for i in range(p.shape[0]):
            o[i] = bilinear(&img[0, 0], img.shape[0], img.shape[1], row, column, p[i, 0], p[i, 1])
    return out


def owners(xs, ys, cells, Py_ssize_t cell_px):
    """(n,) intp: the part of `cells` (rows, cols), the map of which part holds each cell of cell_px,
    at float32 positions xs, ys (n,): `rings.ImageParts.owners` (a coordinate that is not finite, or
    beyond int64, reads cell 0 of its axis, as numpy's conversion and clip have it)."""
    cdef const float[::1] x = np.ascontiguousarray(xs, dtype=np.float32)
    cdef const float[::1] y = np.ascontiguousarray(ys, dtype=np.float32)
    cdef const Py_ssize_t[:, ::1] c = np.ascontiguousarray(cells, dtype=np.intp)
    out = np.empty(x.shape[0], dtype=np.intp)
    cdef Py_ssize_t[::1] o = out
    cdef Py_ssize_t i
    with nogil:
        for i in range(x.shape[0]):
            o[i] = c[cell(y[i], cell_px, c.shape[0]), cell(x[i], cell_px, c.shape[1])]
    return out


cdef inline Py_ssize_t cell(float value, Py_ssize_t cell_px, Py_ssize_t count) noexcept nogil:
    """floor(value / cell_px) clamped into 0..count - 1; 0 where it is not finite or beyond int64."""
    cdef double q = <double>value / cell_px
    if not (q > -9.2e18 and q < 9.2e18):
        return 0
    if q < 1.0:  # floor(q) <= 0
        return 0
    if q >= count - 1:
        return count - 1
    return <Py_ssize_t>q  # truncation: floor, q > 0


def parts_sample(buffer, bases, lefts, tops, widths, heights, part, xy):
    """(n,) float32 samples at float32 positions xy (n, 2) (whole-image coordinates) of the parts of
    `rings.ImageParts` (its flat buffer, and per part its offset in it, left, top, width, height),
    each position read from the part `part` (n,) in its own coordinates (x - left, y - top: exact in
    float32)."""
    cdef const float[::1] buf = buffer
    cdef const Py_ssize_t[::1] base = np.ascontiguousarray(bases, dtype=np.intp)
    cdef const Py_ssize_t[::1] left = np.ascontiguousarray(lefts, dtype=np.intp)
    cdef const Py_ssize_t[::1] top = np.ascontiguousarray(tops, dtype=np.intp)
    cdef const Py_ssize_t[::1] width = np.ascontiguousarray(widths, dtype=np.intp)
    cdef const Py_ssize_t[::1] height = np.ascontiguousarray(heights, dtype=np.intp)
    cdef const Py_ssize_t[::1] owner = np.ascontiguousarray(part, dtype=np.intp)
    cdef const float[:, ::1] p = np.ascontiguousarray(xy, dtype=np.float32)
    out = np.empty(p.shape[0], dtype=np.float32)
    cdef float[::1] o = out
    cdef Py_ssize_t i, k
    with nogil:
        for i in range(p.shape[0]):
            k = owner[i]
            o[i] = bilinear(&buf[base[k]], height[k], width[k], width[k], 1, p[i, 0] - <float>left[k],
                            p[i, 1] - <float>top[k])
    return out


cdef double pairwise_sum(const double *a, Py_ssize_t n) noexcept nogil:
    """Sum of a (n) in numpy's order (its pairwise summation of a contiguous row: 8 partial sums
    below 128 terms, halves above), so that a row's sum is np.sum's to the last bit."""
    cdef double r[8]
    cdef double res = 0.0
    cdef Py_ssize_t i, j, half
    if n < 8:
        for i in range(n):
            res += a[i]
        return res
    if n <= 128:
        for j in range(8):
            r[j] = a[j]
        i = 8
        while i < n - n % 8:
            for j in range(8):
                r[j] += a[i + j]
            i += 8
        res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
        while i < n:
            res += a[i]
            i += 1
        return res
    half = n // 2
    half -= half % 8
    return pairwise_sum(a, half) + pairwise_sum(a + half, n - half)


cdef inline double unit_clip(double x) noexcept nogil:
    """np.clip(x, 0, 1) (NaN stays NaN)."""
    if x != x:
        return x
    return 0.0 if x < 0.0 else (1.0 if x > 1.0 else x)


def ring_stats(values):
    """`rings.ring_stats` of rings values (m, k), each number as numpy makes it (the same operations,
    the sums in np.sum's order): quality (m,), bright level (m,), dark level (m,), bright mask (m, k)."""
    cdef const double[:, ::1] v = np.ascontiguousarray(values, dtype=np.float64)
    cdef Py_ssize_t m = v.shape[0], k = v.shape[1], i, j, half = k // 2
    quality, bright, dark = np.empty(m), np.empty(m), np.empty(m)
    mask = np.empty((m, k), dtype=bool)
    cdef double[::1] q = quality, hi = bright, lo = dark
    cdef unsigned char[:, ::1] h = mask.view(np.uint8)
    scratch = np.empty(k)
    cdef double[::1] t = scratch
    cdef double mean, total, mean_high, mean_low, within, opposite, bimodal, symmetric
    cdef Py_ssize_t transitions, n_high
    if k == 0:
        raise ValueError("rings of no samples")
    with nogil:
        for i in range(m):
            mean = pairwise_sum(&v[i, 0], k) / <double>k
            n_high = 0
            for j in range(k):
                h[i, j] = v[i, j] > mean
                n_high += h[i, j]
            transitions = h[i, 0] != h[i, k - 1]
            for j in range(1, k):
                transitions += h[i, j] != h[i, j - 1]
            for j in range(k):
                t[j] = (v[i, j] - mean) * (v[i, j] - mean)
            total = pairwise_sum(&t[0], k) + 1e-9
            for j in range(k):
                t[j] = v[i, j] if h[i, j] else 0.0
            mean_high = pairwise_sum(&t[0], k) / <double>(n_high if n_high > 1 else 1)
            for j in range(k):
                t[j] = 0.0 if h[i, j] else v[i, j]
            mean_low = pairwise_sum(&t[0], k) / <double>(k - n_high if k - n_high > 1 else 1)
            for j in range(k):
                t[j] = v[i, j] - (mean_high if h[i, j] else mean_low)
                t[j] = t[j] * t[j]
            within = pairwise_sum(&t[0], k)
            bimodal = unit_clip(1.0 - within / total)
            for j in range(k):
                opposite = v[i, k - half + j] if j < half else v[i, j - half]  # np.roll by k // 2
                t[j] = (v[i, j] - opposite) * (v[i, j] - opposite)
            symmetric = unit_clip(1.0 - pairwise_sum(&t[0], k) / (2.0 * total))
            q[i] = bimodal * symmetric if transitions == 4 else 0.0
            hi[i], lo[i] = mean_high, mean_low
    return quality, bright, dark, mask
