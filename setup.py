"""Builds the compiled cores of the pose solver and of its refinement and RANSAC; everything else is configured in pyproject.toml.

The cores are built for the CPU they are built on (`make install` compiles them on the user's
machine): -march=native lets GCC/Clang vectorize the row operations of the elimination template
and the Hessenberg reduction with AVX2 (~12% off a solve on this machine), and -ffp-contract=off
keeps every rounding as in a portable build (no fused multiply-adds), so the candidates are the
same bit for bit. DMAIS_PORTABLE_BUILD=1 builds for any CPU of the architecture instead (for a
wheel or a build shared between machines). -fno-wrapv undoes CPython's -fwrapv (which Cython's
code does not need): with it, GCC cannot count the iterations of loops indexed by a C int and
leaves them scalar, e.g. the column updates of the QR iteration.
"""

import os
import platform
import sys

from Cython.Build import cythonize
from setuptools import Extension, setup


def compile_args() -> list[str]:
    """Compiler flags of the cores (GCC / Clang): tuned to this CPU unless DMAIS_PORTABLE_BUILD is set."""
    if sys.platform == "win32":
        return []
    if os.environ.get("DMAIS_PORTABLE_BUILD") or platform.machine() not in ("x86_64", "AMD64"):
        return ["-fno-wrapv"]
    return ["-fno-wrapv", "-march=native", "-ffp-contract=off"]


setup(ext_modules=cythonize([
    Extension("dmais_pipe.pose._kernels", ["dmais_pipe/pose/_kernels.pyx"], extra_compile_args=compile_args()),
    Extension("dmais_pipe.pose._refine", ["dmais_pipe/pose/_refine.pyx"], extra_compile_args=compile_args()),
]))
