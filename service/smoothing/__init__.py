"""Smoothing of noisy recorded pose paths under the tool's velocity and acceleration limits.

``smooth(times, poses, limits, smoothing, rate_hz, free_ends)`` takes a recorded path
(teleoperation, demonstrations: poses ``T_base_tool`` at their time stamps, with noise) and returns
a smooth path on the same clock that a controller can execute: it starts and ends at rest (unless
``free_ends``: a piece of a longer motion, whose ends keep the data's motion), and the tool point's
linear velocity and acceleration and the tool's angular velocity and acceleration stay within
``limits`` as norms (jerk too where a jerk limit is given), measured from the returned samples.

The model
---------
The path is a cubic B-spline with uniform knots over ``[times[0], times[-1]]``, as many spans as
input intervals (N poses, N + 2 control points; the stamps need not be uniform) or, when smoothing,
spans of at most ``tau / 3`` (below: 19 spans per period of the cutoff, where a cubic spline
follows the smoothed path to ~2e-4 of its amplitude; at 100 Hz and ``smoothing = 1`` a knot every
2.6 samples, 0.38 of the unknowns of the QPs below): the tool point's
position is a B-spline in R^3 and the orientation a cumulative B-spline on SO(3)
(``R(t) = Rc_i Exp(B1 d_i+1) Exp(B2 d_i+2) Exp(B3 d_i+3)`` with the body increments
``d_j = Log(Rc_j-1^-1 Rc_j)``). Its first three and last three control points coincide, which
is rest (zero velocity and acceleration) at both ends; with ``free_ends`` every control point is
free and the ends follow the data. The cost is

    sum_k w_k |e_k|^2 + tau^6 * integral |jerk|^2 dt

separately for the position (``e_k`` in metres) and the orientation (``e_k = Log(R_k^-1 R(t_k))``
in radians, the angular jerk that of the increments), ``w_k`` the time each sample covers. Without
limits this is a zero-phase low-pass filter with gain ``1 / (1 + (f / f_c)^6)`` (a smoothing
spline of order 3; the MAP estimate for white jerk of spectral density ``q`` and white noise of
variance ``s^2`` at spacing ``dt`` when ``tau^6 = s^2 dt / q``).

``smoothing`` is ``tau`` in units of ``1 / (2 pi CUTOFF_HZ)``: ``smoothing = 1`` keeps motion
slower than ``f_c = 2 Hz`` (human teleoperation is mostly below) and removes faster motion,
``smoothing = s`` moves the cutoff to ``2 / s`` Hz, and ``0`` keeps the samples as closely as
the limits allow (no jerk term). ``f_c`` is where the gain is 1/2.

Limits are kept on the spline's control points: velocity, acceleration and jerk of a uniform
B-spline are B-splines of the control-point differences, so a bound on the norm of each
difference bounds the norm everywhere between samples (convex hull) and every finite difference
of samples taken at any rate (a finite difference is a positive, unit-mass average of the
derivative). For the position this is exact; for the orientation it holds to first order in the
rotation per span (the neglected terms are at most ``|w| dt`` of the limit, ~1 % at 1 rad/s and
100 Hz, and vanish while the rotation axis turns slowly), and an angular jerk limit bounds the
increments' (body-frame) jerk while the samples' base-frame jerk differs from it by ``w x alpha``.
So the returned samples are measured (:func:`peaks`) and a limit they break is tightened and
solved again.

The solver
----------
1. One banded solve (a Cholesky factor of bandwidth 3 shared by every step below): the
   unconstrained position; a chordal smoothing of the sign-aligned quaternions as the reference
   orientation; one Gauss-Newton step of the orientation cost about it.
2. If the result obeys the limits, that is the answer. Otherwise one QP per offending channel,
   linearised about the unconstrained solution (not the noisy samples), solved by PIQP through
   ``casadi.conic``. The norm limits are written as an inner polyhedral approximation of the
   ball: per control-point difference a box aligned with the reference direction ``u`` and
   inscribed in the ball (``|u.Q| <= a L``, ``|e_i.Q| <= b L``, ``a^2 + 2 b^2 = 1``), with ``a``
   halfway between the reference's share of the limit and 1 (at most 0.995: where a limit binds,
   0.5 % of it is lost along the motion and the sideways freedom is ``b L``, 7 % of it). Three
   rows per limited quantity and control point, the same count as a per-axis box, and only where
   the reference exceeds 60 % of the limit; rows that the solution then breaks are added and the
   QP solved again. The orientation's rows are held back by 0.5 % for the linearisation error of
   the increments; it is relinearised and solved again only if the exact increments still break
   a limit. The exact second-order cone (``|Q| <= L``) needs a conic solver: of casadi's bundled
   plugins only SuperSCS (first order, like OSQP) takes cones (not tried); IPOPT on the exact
   nonlinear problem takes seconds (tests/bench/bench_smoothing.py).
3. The returned samples are measured (:func:`peaks`); a limit they break (the orientation's
   first-order terms, or a base-frame angular jerk) is tightened by the ratio and solved again.

With rest at the ends, the first and last control points of the QP are pinned where the
unconstrained solution puts them, so a path whose ends are too far apart for its duration under the
limits is reported (:class:`Infeasible`) instead of being cut short silently. With ``free_ends``
nothing is pinned: the ends move as far from the data as the limits need.

The parts: :mod:`~dqpose.smoothing.spline` (the B-splines, the banded problem both channels
share, one channel as a linear model), :mod:`~dqpose.smoothing.qp` (the limits on the control
points and the QP), :mod:`~dqpose.smoothing.solve` (the checks, the banded start and the loop
that measures the samples).
"""
from dqpose.errors import Infeasible
from dqpose.smoothing.solve import CUTOFF_HZ, smooth
from dqpose.smoothing.spline import MIN_POSES  # noqa: F401
from dqpose.trajectory import Limits, Peaks, peaks  # noqa: F401 (Limits: smooth's argument)

__all__ = ["CUTOFF_HZ", "Infeasible", "Peaks", "peaks", "smooth"]
