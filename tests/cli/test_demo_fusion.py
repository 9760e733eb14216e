"""`dqpose demo fusion`: a real UR simulator driven through ur_rtde, two rendered and detected
ChArUco cameras, fused through a real in-process gRPC server."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rtde_control")
pytest.importorskip("matplotlib")

from service.cli import main  # noqa: E402


def test_fused_error_is_below_the_worst_source_and_the_plot_is_written(tmp_path, capsys):
    png = tmp_path / "fusion.png"
    assert main(["demo", "fusion", "--steps", "12", "--plot", str(png)]) == 0
    out = capsys.readouterr().out
    rows = {}
    for line in out.splitlines():
        parts = line.split()
        if parts and parts[0] in ("ur", "camera1", "camera2", "fused"):
            rows[parts[0]] = [float(v) for v in parts[1:]]
    assert set(rows) == {"ur", "camera1", "camera2", "fused"}, out
    # columns: views, rotation median, RMS (deg), translation median, RMS (mm)
    assert rows["fused"][0] == 12
    for col in (2, 4):       # RMS rotation and translation
        worst = max(rows[s][col] for s in ("ur", "camera1", "camera2"))
        best = min(rows[s][col] for s in ("ur", "camera1", "camera2"))
        assert rows["fused"][col] < worst
        assert rows["fused"][col] < 1.5 * best
    assert png.stat().st_size > 10_000
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_run_returns_the_errors_of_every_step():
    from service.cli import demo_fusion
    r = demo_fusion.run(5, progress=False)
    assert r.names == ("ur", "camera1", "camera2", "fused")
    assert r.rotation_deg.shape == r.translation_mm.shape == (5, 4)
    assert np.all(np.isfinite(r.rotation_deg[:, -1]))
    assert np.all(np.diff(r.t) > 0)


def test_bad_steps_is_refused(capsys):
    assert main(["demo", "fusion", "--steps", "0"]) == 2
    assert "--steps must be at least 1" in capsys.readouterr().err


def test_plain_demo_still_blends(capsys):
    assert main(["demo"]) == 0
    assert "Blended with each method" in capsys.readouterr().out
