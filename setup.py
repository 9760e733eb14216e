"""Builds the C core against the NumPy headers and generates the gRPC stubs from proto/
(everything else is in pyproject.toml)."""
import glob
import os
import re

import numpy
from setuptools import Extension, setup

CSRC = os.path.join("service", "csrc")
# -O3 lets GCC vectorise the per-pose loops; no -ffast-math, because the core relies on
# IEEE semantics to detect NaN/Inf input and on exact rounding for 1e-12 agreement.
# -Wno-unused-parameter: every Python function takes CPython's `self` (and METH_O / METH_VARARGS
# fix the signature), which the module functions never use.
extra = ["-O3", "-std=c99", "-Wall", "-Wextra", "-Wno-unused-parameter", "-fno-math-errno"]
if os.environ.get("DQPOSE_NATIVE") == "1":
    extra.append("-march=native")
# CI builds with DQPOSE_WERROR=1 (.ci/run): a warning fails the build there.
if os.environ.get("DQPOSE_WERROR") == "1":
    extra.append("-Werror")

# The pure C99 core, then the CPython/NumPy bindings (py_*.c) and the module's table (module.c).
CORE_SOURCES = ("dq.c", "blend.c", "wire.c", "fused_wire.c", "linalg6.c", "se3.c", "gn.c",
                "fusion.c", "motion.c", "motion_rows.c", "motion_nis.c", "joint.c", "joint_nis.c",
                "traj_law.c", "traj_plan.c", "traj_eval.c", "store.c", "lookup.c", "tick.c")
BINDING_SOURCES = ("py_args.c", "py_dq.c", "py_wire.c", "py_fusion.c", "py_joint.c", "py_se3.c",
                   "py_trajectory.c", "py_store.c", "py_lookup.c", "py_tick.c", "module.c")

core = Extension(
    "dqpose._dqcore",
    sources=[os.path.join(CSRC, f) for f in CORE_SOURCES + BINDING_SOURCES],
    include_dirs=[numpy.get_include(), CSRC],
    define_macros=[("NPY_NO_DEPRECATED_API", "NPY_2_0_API_VERSION")],
    extra_compile_args=extra,
    libraries=["m"],
)

PROTO_ROOT = "proto"
PROTO_OUT = os.path.join("service", "rpc", "_proto")


def generate_stubs() -> None:
    """proto/dqpose/v1/*.proto -> service/rpc/_proto/dqpose/v1/*_pb2*.py (never committed).

    protoc names imports after the proto path (``from dqpose.v1 import ...``); they are rewritten
    to resolve under ``dqpose.rpc._proto`` (the proto package ``dqpose.v1`` is not the import
    package ``dqpose``).
    """
    import grpc_tools
    from grpc_tools import protoc  # a build requirement (pyproject.toml)

    protos = sorted(glob.glob(os.path.join(PROTO_ROOT, "dqpose", "**", "*.proto"), recursive=True))
    wkt = os.path.join(os.path.dirname(grpc_tools.__file__), "_proto")
    os.makedirs(PROTO_OUT, exist_ok=True)
    rc = protoc.main(["grpc_tools.protoc", f"-I{PROTO_ROOT}", f"-I{wkt}",
                      f"--python_out={PROTO_OUT}", f"--pyi_out={PROTO_OUT}",
                      f"--grpc_python_out={PROTO_OUT}", *protos])
    if rc != 0:
        raise SystemExit(f"protoc failed on {protos} (exit {rc})")
    for dirpath, _, files in os.walk(PROTO_OUT):
        init = os.path.join(dirpath, "__init__.py")
        if not os.path.exists(init):
            open(init, "w").close()
        for name in files:
            if name.endswith((".py", ".pyi")) and name != "__init__.py":
                path = os.path.join(dirpath, name)
                with open(path) as f:
                    src = f.read()
                fixed = re.sub(r"^from dqpose\.(v\d+\w*(?:\.\w+)*) import",
                               r"from dqpose.rpc._proto.dqpose.\1 import", src, flags=re.M)
                if fixed != src:
                    with open(path, "w") as f:
                        f.write(fixed)


# Generated whenever setuptools runs this file: metadata, wheel and editable builds all need the
# packages under service/rpc/_proto to exist (pyproject.toml lists them).
generate_stubs()
setup(ext_modules=[core])
