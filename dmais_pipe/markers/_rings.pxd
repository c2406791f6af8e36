"""What markers/_rings.pyx shares with the other markers' cores: one ring's statistics."""


cdef void one_ring(const double *v, Py_ssize_t k, double *t, unsigned char *h, double *quality, double *bright,
                   double *dark) noexcept nogil
