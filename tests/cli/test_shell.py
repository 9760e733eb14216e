"""dqpose.cli.shell: the server's address is --server (--target an alias where no positional is
TARGET), a mistake gets the usage of the (sub)command it was made in and a did-you-mean, and a
reader that closes the pipe (`| head -2`, through a real pipe) ends the command quietly with 141."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from dqpose import dq
from dqpose.cli import build_parser, main
from dqpose.cli.shell import PIPE_CLOSED
from tests.cli._cli import ROOT, server  # noqa: F401  (a fixture)


def _error(capsys, *argv) -> str:
    with pytest.raises(SystemExit) as e:
        main(list(argv))
    assert e.value.code == 2
    return capsys.readouterr().err


def test_a_misspelt_flag_gets_its_subcommands_usage_and_the_nearest_flag(capsys):
    err = _error(capsys, "blend", "--methd", "dib", "poses.csv")
    assert err.startswith("usage: dqpose blend ")
    assert "unrecognized arguments: --methd (did you mean --method?)" in err
    err = _error(capsys, "world", "lookup", "--tme", "3", "tool", "box")
    assert err.startswith("usage: dqpose world lookup ") and "did you mean --time?" in err


def test_a_misspelt_command_action_or_choice_names_the_nearest(capsys):
    err = _error(capsys, "blnd", "poses.csv")
    assert "invalid choice: 'blnd' (did you mean 'blend'?" in err
    err = _error(capsys, "world", "lokup", "tool", "box")
    assert err.startswith("usage: dqpose world ") and "(did you mean 'lookup'?" in err
    err = _error(capsys, "blend", "--method", "dibb", "poses.csv")
    assert "(did you mean 'dib'?" in err
    # nothing near: the choices alone
    err = _error(capsys, "world", "zzz")
    assert "did you mean" not in err and "choose from 'publish', 'watch', 'lookup'" in err


def test_the_server_flag_and_its_old_name_where_no_positional_is_target(capsys):
    args = build_parser(["blend"]).parse_args(["blend", "f.csv", "--target", "h:1"])
    assert args.server == "h:1"
    argv = ["world", "lookup", "--server", "h:2", "tool", "box"]
    args = build_parser(argv).parse_args(argv)
    assert (args.server, args.frame_target, args.frame_source) == ("h:2", "tool", "box")
    # world lookup's first positional is TARGET: --target is no flag there
    err = _error(capsys, "world", "lookup", "--target", "tool", "box")
    assert err.startswith("usage: dqpose world lookup ")
    assert "unrecognized arguments: --target (did you mean --server?)" in err


def _publishing(target: str, until) -> None:
    """Measurements of "box" from "cam", one a request, until ``until()``."""
    from dqpose.rpc.client import Batch, Client

    cov = np.diag([1e-4] * 3 + [1e-6] * 3)[None]

    def batches():
        k = 0
        while not until() and k < 20_000:
            yield Batch(dq.from_pose(np.array([[1.0, 0, 0, 0]]), np.array([[0.1, 0, 0]])), cov,
                        names=["cam"], bodies=["box"], times=np.array([0.01 * k]))
            k += 1
    with Client(target) as c:
        for _ in c.publish(batches(), producer="cam"):
            pass


def test_a_closed_pipe_ends_the_command_quietly_with_141(server):  # noqa: F811
    watch = subprocess.Popen([sys.executable, "-m", "dqpose.cli", "world", "watch", "box",
                              "--server", server.target], cwd=ROOT, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE)
    head = subprocess.Popen(["head", "-2"], stdin=watch.stdout, stdout=subprocess.PIPE)
    watch.stdout.close()        # head alone reads it
    try:
        _publishing(server.target, lambda: watch.poll() is not None)
        shown, _ = head.communicate(timeout=60)
        err = watch.communicate(timeout=60)[1]
    finally:
        watch.kill()
        head.kill()
    assert len(shown.splitlines()) == 2
    assert watch.returncode == PIPE_CLOSED, err
    assert err == b""
