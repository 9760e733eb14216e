"""Builds the C core against the NumPy headers (everything else is in pyproject.toml)."""
import os

import numpy
from setuptools import Extension, setup

CSRC = os.path.join("service", "csrc")
# -O3 lets GCC vectorise the per-pose loops; no -ffast-math, because the core relies on
# IEEE semantics to detect NaN/Inf input and on exact rounding for 1e-12 agreement.
extra = ["-O3", "-std=c99", "-Wall", "-Wextra", "-Wno-unused-parameter", "-fno-math-errno"]
if os.environ.get("DQPOSE_NATIVE") == "1":
    extra.append("-march=native")

core = Extension(
    "service._dqcore",
    sources=[os.path.join(CSRC, f) for f in ("dq.c", "blend.c", "module.c")],
    include_dirs=[numpy.get_include(), CSRC],
    define_macros=[("NPY_NO_DEPRECATED_API", "NPY_2_0_API_VERSION")],
    extra_compile_args=extra,
    libraries=["m"],
)

setup(ext_modules=[core])
