"""``run``: the ``dqpose`` entry point in this process, its output captured."""
from __future__ import annotations

from service.cli import main


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err
