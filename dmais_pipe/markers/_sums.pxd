"""np.sum's order of a contiguous row's sum, shared by the markers' compiled cores."""


cdef inline double pairwise_sum(const double *a, Py_ssize_t n) noexcept nogil:
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
