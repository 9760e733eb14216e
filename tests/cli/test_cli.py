"""dqpose.cli: the `dqpose` entry point. The top-level help imports no command module (so no
NumPy, C core or grpc), and every command's own parser builds and describes itself."""
from __future__ import annotations

import subprocess
import sys

import pytest

from dqpose.cli import COMMANDS, build_parser

HEAVY = ("numpy", "grpc", "dqpose._dqcore", "dqpose.rpc", "dqpose.drivers")


def _modules_after(argv: list[str]) -> set[str]:
    code = ("import sys\nfrom dqpose.cli import main\n"
            f"try:\n    main({argv!r})\nexcept SystemExit:\n    pass\n"
            "print(' '.join(sorted(sys.modules)))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                         check=True).stdout
    return set(out.split("\n")[-2].split())


def test_top_level_help_imports_nothing_heavy():
    loaded = _modules_after(["--help"])
    assert "dqpose.cli" in loaded
    heavy = sorted(m for m in loaded if m.split(".")[0] in HEAVY or m in HEAVY
                   or any(m.startswith(h + ".") for h in HEAVY))
    assert heavy == []
    # and no command module either: they are imported only for their own command
    assert not {module for module, _ in COMMANDS.values()} & loaded


def test_a_command_imports_only_its_own_module():
    loaded = _modules_after(["health", "--help"])
    assert "dqpose.cli.serve" in loaded
    assert {"dqpose.cli.blend", "dqpose.cli.properties", "dqpose.cli.sim"}.isdisjoint(loaded)


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_command_has_a_description_and_a_function(name):
    parser = build_parser([name])
    sub = next(a for a in parser._actions if a.dest == "command").choices[name]
    assert sub.description and len(sub.description) > 20
    assert callable(sub.get_default("func"))


def test_help_of_every_command_renders():
    parser = build_parser(None)          # every command configured, as documentation needs
    sub = next(a for a in parser._actions if a.dest == "command")
    for name, p in sub.choices.items():
        assert name in p.format_help()


def test_blend_help_explains_every_method():
    from dqpose import dq
    parser = build_parser(["blend"])
    sub = next(a for a in parser._actions if a.dest == "command").choices["blend"]
    text = sub.format_help()
    for name, m in dq.METHODS.items():
        assert f"  {name:8s}{m.description}\n" in text
    method = next(a for a in sub._actions if a.dest == "method")
    assert method.choices == list(dq.METHODS)
