"""drivers/sim/__init__.py: the simulator processes ``dqpose serve --sims`` starts. Their output
goes to the ``dqpose.sim`` logger as it comes; a pipe nobody read would fill (64 KB) and block a
chatty simulator."""
from __future__ import annotations

import json
import logging

from dqpose.drivers.sim import end_process, start_process


def test_a_chatty_simulator_does_not_block_and_its_output_is_logged(caplog):
    caplog.set_level(logging.INFO, logger="dqpose.sim")
    proc = start_process("tests.drivers.sim._chatty", 2_000_000)
    try:
        assert proc.wait(timeout=60) == 0
    finally:
        end_process(proc)
    lines = [json.loads(r.getMessage()) for r in caplog.records if r.name == "dqpose.sim"]
    out = [x for x in lines if x["stream"] == "stdout"]
    err = [x for x in lines if x["stream"] == "stderr"]
    assert len(out) == 20_000 + 1 and len(err) == 2_000
    assert out[-1] == {"event": "sim_output", "sim": "tests.drivers.sim._chatty",
                       "pid": proc.pid, "stream": "stdout", "line": "chatty: done"}
    assert {r.levelno for r in caplog.records if r.name == "dqpose.sim"} == {logging.INFO,
                                                                              logging.WARNING}


def test_a_simulator_that_dies_says_why():
    """Its standard error's last lines, once it has ended (Popen's own ``errors`` attribute is
    the text-mode setting: the method must not share its name)."""
    proc = start_process("tests.drivers.sim._chatty", 1000)
    try:
        assert proc.wait(timeout=60) == 0
    finally:
        end_process(proc)
    tail = proc.stderr_tail()
    assert tail.splitlines() == ["x" * 99] * (1000 // 100 // 10)
