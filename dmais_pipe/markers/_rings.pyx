# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled loops of markers.rings: bilinear samples of float32 images (`rings.sample`: the ring tests'
and starts' reads, ~10^5 positions a 12 MP image, without cv2.remap's per-call map copies and its
30,000-row chunks), the statistics of rings of samples (`rings.ring_stats`, ~25 calls an image) and
the clean radius (`rings.clean_radius`: per point its rings from the smallest, each sampled, scored
and compared with the previous in one pass).

The arithmetic is cv2.remap's (OpenCV 5, INTER_LINEAR, BORDER_REPLICATE, float32) to the last bit where
OpenCV's remap runs with fused multiply-adds (x86-64 with FMA, as here): per position, a = x - floor(x),
b = y - floor(y) in float32, the four neighbours at the indexes clamped into the image, then
t0 = fma(a, p01 - p00, p00), t1 = fma(a, p11 - p10, p10), value = fma(b, t1 - t0, t0), one rounding
each on any CPU (the loop is built twice, with the FMA instruction for a CPU that has it, chosen at
run time, and with libm's fmaf, which the portable build calls otherwise); NaN where a coordinate is
not finite; float32 images only (`rings.sample` leaves others to cv2.remap). The ring statistics make every
number as numpy's expressions (`rings._ring_stats`) do, the sums in np.sum's pairwise order, to the
last bit. tests/test_marker_sampling.py compares both with what they replace.
"""

from libc.math cimport isfinite

import numpy as np

from dmais_pipe.markers._sums cimport pairwise_sum


cdef extern from *:
    """
    #include <math.h>
    #include <Python.h>

    /* floorf(x) of a finite x, by a truncating conversion where |x| < 2^30 (no libm call). */
    static inline float dmais_floor(float x) {
        if (x > -1073741824.0f && x < 1073741824.0f) {
            float t = (float)(int)x;
            return t > x ? t - 1.0f : t;
        }
        return floorf(x);
    }

    /* index (an integral value) clamped into 0..size - 1. */
    static inline Py_ssize_t dmais_clamp(double index, Py_ssize_t size) {
        if (index <= 0.0) return 0;
        if (index >= (double)(size - 1)) return size - 1;
        return (Py_ssize_t)index;
    }

    /* The samples out[i] at xy[2 i], xy[2 i + 1] of the part owner[i] (part 0 where owner is NULL):
       part k's pixel r, c is buffer[base[k] + r row[k] + c column[k]], its left column and top row
       left[k], top[k] in the positions' coordinates. FMA: fmaf, or the instruction. */
    /* OUT = the bilinear sample of the part at p (rs, cs its row and column strides, w x h pixels) at its
       offsets x, y (finite), with FMA's roundings and `dmais_clamp`'s edges: `dmais_sample`'s and the rings'. */
    #define DMAIS_BILINEAR(FMA, OUT, p, x, y, w, h, rs, cs) do { \
        float fx_ = dmais_floor(x), fy_ = dmais_floor(y); \
        float a_ = (x) - fx_, b_ = (y) - fy_; \
        Py_ssize_t x0_ = dmais_clamp(fx_, w) * (cs), y0_ = dmais_clamp(fy_, h) * (rs); \
        Py_ssize_t x1_ = dmais_clamp(fx_ + 1.0, w) * (cs), y1_ = dmais_clamp(fy_ + 1.0, h) * (rs); \
        float p00_ = (p)[y0_ + x0_], p01_ = (p)[y0_ + x1_], p10_ = (p)[y1_ + x0_], p11_ = (p)[y1_ + x1_]; \
        float t0_ = FMA(a_, p01_ - p00_, p00_), t1_ = FMA(a_, p11_ - p10_, p10_); \
        (OUT) = FMA(b_, t1_ - t0_, t0_); \
    } while (0)

    #define DMAIS_SAMPLE(NAME, FMA, TYPE) \
    static void NAME(const void *pixels, const Py_ssize_t *base, const Py_ssize_t *left, const Py_ssize_t *top, \
                     const Py_ssize_t *width, const Py_ssize_t *height, const Py_ssize_t *row, \
                     const Py_ssize_t *column, const Py_ssize_t *owner, const float *xy, Py_ssize_t n, float *out) { \
        const TYPE *buffer = (const TYPE *)pixels; \
        for (Py_ssize_t i = 0; i < n; i++) { \
            Py_ssize_t k = owner ? owner[i] : 0; \
            float x = xy[2 * i] - (float)left[k], y = xy[2 * i + 1] - (float)top[k]; \
            if (!(isfinite(x) && isfinite(y))) { out[i] = NAN; continue; } \
            DMAIS_BILINEAR(FMA, out[i], buffer + base[k], x, y, width[k], height[k], row[k], column[k]); \
        } \
    }

    /* The pixels' kinds: float32, uint16, uint8 (read as float32, exactly). */
    typedef void (*dmais_sample_fn)(const void *, const Py_ssize_t *, const Py_ssize_t *, const Py_ssize_t *,
                                    const Py_ssize_t *, const Py_ssize_t *, const Py_ssize_t *, const Py_ssize_t *,
                                    const Py_ssize_t *, const float *, Py_ssize_t, float *);
    DMAIS_SAMPLE(dmais_sample_libm_f32, fmaf, float)
    DMAIS_SAMPLE(dmais_sample_libm_u16, fmaf, unsigned short)
    DMAIS_SAMPLE(dmais_sample_libm_u8, fmaf, unsigned char)
    static const dmais_sample_fn dmais_sample_libm[3] = {dmais_sample_libm_f32, dmais_sample_libm_u16,
                                                         dmais_sample_libm_u8};
    #if defined(__x86_64__) && defined(__GNUC__)
    __attribute__((target("fma"))) DMAIS_SAMPLE(dmais_sample_fma_f32, __builtin_fmaf, float)
    __attribute__((target("fma"))) DMAIS_SAMPLE(dmais_sample_fma_u16, __builtin_fmaf, unsigned short)
    __attribute__((target("fma"))) DMAIS_SAMPLE(dmais_sample_fma_u8, __builtin_fmaf, unsigned char)
    static const dmais_sample_fn dmais_sample_fma[3] = {dmais_sample_fma_f32, dmais_sample_fma_u16,
                                                        dmais_sample_fma_u8};
    static void dmais_sample(int kind, const void *buffer, const Py_ssize_t *base, const Py_ssize_t *left,
                             const Py_ssize_t *top, const Py_ssize_t *width, const Py_ssize_t *height,
                             const Py_ssize_t *row, const Py_ssize_t *column, const Py_ssize_t *owner, const float *xy,
                             Py_ssize_t n, float *out) {
        __builtin_cpu_init();  /* idempotent: the CPU's features known whatever ran first */
        (__builtin_cpu_supports("fma") ? dmais_sample_fma : dmais_sample_libm)[kind](
            buffer, base, left, top, width, height, row, column, owner, xy, n, out);
    }
    #else
    static void dmais_sample(int kind, const void *buffer, const Py_ssize_t *base, const Py_ssize_t *left,
                             const Py_ssize_t *top, const Py_ssize_t *width, const Py_ssize_t *height,
                             const Py_ssize_t *row, const Py_ssize_t *column, const Py_ssize_t *owner, const float *xy,
                             Py_ssize_t n, float *out) {
        dmais_sample_libm[kind](buffer, base, left, top, width, height, row, column, owner, xy, n, out);
    }
    #endif

    /* `cell` (below) in C: floor(value / cell_px) clamped into 0..count - 1, 0 where not finite or beyond int64. */
    static inline Py_ssize_t dmais_cell(float value, Py_ssize_t cell_px, Py_ssize_t count) {
        double q = (double)value / cell_px;
        if (!(q > -9.2e18 && q < 9.2e18)) return 0;
        if (q < 1.0) return 0;
        if (q >= count - 1) return count - 1;
        return (Py_ssize_t)q;
    }

    /* One ring's k samples into out (k): at the float32 positions (float)(cx + scale ring[2 j]),
       (float)(cy + scale ring[2 j + 1]) (each sum in double, then rounded, as `ring_points`), each of the
       part of its cell in cells (cell_rows x cell_columns; NULL: part 0), as `ring_points` and `dmais_sample`
       make them, with no array of positions or parts between. bounds (NULL: none): the least and largest x and y
       offsets of ring (4, finite): with scale >= 0 the extremes of the positions are those of the bounds (each
       rounding does not decrease with its operand), and where they lie within +-2^30 in one cell, every position
       is in that cell (nor does a coordinate's cell), so the ring's part is looked up once. */
    #define DMAIS_RING(NAME, FMA, TYPE) \
    static void NAME(const void *pixels, const Py_ssize_t *base, const Py_ssize_t *left, const Py_ssize_t *top, \
                     const Py_ssize_t *width, const Py_ssize_t *height, const Py_ssize_t *row, \
                     const Py_ssize_t *column, const Py_ssize_t *cells, Py_ssize_t cell_rows, \
                     Py_ssize_t cell_columns, Py_ssize_t cell_px, double cx, double cy, double scale, \
                     const double *ring, const double *bounds, Py_ssize_t k, float *out) { \
        const TYPE *buffer = (const TYPE *)pixels; \
        Py_ssize_t one = 0; \
        if (cells) { \
            one = -1; \
            if (bounds && scale >= 0.0) { \
                float x_lo = (float)(cx + scale * bounds[0]), x_hi = (float)(cx + scale * bounds[1]); \
                float y_lo = (float)(cy + scale * bounds[2]), y_hi = (float)(cy + scale * bounds[3]); \
                if (x_lo > -1073741824.0f && x_hi < 1073741824.0f && y_lo > -1073741824.0f && y_hi < 1073741824.0f) { \
                    Py_ssize_t c0 = dmais_cell(x_lo, cell_px, cell_columns), c1 = dmais_cell(x_hi, cell_px, cell_columns); \
                    Py_ssize_t r0 = dmais_cell(y_lo, cell_px, cell_rows), r1 = dmais_cell(y_hi, cell_px, cell_rows); \
                    if (c0 == c1 && r0 == r1) one = cells[r0 * cell_columns + c0]; \
                } \
            } \
        } \
        if (one >= 0) { /* one part: its numbers in locals (no store to out can change them) */ \
            const TYPE *p = buffer + base[one]; \
            float fl = (float)left[one], ft = (float)top[one]; \
            Py_ssize_t w = width[one], h = height[one], rs = row[one], cs = column[one]; \
            double w_last = (double)(w - 1), h_last = (double)(h - 1); \
            if (bounds && scale >= 0.0) { \
                /* Every position within the part's pixels but its last row and column (the extremes' are: \
                   each rounding does not decrease with its operand): no clamp changes an index, every \
                   position is finite, so neither is made. */ \
                float x_lo = (float)(cx + scale * bounds[0]) - fl, x_hi = (float)(cx + scale * bounds[1]) - fl; \
                float y_lo = (float)(cy + scale * bounds[2]) - ft, y_hi = (float)(cy + scale * bounds[3]) - ft; \
                if (x_lo >= 0.0f && y_lo >= 0.0f && x_hi < (float)w_last && y_hi < (float)h_last \
                        && x_hi < 1073741824.0f && y_hi < 1073741824.0f) { \
                    for (Py_ssize_t j = 0; j < k; j++) { \
                        float x = (float)(cx + scale * ring[2 * j]) - fl, y = (float)(cy + scale * ring[2 * j + 1]) - ft; \
                        float fx = dmais_floor(x), fy = dmais_floor(y); \
                        float a = x - fx, b = y - fy; \
                        Py_ssize_t x0 = (Py_ssize_t)fx * cs, y0 = (Py_ssize_t)fy * rs; \
                        Py_ssize_t x1 = x0 + cs, y1 = y0 + rs; \
                        float p00 = p[y0 + x0], p01 = p[y0 + x1], p10 = p[y1 + x0], p11 = p[y1 + x1]; \
                        float t0 = FMA(a, p01 - p00, p00), t1 = FMA(a, p11 - p10, p10); \
                        out[j] = FMA(b, t1 - t0, t0); \
                    } \
                    return; \
                } \
            } \
            for (Py_ssize_t j = 0; j < k; j++) { \
                float x = (float)(cx + scale * ring[2 * j]) - fl, y = (float)(cy + scale * ring[2 * j + 1]) - ft; \
                if (!(isfinite(x) && isfinite(y))) { out[j] = NAN; continue; } \
                float fx = dmais_floor(x), fy = dmais_floor(y); \
                float a = x - fx, b = y - fy; \
                double dx = fx, dy = fy, dx1 = fx + 1.0, dy1 = fy + 1.0; \
                Py_ssize_t x0 = (dx <= 0.0 ? 0 : (dx >= w_last ? w - 1 : (Py_ssize_t)dx)) * cs; \
                Py_ssize_t y0 = (dy <= 0.0 ? 0 : (dy >= h_last ? h - 1 : (Py_ssize_t)dy)) * rs; \
                Py_ssize_t x1 = (dx1 <= 0.0 ? 0 : (dx1 >= w_last ? w - 1 : (Py_ssize_t)dx1)) * cs; \
                Py_ssize_t y1 = (dy1 <= 0.0 ? 0 : (dy1 >= h_last ? h - 1 : (Py_ssize_t)dy1)) * rs; \
                float p00 = p[y0 + x0], p01 = p[y0 + x1], p10 = p[y1 + x0], p11 = p[y1 + x1]; \
                float t0 = FMA(a, p01 - p00, p00), t1 = FMA(a, p11 - p10, p10); \
                out[j] = FMA(b, t1 - t0, t0); \
            } \
            return; \
        } \
        for (Py_ssize_t j = 0; j < k; j++) { \
            float px = (float)(cx + scale * ring[2 * j]), py = (float)(cy + scale * ring[2 * j + 1]); \
            Py_ssize_t q = cells[dmais_cell(py, cell_px, cell_rows) * cell_columns + dmais_cell(px, cell_px, cell_columns)]; \
            float x = px - (float)left[q], y = py - (float)top[q]; \
            if (!(isfinite(x) && isfinite(y))) { out[j] = NAN; continue; } \
            DMAIS_BILINEAR(FMA, out[j], buffer + base[q], x, y, width[q], height[q], row[q], column[q]); \
        } \
    }

    typedef void (*dmais_ring_fn)(const void *, const Py_ssize_t *, const Py_ssize_t *, const Py_ssize_t *,
                                  const Py_ssize_t *, const Py_ssize_t *, const Py_ssize_t *, const Py_ssize_t *,
                                  const Py_ssize_t *, Py_ssize_t, Py_ssize_t, Py_ssize_t, double, double, double,
                                  const double *, const double *, Py_ssize_t, float *);
    DMAIS_RING(dmais_ring_libm_f32, fmaf, float)
    DMAIS_RING(dmais_ring_libm_u16, fmaf, unsigned short)
    DMAIS_RING(dmais_ring_libm_u8, fmaf, unsigned char)
    static const dmais_ring_fn dmais_ring_libm[3] = {dmais_ring_libm_f32, dmais_ring_libm_u16, dmais_ring_libm_u8};
    #if defined(__x86_64__) && defined(__GNUC__)
    __attribute__((target("fma"))) DMAIS_RING(dmais_ring_fma_f32, __builtin_fmaf, float)
    __attribute__((target("fma"))) DMAIS_RING(dmais_ring_fma_u16, __builtin_fmaf, unsigned short)
    __attribute__((target("fma"))) DMAIS_RING(dmais_ring_fma_u8, __builtin_fmaf, unsigned char)
    static const dmais_ring_fn dmais_ring_fma[3] = {dmais_ring_fma_f32, dmais_ring_fma_u16, dmais_ring_fma_u8};
    /* The ring sampler of this CPU (the FMA instruction's where it has one) for pixels of `kind`, chosen once per
       call of a loop. */
    static dmais_ring_fn dmais_ring_of_cpu(int kind) {
        __builtin_cpu_init();
        return (__builtin_cpu_supports("fma") ? dmais_ring_fma : dmais_ring_libm)[kind];
    }
    #else
    static dmais_ring_fn dmais_ring_of_cpu(int kind) { return dmais_ring_libm[kind]; }
    #endif
    """
    ctypedef void (*dmais_ring_fn)(const void *, const Py_ssize_t *, const Py_ssize_t *, const Py_ssize_t *,
                                   const Py_ssize_t *, const Py_ssize_t *, const Py_ssize_t *, const Py_ssize_t *,
                                   const Py_ssize_t *, Py_ssize_t, Py_ssize_t, Py_ssize_t, double, double, double,
                                   const double *, const double *, Py_ssize_t, float *) noexcept nogil
    dmais_ring_fn dmais_ring_of_cpu(int kind) noexcept nogil
    void dmais_sample(int kind, const void *buffer, const Py_ssize_t *base, const Py_ssize_t *left, const Py_ssize_t *top,
                      const Py_ssize_t *width, const Py_ssize_t *height, const Py_ssize_t *row,
                      const Py_ssize_t *column, const Py_ssize_t *owner, const float *xy, Py_ssize_t n,
                      float *out) noexcept nogil


def sample(image, xy):
    """(n,) float32 samples of the float32 image (h, w) at float32 positions xy (n, 2)."""
    cdef const float[:, :] img = image
    cdef const float[:, ::1] p = np.ascontiguousarray(xy, dtype=np.float32)
    out = np.empty(p.shape[0], dtype=np.float32)
    cdef float[::1] o = out
    cdef Py_ssize_t zero = 0, width = img.shape[1], height = img.shape[0]
    cdef Py_ssize_t row = img.strides[0] // 4, column = img.strides[1] // 4
    if p.shape[0]:
        with nogil:
            dmais_sample(0, &img[0, 0], &zero, &zero, &zero, &width, &height, &row, &column, NULL, &p[0, 0], p.shape[0],
                         &o[0])
    return out


cdef int pixel_kind(buffer) except -1:
    """The kind of a parts' flat buffer (1-D, C-contiguous) for the C samplers: 0 float32, 1 uint16, 2 uint8."""
    if buffer.ndim != 1 or not buffer.flags.c_contiguous:
        raise ValueError("the parts' pixels must be one flat C-ordered buffer")
    if buffer.dtype == np.float32:
        return 0
    if buffer.dtype == np.uint16:
        return 1
    if buffer.dtype == np.uint8:
        return 2
    raise TypeError(f"parts of {buffer.dtype} pixels (float32, uint16 or uint8 only)")


cdef const void *pixel_data(const unsigned char[::1] view) noexcept:
    """The address of a flat buffer's first byte (its bytes `view`), NULL where it has none."""
    return <const void *> &view[0] if view.shape[0] else NULL


cdef float pixel_value(const void *data, int kind, Py_ssize_t at) noexcept nogil:
    """The pixel `at` of a flat buffer of `kind` (`pixel_kind`), as float32 (exact)."""
    if kind == 0:
        return (<const float *> data)[at]
    if kind == 1:
        return <float> (<const unsigned short *> data)[at]
    return <float> (<const unsigned char *> data)[at]


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


cdef const double *ring_bounds(const double *ring, Py_ssize_t k, double *extremes) noexcept nogil:
    """The least and largest x and y of the offsets ring (k, 2) into extremes (4), and extremes; NULL where
    one is not finite (then every position's part is looked up)."""
    cdef Py_ssize_t j
    extremes[0] = extremes[1] = ring[0]
    extremes[2] = extremes[3] = ring[1]
    for j in range(k):
        if not (isfinite(ring[2 * j]) and isfinite(ring[2 * j + 1])):
            return NULL
        extremes[0] = ring[2 * j] if ring[2 * j] < extremes[0] else extremes[0]
        extremes[1] = ring[2 * j] if ring[2 * j] > extremes[1] else extremes[1]
        extremes[2] = ring[2 * j + 1] if ring[2 * j + 1] < extremes[2] else extremes[2]
        extremes[3] = ring[2 * j + 1] if ring[2 * j + 1] > extremes[3] else extremes[3]
    return extremes


def parts_sample(buffer, bases, lefts, tops, widths, heights, rows, part, xy):
    """(n,) float32 samples at float32 positions xy (n, 2) (whole-image coordinates) of the parts of
    `rings.ImageParts` (its flat buffer of float32, uint16 or uint8 pixels, and per part its offset in it,
    left, top, width, height and row stride), each position read from the part `part` (n,) in its own
    coordinates (x - left, y - top: exact in float32)."""
    cdef int kind = pixel_kind(buffer)
    cdef const void *buf = pixel_data(buffer.view(np.uint8))
    cdef const Py_ssize_t[::1] row = np.ascontiguousarray(rows, dtype=np.intp)
    cdef const Py_ssize_t[::1] base = np.ascontiguousarray(bases, dtype=np.intp)
    cdef const Py_ssize_t[::1] left = np.ascontiguousarray(lefts, dtype=np.intp)
    cdef const Py_ssize_t[::1] top = np.ascontiguousarray(tops, dtype=np.intp)
    cdef const Py_ssize_t[::1] width = np.ascontiguousarray(widths, dtype=np.intp)
    cdef const Py_ssize_t[::1] height = np.ascontiguousarray(heights, dtype=np.intp)
    cdef const Py_ssize_t[::1] column = np.ones(len(width), dtype=np.intp)
    cdef const Py_ssize_t[::1] owner = np.ascontiguousarray(part, dtype=np.intp)
    cdef const float[:, ::1] p = np.ascontiguousarray(xy, dtype=np.float32)
    out = np.empty(p.shape[0], dtype=np.float32)
    cdef float[::1] o = out
    if p.shape[0]:
        with nogil:
            dmais_sample(kind, buf, &base[0], &left[0], &top[0], &width[0], &height[0], &row[0], &column[0],
                         &owner[0], &p[0, 0], p.shape[0], &o[0])
    return out




cdef inline double unit_clip(double x) noexcept nogil:
    """np.clip(x, 0, 1) (NaN stays NaN)."""
    if x != x:
        return x
    return 0.0 if x < 0.0 else (1.0 if x > 1.0 else x)


def ring_stats(values):
    """`rings.ring_stats` of rings values (m, k), each number as numpy makes it (the same operations,
    the sums in np.sum's order): quality (m,), bright level (m,), dark level (m,), bright mask (m, k)."""
    cdef const double[:, ::1] v = np.ascontiguousarray(values, dtype=np.float64)
    cdef Py_ssize_t m = v.shape[0], k = v.shape[1], i
    quality, bright, dark = np.empty(m), np.empty(m), np.empty(m)
    mask = np.empty((m, k), dtype=bool)
    cdef double[::1] q = quality, hi = bright, lo = dark
    cdef unsigned char[:, ::1] h = mask.view(np.uint8)
    scratch = np.empty(k)
    cdef double[::1] t = scratch
    if k == 0:
        raise ValueError("rings of no samples")
    with nogil:
        for i in range(m):
            one_ring(&v[i, 0], k, &t[0], &h[i, 0], &q[i], &hi[i], &lo[i])
    return quality, bright, dark, mask


cdef void one_ring(const double *v, Py_ssize_t k, double *t, unsigned char *h, double *quality, double *bright,
                   double *dark) noexcept nogil:
    """`ring_stats` of one ring v (k): its quality, bright and dark levels, its bright mask into h (k);
    t: k doubles of scratch."""
    cdef Py_ssize_t j, half = k // 2, transitions, n_high = 0
    cdef double mean = pairwise_sum(v, k) / <double>k, total, mean_high, mean_low, within, opposite, bimodal
    for j in range(k):
        h[j] = v[j] > mean
        n_high += h[j]
    transitions = h[0] != h[k - 1]
    for j in range(1, k):
        transitions += h[j] != h[j - 1]
    for j in range(k):
        t[j] = (v[j] - mean) * (v[j] - mean)
    total = pairwise_sum(t, k) + 1e-9
    for j in range(k):
        t[j] = v[j] if h[j] else 0.0
    mean_high = pairwise_sum(t, k) / <double>(n_high if n_high > 1 else 1)
    for j in range(k):
        t[j] = 0.0 if h[j] else v[j]
    mean_low = pairwise_sum(t, k) / <double>(k - n_high if k - n_high > 1 else 1)
    for j in range(k):
        t[j] = v[j] - (mean_high if h[j] else mean_low)
        t[j] = t[j] * t[j]
    within = pairwise_sum(t, k)
    bimodal = unit_clip(1.0 - within / total)
    for j in range(k):
        opposite = v[k - half + j] if j < half else v[j - half]  # np.roll by k // 2
        t[j] = (v[j] - opposite) * (v[j] - opposite)
    quality[0] = bimodal * unit_clip(1.0 - pairwise_sum(t, k) / (2.0 * total)) if transitions == 4 else 0.0
    bright[0], dark[0] = mean_high, mean_low


def clean_radius(buffer, bases, lefts, tops, widths, heights, rows, columns, cells, Py_ssize_t cell_px, uv, radii,
                 unit, double min_quality, double max_first):
    """`rings.clean_radius` (n,) about uv (n, 2) of an image given as parts (`rings.ImageParts`' flat
    buffer, per part its offset, left, top, width, height and row and column strides, the map
    `cells` (r, c) of the part each cell of cell_px reads, or None: every sample from part 0), on
    rings of radii (m,) with the unit ring `unit` (k, 2): each ring's samples, statistics and tests
    as numpy makes them."""
    cdef int kind = pixel_kind(buffer)
    cdef const void *buf = pixel_data(buffer.view(np.uint8))
    cdef const Py_ssize_t[::1] base = np.ascontiguousarray(bases, dtype=np.intp)
    cdef const Py_ssize_t[::1] left = np.ascontiguousarray(lefts, dtype=np.intp)
    cdef const Py_ssize_t[::1] top = np.ascontiguousarray(tops, dtype=np.intp)
    cdef const Py_ssize_t[::1] width = np.ascontiguousarray(widths, dtype=np.intp)
    cdef const Py_ssize_t[::1] height = np.ascontiguousarray(heights, dtype=np.intp)
    cdef const Py_ssize_t[::1] row = np.ascontiguousarray(rows, dtype=np.intp)
    cdef const Py_ssize_t[::1] column = np.ascontiguousarray(columns, dtype=np.intp)
    cdef const Py_ssize_t[:, ::1] cell_map = np.zeros((1, 1), dtype=np.intp) if cells is None else \
        np.ascontiguousarray(cells, dtype=np.intp)
    cdef bint one_part = cells is None
    cdef const double[:, ::1] p = np.ascontiguousarray(uv, dtype=np.float64)
    cdef const double[::1] r = np.ascontiguousarray(radii, dtype=np.float64)
    cdef const double[:, ::1] ring = np.ascontiguousarray(unit, dtype=np.float64)
    cdef Py_ssize_t n = p.shape[0], k = ring.shape[0], i, j, a, same_count
    result = np.zeros(n)
    cdef double[::1] out = result
    work = np.empty(4 * k)
    cdef double[::1] w = work
    samples = np.empty(k, dtype=np.float32)
    cdef float[::1] s = samples
    masks = np.empty((2, k), dtype=np.uint8)
    cdef unsigned char[:, ::1] m = masks  # this ring's and the reference
    cdef double quality, high, low, ref_high, ref_low, contrast
    cdef bint started, ok, same
    if k == 0 or n == 0:
        return result
    cdef dmais_ring_fn ring_of = dmais_ring_of_cpu(kind)
    cdef double extremes[4]
    cdef const double *bounds = ring_bounds(&ring[0, 0], k, extremes)
    with nogil:
        for i in range(n):
            started, ref_high, ref_low = False, 0.0, 0.0
            for a in range(r.shape[0]):
                ring_of(buf, &base[0], &left[0], &top[0], &width[0], &height[0], &row[0], &column[0],
                        NULL if one_part else &cell_map[0, 0], cell_map.shape[0], cell_map.shape[1], cell_px,
                        p[i, 0], p[i, 1], r[a], &ring[0, 0], bounds, k, &s[0])
                for j in range(k):
                    w[j] = s[j]
                one_ring(&w[0], k, &w[k], &m[0, 0], &quality, &high, &low)
                ok = quality >= min_quality
                if started:
                    contrast = ref_high - ref_low
                    contrast = contrast if contrast > 1e-9 else (contrast if contrast != contrast else 1e-9)
                    same_count = 0
                    for j in range(k):
                        same_count += m[0, j] == m[1, j]
                    same = (same_count / <double>k >= 0.9 and high >= ref_high - 0.25 * contrast
                            and low <= ref_low + 0.25 * contrast)
                    ok = ok and same
                elif ok:
                    for j in range(k):
                        m[1, j] = m[0, j]
                if ok:
                    ref_high, ref_low = high, low
                    out[i] = r[a]
                if (started and not ok) or (not started and not ok and r[a] >= max_first):
                    break
                started = started or ok
    return result


def ring_samples(buffer, bases, lefts, tops, widths, heights, rows, columns, cells, Py_ssize_t cell_px, centres,
                 offsets):
    """(m, k) float32 samples at the float32 positions centres (m, 2) + offsets (k, 2) (each sum in float64,
    then rounded, as numpy's sum and astype make them) of an image given as parts (`clean_radius`'s)."""
    cdef int kind = pixel_kind(buffer)
    cdef const void *buf = pixel_data(buffer.view(np.uint8))
    cdef const Py_ssize_t[::1] base = np.ascontiguousarray(bases, dtype=np.intp)
    cdef const Py_ssize_t[::1] left = np.ascontiguousarray(lefts, dtype=np.intp)
    cdef const Py_ssize_t[::1] top = np.ascontiguousarray(tops, dtype=np.intp)
    cdef const Py_ssize_t[::1] width = np.ascontiguousarray(widths, dtype=np.intp)
    cdef const Py_ssize_t[::1] height = np.ascontiguousarray(heights, dtype=np.intp)
    cdef const Py_ssize_t[::1] row = np.ascontiguousarray(rows, dtype=np.intp)
    cdef const Py_ssize_t[::1] column = np.ascontiguousarray(columns, dtype=np.intp)
    cdef const Py_ssize_t[:, ::1] cell_map = np.zeros((1, 1), dtype=np.intp) if cells is None else \
        np.ascontiguousarray(cells, dtype=np.intp)
    cdef bint one_part = cells is None
    cdef const double[:, ::1] p = np.ascontiguousarray(centres, dtype=np.float64)
    cdef const double[:, ::1] ring = np.ascontiguousarray(offsets, dtype=np.float64)
    cdef Py_ssize_t m = p.shape[0], k = ring.shape[0], i
    out = np.empty((m, k), dtype=np.float32)
    cdef float[:, ::1] o = out
    if k == 0 or m == 0:
        return out
    cdef dmais_ring_fn ring_of = dmais_ring_of_cpu(kind)
    cdef double extremes[4]
    cdef const double *bounds = ring_bounds(&ring[0, 0], k, extremes)
    with nogil:
        for i in range(m):
            ring_of(buf, &base[0], &left[0], &top[0], &width[0], &height[0], &row[0], &column[0],
                    NULL if one_part else &cell_map[0, 0], cell_map.shape[0], cell_map.shape[1], cell_px,
                    p[i, 0], p[i, 1], 1.0, &ring[0, 0], bounds, k, &o[i, 0])  # 1.0 * x is x
    return out


def parts_gather(buffer, bases, lefts, tops, widths, heights, rows, cells, Py_ssize_t cell_px, ys, xs):
    """(n,) float32 pixels at integer positions ys, xs (n,) (whole-image coordinates) of the parts of
    `rings.ImageParts` (its flat buffer of float32, uint16 or uint8 pixels, per part its offset, left, top,
    width, height and row stride, and the map `cells` (r, c) of the part each cell of cell_px holds): each
    from the part of its cell, its row and column clamped into that part (`ImageParts.__getitem__`'s)."""
    cdef int kind = pixel_kind(buffer)
    cdef const void *buf = pixel_data(buffer.view(np.uint8))
    cdef const Py_ssize_t[::1] stride = np.ascontiguousarray(rows, dtype=np.intp)
    cdef const Py_ssize_t[::1] base = np.ascontiguousarray(bases, dtype=np.intp)
    cdef const Py_ssize_t[::1] left = np.ascontiguousarray(lefts, dtype=np.intp)
    cdef const Py_ssize_t[::1] top = np.ascontiguousarray(tops, dtype=np.intp)
    cdef const Py_ssize_t[::1] width = np.ascontiguousarray(widths, dtype=np.intp)
    cdef const Py_ssize_t[::1] height = np.ascontiguousarray(heights, dtype=np.intp)
    cdef const Py_ssize_t[:, ::1] cell_map = np.ascontiguousarray(cells, dtype=np.intp)
    cdef const Py_ssize_t[::1] y = np.ascontiguousarray(ys, dtype=np.intp)
    cdef const Py_ssize_t[::1] x = np.ascontiguousarray(xs, dtype=np.intp)
    cdef Py_ssize_t n = y.shape[0], i, k, row, column
    out = np.empty(n, dtype=np.float32)
    cdef float[::1] o = out
    with nogil:
        for i in range(n):
            k = cell_map[index_cell(y[i], cell_px, cell_map.shape[0]), index_cell(x[i], cell_px, cell_map.shape[1])]
            row = clamp_index(y[i] - top[k], height[k])
            column = clamp_index(x[i] - left[k], width[k])
            o[i] = pixel_value(buf, kind, base[k] + row * stride[k] + column)
    return out


cdef inline Py_ssize_t clamp_index(Py_ssize_t value, Py_ssize_t size) noexcept nogil:
    """value clamped into 0..size - 1."""
    return 0 if value < 0 else (size - 1 if value > size - 1 else value)


cdef inline Py_ssize_t index_cell(Py_ssize_t value, Py_ssize_t cell_px, Py_ssize_t count) noexcept nogil:
    """floor(value / cell_px) clamped into 0..count - 1 (a negative value's cell is 0 either way)."""
    return clamp_index(value // cell_px if value >= 0 else 0, count)


def strided_ranks_u16(values, Py_ssize_t step, Py_ssize_t low, Py_ssize_t high):
    """(the value of rank low, of rank high) (0-based, ascending) among values[::step] of the uint16 values
    (n,) (C-contiguous), as np.sort(values[::step])[[low, high]] has them: from the sampled values' counts
    in one pass, without the strided copy (`detect._percentile_u16`'s order statistics, the 16-bit scale's)."""
    cdef const unsigned short[::1] v = values
    cdef Py_ssize_t n = v.shape[0], i, value, seen = 0, found_low = -1, found_high = -1
    if step < 1 or n == 0 or low < 0 or high < low or high >= (n + step - 1) // step:
        raise ValueError("ranks beyond the sampled values")
    counts = np.zeros(65536, dtype=np.intp)
    cdef Py_ssize_t[::1] c = counts
    with nogil:
        i = 0
        while i < n:
            c[v[i]] += 1
            i += step
        for value in range(65536):
            seen += c[value]
            if found_low < 0 and seen > low:
                found_low = value
            if seen > high:
                found_high = value
                break
    return found_low, found_high
