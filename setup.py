"""Builds the compiled core of the pose solver; everything else is configured in pyproject.toml."""

from Cython.Build import cythonize
from setuptools import Extension, setup

setup(ext_modules=cythonize([Extension("dmais_pipe.pose._kernels", ["dmais_pipe/pose/_kernels.pyx"])]))
