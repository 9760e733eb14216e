"""The build of the batch loops of service/csrc/blend.c: each ISA clone runs code of its own ISA.

`target_clones` compiles a function once per ISA, but a body it calls is compiled for the clone's
ISA only if it is inlined into the clone; GCC kept the ScLERP-pairs block out of line once, built
for the baseline, so the AVX2 clone ran SSE2 code at half speed (same results, so only the
machine code shows it). Skipped where there are no clones (not GCC on x86-64 Linux) or no objdump.
"""
import re
import shutil
import subprocess

import pytest

from dqpose import _dqcore

# The batch loops built as clones; each AVX2 clone must use the 256-bit registers throughout.
CLONED = ("dq_sclerp_pairs", "dq_sclerp_pairs_checked", "log_sum")


def disassembly() -> dict[str, str]:
    objdump = shutil.which("objdump")
    if objdump is None:
        pytest.skip("objdump (binutils) is not installed")
    text = subprocess.run([objdump, "-d", "--no-show-raw-insn", _dqcore.__file__], check=True,
                          capture_output=True, text=True).stdout
    return {m.group(1): m.group(2) for m in re.finditer(r"^[0-9a-f]+ <([^>]+)>:\n(.*?)(?:\n\n|\Z)",
                                                      text, re.S | re.M)}


@pytest.mark.parametrize("name", CLONED)
def test_the_avx2_clone_runs_avx2_code(name):
    funcs = disassembly()
    if f"{name}.avx2" not in funcs:
        pytest.skip(f"{name} has no AVX2 clone in this build")
    avx2, default = funcs[f"{name}.avx2"], funcs[f"{name}.default"]
    # The vector loops are in the clone itself, not in a baseline body both clones call.
    assert len(re.findall(r"%ymm", avx2)) >= 100
    assert "%ymm" not in default
    called = set(re.findall(r"call\s+[0-9a-f]+ <([^>@+]+)", avx2))
    assert not {c for c in called if c.endswith("_block")}, called
