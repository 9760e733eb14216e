"""Issue 40's lengths, which `make lint` runs: no source file over ``MAX_FILE`` lines, no Python
function over ``MAX_PY`` lines (tests and benchmarks included), no C function over ``MAX_C``
(signature to closing brace). A file longer is two concepts; a function longer is two steps."""
from __future__ import annotations

import ast
import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parents[1]
MAX_FILE, MAX_PY, MAX_C = 600, 80, 100
SUFFIXES = (".py", ".c", ".h", ".proto")


FOLDERS = ("service", "drivers", "tests", "proto", "examples")
# what is made, not written: generated stubs, build trees, the benchmarks' virtual environments
MADE = {"_proto", "_build", "build", ".venv", "__pycache__", "node_modules"}


def tracked(root: pathlib.Path = ROOT) -> list[pathlib.Path]:
    """The project's sources (no git needed: a CI checkout may be a plain copy)."""
    return [p for folder in FOLDERS for p in sorted((root / folder).rglob("*"))
            if p.suffix in SUFFIXES and p.is_file()
            and not MADE.intersection(p.relative_to(root).parts)]


def long_files(paths) -> list[str]:
    return [f"{p.name}: {n} lines" for p in paths
            if (n := len(p.read_text(errors="replace").splitlines())) > MAX_FILE]


def long_python(path: pathlib.Path) -> list[str]:
    tree = ast.parse(path.read_text())
    return [f"{path.name}:{f.lineno} {f.name}: {f.end_lineno - f.lineno + 1} lines"
            for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
            and f.end_lineno - f.lineno + 1 > MAX_PY]


# a C function's definition starts at column 0 with its type and name and opens its body at a
# "{" alone on a line; it ends at the first "}" at column 0
_C_START = re.compile(r"^[A-Za-z_][\w \*]*\b(\w+)\(")


def long_c(path: pathlib.Path) -> list[str]:
    out, start, name, body = [], None, "", False
    for k, line in enumerate(path.read_text().splitlines(), 1):
        m = _C_START.match(line)
        if start is None:
            if m and not line.rstrip().endswith(";"):
                start, name, body = k, m[1], False
        elif not body and line.rstrip().endswith(";"):
            start = None                # a prototype over several lines, not a definition
        elif line.startswith("{"):
            body = True
        elif line.startswith("}"):
            if k - start + 1 > MAX_C:
                out.append(f"{path.name}:{start} {name}: {k - start + 1} lines")
            start = None
    return out


def long_functions(paths) -> list[str]:
    out = []
    for p in paths:
        if p.suffix == ".py":
            out += long_python(p)
        elif p.suffix == ".c":
            out += long_c(p)
    return out


def test_no_file_is_two_concepts():
    assert long_files(tracked()) == []


def test_no_function_is_two_steps():
    assert long_functions(tracked()) == []


def test_the_checks_find_what_they_look_for(tmp_path):
    py = tmp_path / "a.py"
    py.write_text("def f():\n" + "    x = 1\n" * MAX_PY + "\n\ndef g():\n    pass\n")
    c = tmp_path / "a.c"
    c.write_text("int g(int a,\n      int b);\n\nstatic int f(int a)\n{\n"
                 + "    a++;\n" * (MAX_C - 2) + "}\n\nint h(void)\n{\n    return 0;\n}\n")
    long = tmp_path / "b.h"
    long.write_text("x\n" * (MAX_FILE + 1))
    assert [s.split()[1] for s in long_functions([py, c])] == ["f:", "f:"]
    assert long_files([py, c, long]) == [f"b.h: {MAX_FILE + 1} lines"]
