"""Where the viewer's camera goes, its grid's cells, the ellipsoids' scale, arms placed aside and
the trails' span (dqpose.view.layout), computed without a page: every point framed lies within
the view when projected through the camera the way three.js projects it."""
from __future__ import annotations

import math

import numpy as np
import pytest

from dqpose.view import layout


def project(view: layout.View, p) -> np.ndarray:
    """``p (n, 3)`` on the view as fractions of its half width and half height (within -1..1:
    in the view), with the camera's vertical field of view and the aspect the fit counts on."""
    back = view.position - view.look_at
    forward = -back / np.linalg.norm(back)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    d = np.asarray(p, dtype=float) - view.position
    depth = d @ forward
    tan = math.tan(layout.FOV / 2)
    return np.stack([d @ right / depth / (tan * layout.ASPECT), d @ up / depth / tan], axis=1)


@pytest.mark.parametrize("scale", [0.05, 1.0, 50.0])
@pytest.mark.parametrize("spread", [(1.0, 0.1, 0.0), (0.1, 1.0, 0.3), (1.0, 1.0, 1.0)])
def test_the_camera_frames_the_points_at_every_size(scale, spread):
    rng = np.random.default_rng(0)
    points = np.array([3.0, -2.0, 0.5]) * scale + rng.uniform(-1, 1, (200, 3)) * spread * scale
    view = layout.camera(points)
    xy = np.abs(project(view, points))
    # within the view, and filling it: the farthest point near FILL across or up
    assert np.all(xy <= layout.FILL + 1e-9)
    assert np.max(xy) == pytest.approx(layout.FILL, rel=1e-6)
    assert view.near < np.min(np.linalg.norm(points - view.position, axis=1)) < view.far


def test_a_point_and_its_padding_are_framed_as_a_box_of_the_least_extent():
    view = layout.camera([[1.0, 2.0, 3.0]])
    assert view.extent == pytest.approx(layout.MIN_EXTENT)
    np.testing.assert_allclose(view.look_at, [1.0, 2.0, 3.0], atol=1e-9)
    # a sphere's padding keeps the sphere in view
    pad = 0.2
    view = layout.camera([[0.0, 0, 0], [1.0, 0, 0]], pad)
    rim = np.array([[0.0, 0, pad], [0.0, 0, -pad], [1.0, 0, pad], [1.0 + pad, 0, 0]])
    assert np.all(np.abs(project(view, rim)) <= layout.FILL + 1e-9)


def test_grid_cells_read_at_every_size():
    assert layout.grid_step(1.0) == pytest.approx(0.1)
    assert layout.grid_step(0.3) == pytest.approx(0.02)
    assert layout.grid_step(7.0) == pytest.approx(0.5)
    assert layout.grid_step(0.0) == pytest.approx(layout.MIN_EXTENT / 10)


def test_the_ellipsoids_scale_is_the_smallest_that_shows_them():
    extent = 1.0
    assert layout.ellipsoid_scale(None, extent) == 1
    assert layout.ellipsoid_scale(0.05, extent) == 1
    assert layout.ellipsoid_scale(1e-3, extent) == 100      # 1 mm: x10 is 1 cm, < 2 cm
    assert layout.ellipsoid_scale(3e-3, extent) == 10
    assert layout.ellipsoid_scale(1e-6, extent) == 100      # the largest when none shows it


def test_arms_aside_and_a_trail_of_the_last_seconds():
    assert np.ptp([layout.aside(k, 0.8)[1] for k in range(3)]) == pytest.approx(1.6)
    times = np.arange(50) * 0.1
    assert layout.recent(times, 4.9) == 29                   # 2.9 s .. 4.9 s
    assert layout.recent(times, 1.0) == 0


def test_the_grid_lies_under_the_content():
    assert layout.camera([[0.0, 0, 0], [1.0, 0, 0.5]]).floor == 0.0        # it reaches z = 0
    assert layout.camera([[0.0, 0, 0.4], [0.1, 0, 0.5]]).floor == pytest.approx(0.4)
    assert layout.camera([[0.0, 0, -0.5], [0.1, 0, -0.4]]).floor == pytest.approx(-0.5)
