# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled bilinear samples of float32 images (markers.rings.sample): the ring tests' and starts' reads,
~10^5 positions a 12 MP image, without cv2.remap's per-call map copies and its 30,000-row chunks.

The arithmetic is cv2.remap's (OpenCV 5, INTER_LINEAR, BORDER_REPLICATE, float32) to the last bit where
OpenCV's remap runs with fused multiply-adds (x86-64 with FMA, as here): per position, a = x - floor(x),
b = y - floor(y) in float32, the four neighbours at the indexes clamped into the image, then
t0 = fma(a, p01 - p00, p00), t1 = fma(a, p11 - p10, p10), value = fma(b, t1 - t0, t0) (fmaf: one
rounding each, on any CPU); NaN where a coordinate is not finite. tests/test_marker_sampling.py
compares it with cv2.remap.
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
