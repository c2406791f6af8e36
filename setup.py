"""Builds the compiled cores of the pose solver and of its refinement and RANSAC; everything else is configured in pyproject.toml."""

from Cython.Build import cythonize
from setuptools import Extension, setup

setup(ext_modules=cythonize([
    Extension("dmais_pipe.pose._kernels", ["dmais_pipe/pose/_kernels.pyx"]),
    Extension("dmais_pipe.pose._refine", ["dmais_pipe/pose/_refine.pyx"]),
]))
