"""dqpose.names: the one rule of a client's names, at its edges, and how errors quote one."""
from __future__ import annotations

import pytest

from dqpose.errors import FieldError
from dqpose.names import MAX_NAME_BYTES, QUOTE_CHARS, check_name, name_problem, quoted


@pytest.mark.parametrize("name", ["box", "a" * MAX_NAME_BYTES, "\u00e9" * (MAX_NAME_BYTES // 2),
                                  "cam 1", "k\u00e4stchen", "\U0001f4e6"])
def test_names_within_the_rule(name):
    assert name_problem(name) is None and check_name(name, "body") == name


@pytest.mark.parametrize("name, problem", [
    ("", "empty"),
    ("a" * (MAX_NAME_BYTES + 1), "129 characters"),
    ("\u00e9" * (MAX_NAME_BYTES // 2 + 1), "130 bytes of UTF-8"),
    ("a" * 10**6, "1000000 characters"),
    ("a/stats", "'/' at 1"),
    ("a\x00b", "U+0000 at 1"),
    ("a\nb", "U+000A"),
    ("a\x7f", "U+007F"),
    ("a\x85", "U+0085"),           # C1: NEXT LINE
    ("\ud800", "not valid UTF-8"),   # a lone surrogate
    (b"box", "expected a string, got bytes"),
    (None, "expected a string, got NoneType"),
])
def test_names_beyond_the_rule_are_refused_naming_the_field(name, problem):
    with pytest.raises(FieldError) as e:
        check_name(name, "measurements[3].body")
    text = str(e.value)
    assert text.startswith("measurements[3].body: ") and problem in text, text
    assert len(text) < 200      # the name quoted cut short


def test_empty_is_allowed_where_it_means_the_world_frame():
    assert name_problem("", empty=True) is None
    assert name_problem("a/b", empty=True) is not None


def test_an_error_quotes_at_most_64_characters():
    assert quoted("box") == "'box'"
    long = quoted("x" * 10**6)
    assert long == repr("x" * QUOTE_CHARS) + "..."
