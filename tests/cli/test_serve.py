"""``dqpose serve``'s options: a value out of range is one line naming the flag and the allowed
range, exit code 2, and no server (the ranges themselves live in ``ServerConfig``)."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


@pytest.mark.parametrize("flags, message", [
    (["--port", "116686"], "--port: must be within 0..65535, got 116686"),
    (["--port", "-1"], "--port: must be within 0..65535, got -1"),
    (["--metrics-port", "70000"], "--metrics-port: must be within 1..65535, got 70000"),
    (["--max-message-bytes", "-1"], "--max-message-bytes: must be within 1..2147483647, got -1"),
    (["--max-poses", "0"], "--max-poses: must be within 1..2147483647, got 0"),
    (["--max-poses", "-5"], "--max-poses: must be within 1..2147483647, got -5"),
    (["--grace", "-1"], "--grace: must be a finite number of seconds >= 0, got -1"),
    (["--drain", "nan"], "--drain: must be a finite number of seconds >= 0, got nan"),
    (["--keepalive", "0"], "--keepalive: must be within 0.001..2147483 seconds, got 0"),
])
def test_an_option_out_of_range_is_one_line_naming_the_flag_and_exit_2(flags, message):
    res = subprocess.run([sys.executable, "-m", "service.cli", "serve", *flags],
                         capture_output=True, text=True, timeout=30, cwd=ROOT)
    assert (res.returncode, res.stderr) == (2, f"dqpose serve: error: {message}\n")
    assert res.stdout == ""
