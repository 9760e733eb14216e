"""service/limits.py, the one table of the server's limits: every limit has its unit, meaning
and flag; ServerConfig refuses values it cannot run with, naming the limit; the flags parse back
into the same table."""
from __future__ import annotations

import argparse
import dataclasses

import pytest

from dqpose import limits
from dqpose.rpc.server import ConfigError, ServerConfig


def test_every_limit_has_a_unit_a_meaning_and_its_own_flag():
    fields = dataclasses.fields(limits.Limits)
    assert len({limits.flag(f.name) for f in fields}) == len(fields)
    for f in fields:
        assert f.metadata["unit"] and f.metadata["meaning"], f.name
        assert f.default >= f.metadata["lo"], f.name


def test_the_flags_parse_into_the_table():
    p = argparse.ArgumentParser()
    limits.add_flags(p)
    assert limits.from_args(p.parse_args([])) == limits.DEFAULT
    got = limits.from_args(p.parse_args(["--max-robust", "50", "--max-output-rate", "20.5"]))
    assert (got.max_robust, got.max_output_rate) == (50, 20.5)


@pytest.mark.parametrize("name, value, problem", [
    ("max_robust", 0, "must be finite and >= 1"),
    ("max_window", 2.5, "must be an integer"),
    ("max_output_rate", float("inf"), "must be finite"),
    ("max_time", 1e300, "max_time * max_output_rate must stay below 2^50"),
])
def test_a_limit_the_server_cannot_run_with_is_refused_naming_it(name, value, problem):
    with pytest.raises(ConfigError) as e:
        ServerConfig(limits=_unchecked(**{name: value}))
    assert e.value.setting == name and problem in e.value.problem, str(e.value)


def _unchecked(**values) -> limits.Limits:
    """A Limits with these values, its own check skipped (as if changed after it was made)."""
    out = dataclasses.replace(limits.DEFAULT)
    for k, v in values.items():
        object.__setattr__(out, k, v)
    return out
