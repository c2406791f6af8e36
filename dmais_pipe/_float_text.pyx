# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled text of float64 cells (`files.csv_text`): each cell exactly Python's repr(float(x)), NaN empty,
~100 ns a cell against float.__repr__'s 400-800 (David Gay's dtoa in big integers); about half of what
is left is making the str.

A normal double x = m 2**e (2**52 <= m < 2**53) is the double nearest to every number of the interval
between the midpoints to its neighbours (the lower midpoint a quarter ulp below where m = 2**52, as the
double below has half the spacing); the midpoints themselves read back as x where m is even (reading
rounds half to even). repr writes the decimal of that interval with the fewest significant digits and,
of two such, the one nearest x. Here x 10**p = 4m 5**p / 2**j with p chosen so that x 10**p lies in
[10**16, 2 10**17) (the interval is then wider than 1.1 in those units: it holds an integer) and j >= 0.
4m 5**p and the ends (4m - 1 or 2) 5**p, (4m + 2) 5**p fit in 127 bits (unsigned __int128), so the
interval's first and last integers are exact shifts; the interval is divided by 10 while it still holds
an integer, and the nearest of the integers left is found from the exact remainder. That holds for
2**-49 <= |x| < 2**55 (p <= 31); other cells (subnormals, tiny and huge magnitudes, infinities) and a tie
between two candidates (which the arithmetic rules out, but is not assumed) are float.__repr__'s.
tests/test_float_text.py compares with repr over a million doubles drawn many ways.

Reading (`cells_floats`, dataset.py's columns): float() of each cell without a call of float() per cell.
"""

import numpy as np

from cpython.list cimport PyList_New, PyList_SET_ITEM
from cpython.ref cimport Py_INCREF
from cpython.unicode cimport PyUnicode_1BYTE_DATA, PyUnicode_New
from libc.stdint cimport uint32_t, uint64_t
from libc.string cimport memcpy


cdef extern from *:
    """
    #if defined(__SIZEOF_INT128__)
    typedef unsigned __int128 dmais_u128;
    #define DMAIS_HAVE_U128 1
    #else  /* no 128-bit integers (MSVC): every cell is float.__repr__'s */
    typedef unsigned long long dmais_u128;
    #define DMAIS_HAVE_U128 0
    #endif
    """
    ctypedef unsigned long long u128 "dmais_u128"
    bint HAVE_U128 "DMAIS_HAVE_U128"


cdef uint64_t SIGN = 1ULL << 63, HIDDEN = 1ULL << 52, FRACTION = HIDDEN - 1, INFINITY_BITS = 0x7ffULL << 52
cdef u128 POW5[32]
cdef int _k
POW5[0] = 1
for _k in range(1, 32):
    POW5[_k] = POW5[_k - 1] * 5
cdef uint64_t POW10[20]
POW10[0] = 1
for _k in range(1, 20):
    POW10[_k] = POW10[_k - 1] * 10
cdef const char *PAIRS = b"00010203040506070809101112131415161718192021222324252627282930313233343536373839" \
    b"40414243444546474849505152535455565758596061626364656667686970717273747576777879" \
    b"8081828384858687888990919293949596979899"


cdef inline int fewer(uint64_t *lo, uint64_t *hi, uint64_t ten, int k) noexcept nogil:
    """k if the integers lo..hi include a multiple of ten = 10**k, lo and hi then in units of ten; else 0."""
    cdef uint64_t a = (lo[0] + ten - 1) // ten, b = hi[0] // ten
    if a > b:
        return 0
    lo[0], hi[0] = a, b
    return k


cdef bint shortest(uint64_t magnitude, uint64_t *digits, int *exponent) noexcept nogil:
    """Whether repr's digits of the positive normal double of bits `magnitude` are known here; if so,
    digits (no trailing zeros) * 10**exponent is the decimal repr writes."""
    cdef int e2 = <int>(magnitude >> 52) - 1023  # x = m 2**(e2 - 52)
    if not HAVE_U128 or e2 < -49 or e2 > 54:
        return False
    cdef uint64_t m = (magnitude & FRACTION) | HIDDEN
    cdef int p = 16 - ((e2 * 78913) >> 18)  # 78913 / 2**18 ~ log10(2), exact floors for |e2| < 1100
    cdef int j = 54 - e2 - p, d  # x 10**p = 4m 5**p / 2**j
    cdef u128 one = 1, five = POW5[p]
    cdef u128 scaled = <u128>(4 * m) * five
    cdef u128 low = <u128>(4 * m - (1 if m == HIDDEN else 2)) * five, high = <u128>(4 * m + 2) * five
    cdef uint64_t whole = <uint64_t>(scaled >> j), lo, hi, q, r, ten, c
    cdef u128 fraction = scaled - (<u128>whole << j), twice, span
    if m & 1 == 0:  # the midpoints read back as x
        lo, hi = <uint64_t>((low + (one << j) - 1) >> j), <uint64_t>(high >> j)
    else:
        lo, hi = <uint64_t>(low >> j) + 1, <uint64_t>((high - 1) >> j)
    if lo > hi:  # not expected: the interval is wider than 1
        return False
    d = fewer(&lo, &hi, 10, 1)  # most full-precision values (16, 17 digits) stop here
    if d:  # the most digits that can go, in steps of 16, 8, 4, 2, 1 (in this order: one statement each)
        d += fewer(&lo, &hi, 10000000000000000, 16)
        d += fewer(&lo, &hi, 100000000, 8)
        d += fewer(&lo, &hi, 10000, 4)
        d += fewer(&lo, &hi, 100, 2)
        d += fewer(&lo, &hi, 10, 1)
    ten = POW10[d]
    c = lo
    if lo < hi:  # the candidate nearest x: x 10**p - q ten against ten / 2, both times 2**(j + 1)
        q = whole // ten
        r = whole - q * ten
        twice, span = (<u128>r << (j + 1)) + 2 * fraction, <u128>ten << j
        if twice == span:
            return False
        c = min(max(q + (twice > span), lo), hi)
    digits[0], exponent[0] = c, d - p
    return True


cdef int decimal(uint64_t c, char *text) noexcept nogil:
    """Write c's decimal digits to the end of text (20 chars); their count."""
    cdef uint32_t low
    cdef int n = 20, k
    if c >= 100000000:  # the last 8 digits in 32 bits, a chain of their own
        low, c = <uint32_t>(c % 100000000), c // 100000000
        for k in range(4):
            n -= 2
            memcpy(&text[n], &PAIRS[2 * (low % 100)], 2)
            low //= 100
    while c >= 100:
        n -= 2
        memcpy(&text[n], &PAIRS[2 * (c % 100)], 2)
        c //= 100
    if c >= 10:
        n -= 2
        memcpy(&text[n], &PAIRS[2 * c], 2)
    else:
        n -= 1
        text[n] = <char>(48 + c)
    return 20 - n


cdef Py_ssize_t layout(uint64_t digits, int exponent, bint negative, char *out) noexcept nogil:
    """Write repr's text of -+digits 10**exponent (digits > 0 without trailing zeros, at most 17) to out
    (32 chars); its length. Positional where the decimal point is after point digits, -4 < point <= 16,
    with a digit after the point ('0.001', '1234567.0'), else 'd.ddde-05', '1e+16'."""
    cdef char text[20]
    cdef int n = decimal(digits, text), start = 20 - n, k, point, size = 0
    point = n + exponent
    if negative:
        out[0] = b'-'
        size = 1
    if point <= -4 or point > 16:
        out[size] = text[start]
        size += 1
        if n > 1:
            out[size] = b'.'
            memcpy(&out[size + 1], &text[start + 1], n - 1)
            size += n
        out[size] = b'e'
        out[size + 1] = b'-' if point <= 0 else b'+'
        k = point - 1 if point > 0 else 1 - point
        if k >= 100:
            out[size + 2] = <char>(48 + k // 100)
            size += 1
        memcpy(&out[size + 2], &PAIRS[2 * (k % 100)], 2)
        return size + 4
    if point <= 0:
        out[size], out[size + 1] = b'0', b'.'
        for k in range(-point):
            out[size + 2 + k] = b'0'
        memcpy(&out[size + 2 - point], &text[start], n)
        return size + 2 - point + n
    if point < n:
        memcpy(&out[size], &text[start], point)
        out[size + point] = b'.'
        memcpy(&out[size + point + 1], &text[start + point], n - point)
        return size + n + 1
    memcpy(&out[size], &text[start], n)
    for k in range(n, point):
        out[size + k] = b'0'
    out[size + point], out[size + point + 1] = b'.', b'0'
    return size + point + 2


def float_cells(values):
    """list of str (n,): repr(float(x)) of each x of the float64 values (n,), "" for NaN."""
    array = np.ascontiguousarray(values, dtype=np.float64)
    cdef const double[::1] x = array
    cdef const uint64_t[::1] bits = array.view(np.uint64)
    cdef Py_ssize_t n = x.shape[0], i, size
    cdef uint64_t magnitude, digits
    cdef int exponent
    cdef char text[32]
    cells = PyList_New(n)
    empty, zero, negative_zero = "", "0.0", "-0.0"
    for i in range(n):
        magnitude = bits[i] & ~SIGN
        if magnitude == 0:
            cell = negative_zero if bits[i] else zero
        elif magnitude > INFINITY_BITS:
            cell = empty
        elif shortest(magnitude, &digits, &exponent):
            size = layout(digits, exponent, bits[i] != magnitude, text)
            cell = PyUnicode_New(size, 127)
            memcpy(PyUnicode_1BYTE_DATA(cell), text, size)
        else:
            cell = float.__repr__(x[i])
        Py_INCREF(cell)
        PyList_SET_ITEM(cells, i, cell)
    return cells


cdef extern from "Python.h":
    bint PyUnicode_IS_COMPACT_ASCII(object o)
    Py_ssize_t PyUnicode_GET_LENGTH(object o)


cdef extern from "<locale.h>" nogil:
    ctypedef struct __locale_struct:
        pass
    ctypedef __locale_struct *locale_t
    int LC_ALL_MASK
    locale_t newlocale(int category_mask, const char *locale, locale_t base)


cdef extern from "<stdlib.h>" nogil:
    double strtod_l(const char *text, char **end, locale_t locale)


cdef locale_t C_LOCALE = newlocale(LC_ALL_MASK, b"C", <locale_t> NULL)  # a point is the decimal point
cdef unsigned char PLAIN[256]  # the characters of a plain decimal: digits, point, sign, exponent
cdef const char *_plain = b"0123456789.+-eE"
for _k in range(15):
    PLAIN[<unsigned char> _plain[_k]] = 1


cdef bint plain_cell(const unsigned char *text, Py_ssize_t size) noexcept nogil:
    """Whether the ASCII text holds one or more PLAIN characters and nothing else."""
    cdef Py_ssize_t i
    if size == 0:
        return False
    for i in range(size):
        if not PLAIN[text[i]]:
            return False
    return True


def cells_floats(cells, Py_ssize_t n):
    """(n,) float(cell) of each of the n str `cells` (a sequence), or None where one is not a number (an empty
    cell too). A cell of digits, point, sign and exponent alone is read by the C library's strtod in the C
    locale: like Python's reading, it rounds the decimal correctly (to nearest, ties to even; beyond the range
    to inf or 0), so the bits are float()'s (tests/test_float_text.py), at a third of its cost; a cell it does
    not read to its end is not a number, as float() would say. Any other cell (nan, inf, an underscore, a
    space, a non-ASCII digit) is float()'s own."""
    cdef Py_ssize_t i, size
    cdef char *end
    cdef const unsigned char *text
    out = np.empty(n, dtype=np.float64)
    cdef double[::1] x = out
    sequence = cells if type(cells) is list else list(cells)
    if len(sequence) != n:
        raise ValueError(f"cells_floats: {len(sequence)} cells, expected {n}")
    for i in range(n):
        cell = sequence[i]
        if C_LOCALE != NULL and type(cell) is str and PyUnicode_IS_COMPACT_ASCII(cell):
            size = PyUnicode_GET_LENGTH(cell)
            text = PyUnicode_1BYTE_DATA(cell)
            if plain_cell(text, size):
                x[i] = strtod_l(<const char *> text, &end, C_LOCALE)
                if end != <char *> text + size:
                    return None
                continue
        try:
            x[i] = float(cell)
        except ValueError:
            return None
    return out


def csv_lines(str header, columns):
    """header + "\\n" + the rows of `columns` (k lists of n str each: a row's cells joined by ",") each ended
    by "\\n": "\\n".join([header, *map(",".join, zip(*columns))]) + "\\n", in one pass where every cell is
    ASCII; None otherwise (the caller joins them)."""
    cdef Py_ssize_t k = len(columns), n = len(columns[0]) if k else 0, i, j, size, total
    cdef list column
    cdef char *out
    for column in columns:
        if len(column) != n:
            raise ValueError("csv_lines: the columns differ in length")
    if not PyUnicode_IS_COMPACT_ASCII(header):
        return None
    total = PyUnicode_GET_LENGTH(header) + 1 + n * k  # the header and its line end, the commas and line ends
    for column in columns:
        for i in range(n):
            cell = column[i]
            if type(cell) is not str or not PyUnicode_IS_COMPACT_ASCII(cell):
                return None
            total += PyUnicode_GET_LENGTH(cell)
    text = PyUnicode_New(total, 127)
    out = <char *> PyUnicode_1BYTE_DATA(text)
    size = PyUnicode_GET_LENGTH(header)
    memcpy(out, PyUnicode_1BYTE_DATA(header), size)
    out[size] = b"\n"
    out += size + 1
    for i in range(n):
        for j in range(k):
            cell = (<list> columns[j])[i]
            size = PyUnicode_GET_LENGTH(cell)
            memcpy(out, PyUnicode_1BYTE_DATA(cell), size)
            out[size] = b"," if j < k - 1 else b"\n"
            out += size + 1
    return text
