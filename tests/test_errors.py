"""service.errors: the core's argument names replaced by the caller's field paths."""
from service.errors import FieldError, rename


def test_rename_maps_the_core_argument_to_the_field_path():
    e = rename(ValueError("q[3]: zero quaternion"), {"q": "poses{}.orientation"})
    assert isinstance(e, FieldError) and str(e) == "poses[3].orientation: zero quaternion"
    # no index in the core's message: the placeholder disappears
    assert str(rename(ValueError("weights: all weights are zero"), {"weights": "weights{}"})) == \
        "weights: all weights are zero"
    # an unknown name is kept
    assert str(rename(ValueError("x[1]: bad"), {"q": "poses{}"})) == "x[1]: bad"


def test_rename_all_maps_every_argument_the_message_names():
    from service.errors import Infeasible, rename_all
    names = {"a": "pairs{}.first", "b": "pairs{}.second"}
    e = rename_all(Infeasible("a, b[2]: apart; b[2] against a[0]"), names)
    assert str(e) == "pairs.first, pairs[2].second: apart; pairs[2].second against pairs[0].first"
    assert isinstance(e, Infeasible) and isinstance(e, FieldError)
    # whole words only: "ab" is not "a"
    assert str(rename_all(ValueError("ab[1]: x"), names)) == "ab[1]: x"
