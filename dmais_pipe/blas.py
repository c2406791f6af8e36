"""BLAS threading: the pose solver's small matrices run fastest on one OpenBLAS thread."""

from __future__ import annotations

import ctypes
from contextlib import contextmanager
from pathlib import Path


def _thread_setters() -> list:
    """`openblas_set_num_threads_local` of every OpenBLAS in /proc/self/maps (OpenBLAS >= 0.3.27)."""
    maps = Path("/proc/self/maps")
    paths = {line.split()[-1] for line in maps.read_text().splitlines() if "openblas" in line} if maps.exists() else set()
    setters = [getattr(ctypes.CDLL(path), "openblas_set_num_threads_local", None) for path in sorted(paths)]
    return [setter for setter in setters if setter is not None]


def limit_blas_threads() -> None:
    """One OpenBLAS thread for the rest of this thread's life (e.g. a worker thread's initializer)."""
    for setter in _thread_setters():
        setter(1)


@contextmanager
def single_threaded_blas():
    """Limit the OpenBLAS copies loaded by numpy and scipy to one thread in this thread, restored after.

    The solver's matrices are small (at most 118 x 158): threads gain nothing there, while on a
    busy 2-core machine their hand-offs cost milliseconds per solve. The paper's C++ figures are
    single-threaded too. Does nothing where there is no OpenBLAS.
    """
    previous = [(setter, setter(1)) for setter in _thread_setters()]
    try:
        yield
    finally:
        for setter, threads in previous:
            setter(threads)
