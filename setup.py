"""Builds the compiled cores of the pose solver and its tighter certificate, of its refinement and RANSAC,
of the markers' fit and samples and of the CSV tables' float cells; everything else is configured in pyproject.toml.

The cores are built for the CPU they are built on (`make install` compiles them on the user's
machine): -march=native lets GCC/Clang vectorize the row operations of the elimination template
and the Hessenberg reduction with AVX2 (~12% off a solve on this machine), and -ffp-contract=off
keeps every rounding as in a portable build (no fused multiply-adds), so the candidates are the
same bit for bit. DMAIS_PORTABLE_BUILD=1 builds for any CPU of the architecture instead (for a
wheel or a build shared between machines). A tuned build records the build CPU's flags in
dmais_pipe/pose/_build_cpu.txt, which `pose.build_cpu` checks before loading the cores (a cluster
node without the build CPU's AVX-512 gets one clear error, not an illegal instruction).
-fno-wrapv undoes CPython's -fwrapv (which Cython's code does not need): with it, GCC cannot
count the iterations of loops indexed by a C int and leaves them scalar, e.g. the column updates
of the QR iteration.
"""

import os
import platform
import sys
from pathlib import Path

from Cython.Build import cythonize
from setuptools import Extension, setup


BUILD_CPU_RECORD = Path(__file__).parent / "dmais_pipe" / "pose" / "_build_cpu.txt"


def tuned() -> bool:
    """Whether the cores are built for this CPU (x86-64 with GCC / Clang, DMAIS_PORTABLE_BUILD unset)."""
    return (sys.platform != "win32" and not os.environ.get("DMAIS_PORTABLE_BUILD")
            and platform.machine() in ("x86_64", "AMD64"))


def compile_args() -> list[str]:
    """Compiler flags of the cores (GCC / Clang): tuned to this CPU unless DMAIS_PORTABLE_BUILD is set."""
    if sys.platform == "win32":
        return []
    return ["-fno-wrapv", "-march=native", "-ffp-contract=off"] if tuned() else ["-fno-wrapv"]


def portable_args() -> list[str]:
    """Compiler flags of the markers' cores (markers/_xfit.pyx, _rings.pyx, _centring.pyx, _shadow.pyx) and
    of the CSV float cells (_float_text.pyx, integer arithmetic only): for any CPU of the architecture, as
    a marker job checks no build CPU (pose.build_cpu comes with the pose package) and -march=native made
    them no faster; the same roundings (no contracted multiply-adds)."""
    return [] if sys.platform == "win32" else ["-fno-wrapv", "-ffp-contract=off"]


def record_build_cpu() -> None:
    """Write this CPU's /proc/cpuinfo flags line for `pose.build_cpu` (a tuned build), else remove the record."""
    cpuinfo = Path("/proc/cpuinfo")
    flags = next((line for line in cpuinfo.read_text().splitlines() if line.startswith("flags")), None) \
        if tuned() and cpuinfo.is_file() else None
    if flags:
        BUILD_CPU_RECORD.write_text(flags + "\n")
    else:
        BUILD_CPU_RECORD.unlink(missing_ok=True)


record_build_cpu()


setup(ext_modules=cythonize([
    Extension("dmais_pipe.pose._kernels", ["dmais_pipe/pose/_kernels.pyx"], extra_compile_args=compile_args()),
    Extension("dmais_pipe.pose._refine", ["dmais_pipe/pose/_refine.pyx"], extra_compile_args=compile_args()),
    Extension("dmais_pipe.pose._group", ["dmais_pipe/pose/_group.pyx"], extra_compile_args=compile_args()),
    Extension("dmais_pipe.pose._error", ["dmais_pipe/pose/_error.pyx"], extra_compile_args=compile_args()),
    Extension("dmais_pipe.pose._certificate", ["dmais_pipe/pose/_certificate.pyx"], extra_compile_args=compile_args()),
    Extension("dmais_pipe.markers._xfit", ["dmais_pipe/markers/_xfit.pyx"], extra_compile_args=portable_args()),
    Extension("dmais_pipe.markers._rings", ["dmais_pipe/markers/_rings.pyx"], extra_compile_args=portable_args()),
    Extension("dmais_pipe.markers._centring", ["dmais_pipe/markers/_centring.pyx"], extra_compile_args=portable_args()),
    Extension("dmais_pipe.markers._shadow", ["dmais_pipe/markers/_shadow.pyx"], extra_compile_args=portable_args()),
    Extension("dmais_pipe._float_text", ["dmais_pipe/_float_text.pyx"], extra_compile_args=portable_args()),
]))
