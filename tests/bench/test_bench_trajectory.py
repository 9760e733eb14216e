"""The planning benchmark runs (its quick mode, in CI) and its table says what the issue claims
of ours: no limit broken on any path, straight moves as fast as Ruckig's; and the peers' rows
are there, measured in the same run."""
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_planning_bench_quick():
    out = subprocess.run([sys.executable, "-m", "tests.bench.bench_trajectory", "--quick"],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    rows = [[c.strip() for c in line.strip("|").split("|")]
            for line in out.stdout.splitlines() if line.startswith("| ") and " ms |" in line]
    ours = [r for r in rows if r[1].startswith("ours")]
    peers = {r[1] for r in rows} - {r[1] for r in ours}
    assert len(ours) >= 6
    assert {"Ruckig, norm-scaled axes", "TOPP-RA (no jerk)"} <= peers
    for r in ours:
        assert r[4] == "0" and r[5] == "0", r          # worst v/a and jerk violations
    for r in rows:
        if r[1] == "Ruckig, norm-scaled axes":
            mine = next(o for o in ours if o[0] == r[0])
            assert float(mine[2]) <= 1.05 * float(r[2]), (mine, r)
