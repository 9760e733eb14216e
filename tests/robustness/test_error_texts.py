"""The two rules every refusal's text passes: it starts with the request's field (what NumPy or
SciPy raised from inside the domain is put under the field it was about) and its numbers are
readable (%.6g, never a 17-digit repr or a 300-digit count)."""
from __future__ import annotations

import numpy as np

from dqpose.errors import FieldError, FieldInfeasible, Infeasible
from dqpose.rpc.calls import readable
from dqpose.rpc.checks import field_named
from dqpose.rpc.handeye_convert import calibrate_error


def test_long_numbers_are_written_with_six_digits_names_and_indices_kept():
    assert readable("waypoints[1].blend_radius: 1e+308 m is more than half a neighbouring "
                    "segment (0.041694716291423795 m)") == (
        "waypoints[1].blend_radius: 1e+308 m is more than half a neighbouring segment "
        "(0.0416947 m)")
    assert readable("rate_hz: " + "5" * 300 + " samples") == "rate_hz: 5.55556e+299 samples"
    assert readable("requests[123456789].x: body 'b12345678901': 2.2250738585072014e-308") == (
        "requests[123456789].x: body 'b12345678901': 2.22507e-308")
    assert readable("time: 0.5 or 1e+300 or nan") == "time: 0.5 or 1e+300 or nan"
    # an interval's bounds are numbers, not indices
    assert readable("outside the span [0.009999999999999998, 0.019] of the measurements") == (
        "outside the span [0.01, 0.019] of the measurements")
    # a whole count stays exact up to 15 digits; one longer is no count a person reads
    assert readable("999999990 ticks, 1234567890123456 rows") == (
        "999999990 ticks, 1.23457e+15 rows")


def test_an_error_from_inside_numpy_is_put_under_a_field():
    try:
        np.linalg.inv(np.zeros((2, 2)))
    except np.linalg.LinAlgError as e:
        named = field_named(e, ("measurements", "options"), "measurements")
    assert isinstance(named, FieldError) and str(named) == "measurements: Singular matrix"
    assert str(calibrate_error(np.linalg.LinAlgError(
        "2-th leading minor not positive definite"))) == (
        "pairs: 2-th leading minor not positive definite")


def test_a_named_error_keeps_its_text_and_its_kind():
    e = field_named(Infeasible("options.window: too short"), ("options",), "measurements")
    assert isinstance(e, FieldInfeasible) and str(e) == "options.window: too short"
    assert str(field_named(ValueError("optionsx: y"), ("options",), "measurements")) == (
        "measurements: optionsx: y")
