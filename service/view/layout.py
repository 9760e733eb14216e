"""Where the viewer puts its camera, its grid and the arms whose base it does not know, and how
large it draws ellipsoids, from what it draws (NumPy only, no page).

The camera fits the content: it looks at the content from above one side (the side that shows
the content's longer horizontal dimension across the view), centred on the content as the view
shows it, and stands as close as lets every point lie within :data:`FILL` of the view's half
height and half width. Content smaller than :data:`MIN_EXTENT` (one pose) is framed as a box
that large. The grid's
cells and the frames' axes follow the box's size, so millimetres and metres both read; the grid
lies under the content."""
from __future__ import annotations

import dataclasses
import math

import numpy as np

#: the camera's vertical field of view (rad); three.js's default of 75 degrees distorts a
#: close-up's corners
FOV = math.radians(50.0)
#: the share of the view's half height (and half width) the content's farthest point reaches
FILL = 0.85
#: the view's width over its height the fit counts on: a 1280x800 window less the controls
#: docked beside the view (955x800); a wider window shows more around the content
ASPECT = 1.2
#: the camera's height above the content's centre, as an angle from the horizontal (rad)
ELEVATION = math.radians(35.0)
#: content smaller than this (m) is framed as a box this large (one pose has no extent)
MIN_EXTENT = 0.05
#: a frame's axes, as a share of the content's size (m of axes per m of content)
AXES_SHARE = 0.12
#: the ellipsoid scales the page offers
SCALES = (1, 10, 100)
#: the share of the content's size the largest ellipsoid's half axis reaches at the scale
#: chosen for it: 1 % is a few pixels on a laptop's screen
VISIBLE = 0.02
#: seconds of each body's past positions drawn behind it
TRAIL_SECONDS = 2.0


@dataclasses.dataclass
class View:
    """A camera ``position`` looking at ``look_at``, its clipping planes, the size of what it
    frames (``extent``, m: the largest side of the content's box) and the height of the grid
    under it (``floor``, m: the world's z = 0 when the content reaches it, else the content's
    lowest z, so that the grid is in view)."""
    position: np.ndarray
    look_at: np.ndarray
    near: float
    far: float
    extent: float
    floor: float = 0.0

    @property
    def axes(self) -> float:
        """The length of a frame's axes (m) at this size of content."""
        return AXES_SHARE * self.extent


def box(points, pad=0.0) -> tuple[np.ndarray, np.ndarray]:
    """The axis-aligned box ``(lo, hi)`` of ``points (n, 3)`` (finite ones only; none: the
    origin), each point a sphere of radius ``pad`` (one for all, or ``(n,)``), widened to
    :data:`MIN_EXTENT` at the least."""
    p, r = _finite(points, pad)
    if not len(p):
        p, r = np.zeros((1, 3)), np.zeros(1)
    lo, hi = np.min(p - r[:, None], axis=0), np.max(p + r[:, None], axis=0)
    if np.max(hi - lo) < MIN_EXTENT:
        centre = (lo + hi) / 2
        lo, hi = centre - MIN_EXTENT / 2, centre + MIN_EXTENT / 2
    return lo, hi


def _finite(points, pad) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    r = np.broadcast_to(np.asarray(pad, dtype=np.float64), (len(p),))
    keep = np.all(np.isfinite(p), axis=1) & np.isfinite(r)
    return p[keep], r[keep]


def camera(points, pad=0.0, fov: float = FOV) -> View:
    """The :class:`View` framing ``points (n, 3)``, each a sphere of radius ``pad`` (one for
    all, or ``(n,)``) (module docstring)."""
    lo, hi = box(points, pad)
    p, pad = _finite(points, pad)
    if not len(p) or np.max(hi - lo) <= MIN_EXTENT:
        p, pad = box_corners(lo, hi), np.zeros(8)   # one pose: framed as a box
    size = hi - lo
    # from the side that faces the longer horizontal dimension, turned 30 degrees off it
    azimuth = math.radians(-60.0 if size[0] >= size[1] else -30.0)
    back = np.array([math.cos(ELEVATION) * math.cos(azimuth),
                     math.cos(ELEVATION) * math.sin(azimuth), math.sin(ELEVATION)])
    forward = -back
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    # centred on the points as the view shows them (across and up), in depth on the box's
    x, y = p @ right, p @ up
    centre = (((x - pad).min() + (x + pad).max()) / 2 * right
              + ((y - pad).min() + (y + pad).max()) / 2 * up
              + ((lo + hi) / 2 @ forward) * forward)
    v = p - centre
    # each point's sphere within the view's planes, tilted a half angle t from forward (t
    # across: tan t = tan(fov / 2) FILL ASPECT; up: without ASPECT): the sphere's centre, at
    # depth (distance + v.forward) and |v.right| across, lies pad or more inside the plane,
    # depth sin t - |v.right| cos t >= pad
    tan_up = math.tan(fov / 2) * FILL
    need = np.maximum.reduce([np.abs(v @ axis) / tan + pad / math.sin(math.atan(tan))
                              for axis, tan in ((right, tan_up * ASPECT), (up, tan_up))]) \
        - v @ forward
    distance = float(max(np.max(need), 1e-3))
    floor = 0.0 if lo[2] <= 0.0 <= hi[2] else float(lo[2])
    return View(centre + distance * back, centre, distance / 100, distance * 100,
                float(np.max(size)), floor)


def box_corners(lo, hi) -> np.ndarray:
    """The 8 corners of the box ``lo``, ``hi``."""
    return np.array([[a[0], b[1], c[2]] for a in (lo, hi) for b in (lo, hi) for c in (lo, hi)])


def grid_step(extent: float) -> float:
    """A grid cell (m): 1, 2 or 5 times a power of ten, about a tenth of ``extent``."""
    raw = max(extent, MIN_EXTENT) / 10
    power = 10.0 ** math.floor(math.log10(raw))
    return max(m * power for m in (1.0, 2.0, 5.0) if m * power <= raw * 1.0000001)


def ellipsoid_scale(largest_half_axis: float | None, extent: float) -> int:
    """The smallest of :data:`SCALES` at which an ellipsoid of ``largest_half_axis`` (m)
    reaches :data:`VISIBLE` of ``extent`` (the largest when none does; 1 without ellipsoids)."""
    if not largest_half_axis or not math.isfinite(largest_half_axis):
        return SCALES[0]
    for s in SCALES:
        if s * largest_half_axis >= VISIBLE * extent:
            return s
    return SCALES[-1]


def aside(k: int, spacing: float) -> np.ndarray:
    """Where the ``k``-th arm whose base is not known is drawn: ``spacing`` (m) apart along
    -y, so that two arms' paths, each in its own base frame, do not overlap."""
    return np.array([0.0, -spacing * k, 0.0])


def recent(times, at: float, seconds: float = TRAIL_SECONDS) -> int:
    """The index of the first of ``times`` (s, ascending) within ``seconds`` before ``at``."""
    return int(np.searchsorted(np.asarray(times, dtype=np.float64), at - seconds, side="left"))
