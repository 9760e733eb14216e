"""The execution benchmark runs (2 s idle, in CI): the executor drives the simulated UR through
ur_rtde to the end, and the table reports what it measured at the simulator (no timing is
asserted here: the figures are the benchmark's, on a quiet machine)."""
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def test_execution_bench_short():
    pytest.importorskip("rtde_control")
    out = subprocess.run([sys.executable, "-m", "tests.bench.bench_executor", "--rows", "idle",
                          "--seconds", "2", "--cancels", "1"],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    row = next(line for line in out.stdout.splitlines() if line.startswith("| idle |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1].startswith("FINISHED")
    assert int(cells[2]) == 1001            # 2 s at 500 Hz: every set-point reached the controller
