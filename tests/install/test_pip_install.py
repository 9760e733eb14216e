"""``pip install .`` from a clone, no extras, into a new virtual environment: the server starts and
answers every service that needs no extra, and what needs one says which, with the command that
installs it from a clone."""
from __future__ import annotations

import os

import pytest

from tests.install._install import (
    LIMITS,
    Venv,
    build_requirements,
    check_bare_server,
    copy_sources,
    hint,
    serving,
)

pytestmark = pytest.mark.install

SMOOTH_CSV = "t,x,y,z,qw,qx,qy,qz\n" + "".join(f"{0.1 * i:g},{0.01 * i:g},0,0.3,1,0,0,0\n"
                                              for i in range(11))
PLAN_CSV = "x,y,z,qw,qx,qy,qz\n0.4,0,0.3,0,1,0,0\n0.5,0,0.3,0,1,0,0\n"
LIMIT_FLAGS = [f"--{k.replace('_', '-')}={v}" for k, v in LIMITS.items()]


@pytest.fixture(scope="module")
def clone(tmp_path_factory):
    """(venv, clone folder): ``pip install .`` run in a copy of the sources."""
    src = copy_sources(str(tmp_path_factory.mktemp("clone")))
    venv = Venv(str(tmp_path_factory.mktemp("venv")))
    venv.run(venv.python, "-m", "pip", "install", "-q", "--upgrade", "pip", *build_requirements())
    venv.run(venv.python, "-m", "pip", "install", "-q", "--no-build-isolation", ".", cwd=src)
    with open(os.path.join(src, "recording.csv"), "w") as f:
        f.write(SMOOTH_CSV)
    with open(os.path.join(src, "path.csv"), "w") as f:
        f.write(PLAN_CSV)
    with open(os.path.join(src, "poses.yaml"), "w") as f:
        f.write("poses:\n  - {position: {x: 0.1}, orientation: {w: 1}}\n")
    return venv, src


def test_the_server_answers_every_service_that_needs_no_extra(clone):
    venv, src = clone
    with serving(venv, "--port", "0", cwd=src) as address:
        health = venv.run("dqpose", "health", "--server", address, cwd=src)
        assert health.stdout.strip() == "SERVING"
        check_bare_server(address, hint("planning", "."))
        # the CLI of this install, through its client: the server's answer, exit 2
        smooth = venv.run("dqpose", "smooth", "recording.csv", "--server", address, *LIMIT_FLAGS,
                          cwd=src, check=False)
        assert smooth.returncode == 2, smooth
        assert smooth.stderr.strip().endswith(hint("planning", ".")), smooth.stderr
        blend = venv.run("dqpose", "blend", "path.csv", "--server", address, cwd=src)
        assert blend.stdout.splitlines()[0] == "x,y,z,qw,qx,qy,qz"


@pytest.mark.parametrize("argv,extra", [
    (["smooth", "recording.csv", "--local", *LIMIT_FLAGS], "planning"),
    (["plan", "path.csv", "--local", "--plot", "plan.png", *LIMIT_FLAGS], "plot"),
    (["serve", "--port", "0", "--sims"], "devices"),
    (["handeye", "solve", ".", "--local"], "devices"),
    (["blend", "poses.yaml", "--local"], "yaml"),
], ids=["smooth", "plan-plot", "serve-sims", "handeye", "yaml"])
def test_a_command_that_needs_an_extra_exits_2_naming_it(clone, argv, extra):
    venv, src = clone
    proc = venv.run("dqpose", *argv, cwd=src, check=False, timeout=120)
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    assert "Traceback" not in proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith(f"dqpose {argv[0]}") and last.endswith(hint(extra, ".")), proc.stderr


def test_only_dqpose_is_installed_at_the_top_level(clone):
    """The wheel's top-level names (its RECORD): the package dqpose, its console script and its
    metadata; nothing called service or drivers that a robotics workspace would collide with."""
    venv, src = clone
    code = ("import importlib.metadata as m, sys\n"
            "files = m.distribution('dqpose').files\n"
            "print('\\n'.join(sorted({f.parts[0] for f in files if f.parts[0] not in ('..',)})))\n")
    tops = venv.run(venv.python, "-c", code, cwd="/").stdout.split()
    assert [t for t in tops if not t.startswith("dqpose-")] == ["dqpose"], tops
    out = venv.run(venv.python, "-c", "import dqpose.drivers, dqpose.rpc.client, dqpose.cli; "
                   "print(dqpose.drivers.__file__)", cwd="/").stdout
    assert "site-packages/dqpose/drivers/__init__.py" in out, out
    for name in ("service", "drivers"):
        gone = venv.run(venv.python, "-c", f"import {name}", cwd="/", check=False)
        assert gone.returncode != 0 and "ModuleNotFoundError" in gone.stderr, (name, gone)
