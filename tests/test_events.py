"""dqpose.events: event lines said by many threads at once each come out whole (a view
follows a server's world and its arms on threads of their own)."""
from __future__ import annotations

import json
import subprocess
import sys

from tests.cli._cli import ROOT

SAYERS = """
import sys, threading
from dqpose.events import say_err as say
def run(k):
    for i in range(2000):
        say(event="drawn", body=f"body{k}", i=i, pad="x" * (k * 37 % 200))
threads = [threading.Thread(target=run, args=(k,)) for k in range(8)]
for t in threads: t.start()
for t in threads: t.join()
"""


def test_lines_said_by_many_threads_at_once_are_each_whole_json():
    err = subprocess.run([sys.executable, "-c", SAYERS], cwd=ROOT, capture_output=True,
                         text=True, timeout=120, check=True).stderr
    events = [json.loads(line) for line in err.splitlines()]
    assert len(events) == 8 * 2000
    assert {(e["body"], e["i"]) for e in events} == {(f"body{k}", i) for k in range(8)
                                                     for i in range(2000)}
