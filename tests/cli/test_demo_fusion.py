"""`dqpose demo fusion`: a real UR simulator driven through ur_rtde, two rendered and detected
ChArUco cameras, fused through a real in-process gRPC server."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rtde_control")
pytest.importorskip("matplotlib")

from service.cli import main  # noqa: E402


def test_fused_error_is_below_every_source_alone_and_the_plot_is_written(tmp_path, capsys):
    png = tmp_path / "fusion.png"
    assert main(["demo", "fusion", "--steps", "30", "--plot", str(png)]) == 0
    out = capsys.readouterr().out
    rows = {}
    for line in out.splitlines():
        parts = line.split()
        if parts and parts[0] in ("ur", "camera1", "camera2", "fused"):
            rows[parts[0]] = [float(v) for v in parts[1:]]
    assert set(rows) == {"ur", "camera1", "camera2", "fused"}, out
    # columns: answers, rotation median, RMS (deg), translation median, RMS (mm), all at the
    # instants of the fused answers (3 s of measurements' time at 10 Hz)
    assert rows["fused"][0] >= 15
    # Rotation RMS below every source's; translation below the arm's. The live demo runs on
    # wall-clock threads, so the medians are not asserted against the best camera: in a loaded
    # CI run the fused rotation median lost to it by 2 % (0.0776 vs 0.0758 deg, RMS 0.097 vs
    # 0.113), and in 20 steps the translation did in about a third of runs (answers at the
    # simulator's read stalls, the per-window latency estimate: open on issue 9).
    # bench_fusion's moving scene is the deterministic check of that claim.
    best = min(rows[s][2] for s in ("ur", "camera1", "camera2"))
    assert rows["fused"][2] < best, out
    assert rows["fused"][1] < rows["ur"][1], out
    for col in (3, 4):
        assert rows["fused"][col] < rows["ur"][col], out
    assert "latency of camera1 as the server estimated it" in out
    assert png.stat().st_size > 10_000
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_run_returns_the_errors_at_every_answer():
    from service.cli import demo_fusion
    r = demo_fusion.run(5)
    assert r.names == ("ur", "camera1", "camera2", "fused")
    fused = r.series["fused"]
    assert len(fused.t) >= 2
    assert np.all(np.isfinite(fused.rotation_deg)) and np.all(np.isfinite(fused.translation_mm))
    assert np.all(np.diff(fused.t) > 0)
    for n in r.names[:-1]:       # every source measured; the arm five times a step
        assert len(r.accuracy[n]) + r.rejected.get(n, 0) == (25 if n == "ur" else 5)
    assert set(r.latencies) == {"camera1", "camera2"}


def test_bad_steps_is_refused(capsys):
    assert main(["demo", "fusion", "--steps", "0"]) == 2
    assert "--steps must be at least 1" in capsys.readouterr().err


def test_plain_demo_still_blends(capsys):
    assert main(["demo"]) == 0
    assert "Blended with each method" in capsys.readouterr().out
