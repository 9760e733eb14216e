"""The installed layout's two rules a linter cannot check: no private name (``_x``) imported from
another ``dqpose`` module, and no import cycle between ``dqpose`` modules.

Read over ``ast`` from the sources (``service/`` is ``dqpose``, ``drivers/`` is ``dqpose.drivers``),
nothing imported. Exempt: the generated stubs (``dqpose.rpc._proto``), the C extension
(``dqpose._dqcore``), third-party modules, and the tests themselves.

And DEVELOPERS.md kept a map: no line over ``MAX_LINE`` characters, every source file named."""
from __future__ import annotations

import ast
import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parents[1]
FOLDERS = {"service": ("dqpose",), "drivers": ("dqpose", "drivers")}
EXEMPT = {"_dqcore", "_proto"}
MAX_LINE = 200


def sources(root: pathlib.Path = ROOT) -> dict[str, pathlib.Path]:
    """Each installed module's dotted name and its file."""
    out = {}
    for folder, head in FOLDERS.items():
        for path in sorted((root / folder).rglob("*.py")):
            parts = path.relative_to(root / folder).with_suffix("").parts
            if "_proto" in parts:
                continue
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(head + parts)] = path
    return out


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__") and name not in EXEMPT


def private_imports(tree: ast.Module, modules=frozenset()) -> list[tuple[int, str, str]]:
    """``(line, module, name)`` of each ``from dqpose... import _name`` (lazy imports included)
    and each ``m._name`` read where ``m`` is one of ``modules`` imported (``from a import m``,
    ``import a.m as m``)."""
    found, alias = [], {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            alias.update({a.asname: a.name for a in node.names if a.asname and a.name in modules})
        if not isinstance(node, ast.ImportFrom) or node.level or not node.module:
            continue
        alias.update({a.asname or a.name: f"{node.module}.{a.name}" for a in node.names
                      if f"{node.module}.{a.name}" in modules})
        if node.module.split(".")[0] != "dqpose" or EXEMPT & set(node.module.split(".")):
            continue
        found += [(node.lineno, node.module, a.name) for a in node.names if _private(a.name)]
    found += [(node.lineno, alias[node.value.id], node.attr) for node in ast.walk(tree)
              if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
              and node.value.id in alias and _private(node.attr)]
    return found


def _imports(body: list[ast.stmt], lazy: bool = False):
    """The import statements run when the module is imported (not under ``if TYPE_CHECKING``;
    with ``lazy``, those in its functions too)."""
    for node in body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        elif isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            yield from _imports(node.orelse, lazy)
        elif lazy or not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for field in ("body", "orelse", "finalbody", "handlers"):
                sub = getattr(node, field, None)
                if isinstance(sub, list):
                    yield from _imports(sub, lazy)


def import_graph(modules: dict[str, pathlib.Path], lazy: bool = False) -> dict[str, set[str]]:
    """Module -> the ``dqpose`` modules it imports when imported (``from a import b``: ``a.b`` when
    that is a module, else ``a``); with ``lazy``, or when one of its functions runs."""
    graph = {}
    for name, path in modules.items():
        out = set()
        for node in _imports(ast.parse(path.read_text()).body, lazy):
            if isinstance(node, ast.Import):
                out |= {a.name for a in node.names}
            elif node.module and not node.level:
                out |= {f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in modules
                        else node.module for a in node.names}
        graph[name] = {m for m in out if m in modules and m != name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        while work:
            v, edges = work[-1]
            w = next(edges, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = stack[stack.index(v):]
                del stack[stack.index(v):]
                if len(comp) > 1:
                    found.append(sorted(comp))
    return found


def _private_imports_by_file(modules) -> dict[str, list[str]]:
    out = {}
    for path in modules.values():
        rel = path.relative_to(ROOT).as_posix()
        hits = [f"{line}: {mod}.{name}"
                for line, mod, name in private_imports(ast.parse(path.read_text()), set(modules))]
        if hits:
            out[rel] = hits
    return out


def test_no_private_name_of_another_module_is_used():
    found = _private_imports_by_file(sources())
    assert not found, "give these a public name where they are defined:\n" + "\n".join(
        f"{f}:{h}" for f, hits in sorted(found.items()) for h in hits)


def test_no_import_cycle_between_modules():
    graph = import_graph(sources())
    assert sum(map(len, graph.values())) > 100       # the walk sees the layout's arrows
    assert not cycles(graph)


def test_no_import_cycle_through_imports_in_functions():
    assert not cycles(import_graph(sources(), lazy=True))


def test_the_checks_find_what_they_look_for(tmp_path):
    (tmp_path / "service" / "pkg").mkdir(parents=True)
    (tmp_path / "drivers").mkdir()
    (tmp_path / "service" / "pkg" / "__init__.py").write_text("")
    (tmp_path / "service" / "pkg" / "a.py").write_text(
        "from dqpose.pkg.b import _hidden, public\nfrom dqpose import _dqcore\n"
        "from dqpose.pkg import b\nb.public, b._inner, _dqcore._c, public._x\n")
    (tmp_path / "service" / "pkg" / "b.py").write_text(
        "import typing\nif typing.TYPE_CHECKING:\n    from dqpose.drivers import x\n"
        "def f():\n    from dqpose.pkg import a\n")
    (tmp_path / "drivers" / "x.py").write_text("from dqpose.pkg import b\n")
    (tmp_path / "drivers" / "__init__.py").write_text("from dqpose.drivers.x import _y\n")
    modules = sources(tmp_path)
    assert set(modules) == {"dqpose.pkg", "dqpose.pkg.a", "dqpose.pkg.b", "dqpose.drivers",
                            "dqpose.drivers.x"}
    hidden = {m: private_imports(ast.parse(p.read_text()), set(modules))
              for m, p in modules.items()}
    assert hidden["dqpose.pkg.a"] == [(1, "dqpose.pkg.b", "_hidden"), (4, "dqpose.pkg.b", "_inner")]
    assert hidden["dqpose.drivers"] == [(1, "dqpose.drivers.x", "_y")]
    assert not cycles(import_graph(modules))        # lazy and TYPE_CHECKING imports aside
    assert cycles(import_graph(modules, lazy=True)) == [["dqpose.pkg.a", "dqpose.pkg.b"]]
    (tmp_path / "service" / "pkg" / "b.py").write_text("from dqpose.drivers import x\n")
    assert cycles(import_graph(sources(tmp_path))) == [["dqpose.drivers.x", "dqpose.pkg.b"]]


def documented(text: str) -> set[str]:
    """The paths DEVELOPERS.md names: each backticked ``dir/file``, and a bare backticked file name
    in the folder of its line's first path (``service/csrc/dq.h``, ``dq.c``)."""
    out: set[str] = set()
    for line in text.splitlines():
        folder = None
        for tok in re.findall(r"`([\w./*-]+)`", line):
            if "/" in tok:
                out.add(tok)
                folder = folder or tok.rsplit("/", 1)[0]
            elif folder and re.fullmatch(r"[\w-]+(\.\w+)+", tok):
                out.add(f"{folder}/{tok}")
    return out


def undocumented(root: pathlib.Path, text: str) -> list[str]:
    """Source files (service/, drivers/: .py .c .h; proto/: .proto) that ``text`` does not name,
    the generated stubs aside."""
    files = [p for folder in ("service", "drivers") for p in (root / folder).rglob("*")
             if p.suffix in (".py", ".c", ".h") and "_proto" not in p.parts]
    files += list((root / "proto").rglob("*.proto"))
    return sorted({p.relative_to(root).as_posix() for p in files} - documented(text))


def long_lines(text: str) -> list[int]:
    return [n for n, line in enumerate(text.splitlines(), 1) if len(line) > MAX_LINE]


def test_developers_md_is_short_lines_naming_every_source_file():
    text = (ROOT / "DEVELOPERS.md").read_text()
    long, missing = long_lines(text), undocumented(ROOT, text)
    assert not long, f"DEVELOPERS.md lines over {MAX_LINE} characters: {long}"
    assert not missing, f"give these a line in DEVELOPERS.md: {missing}"


def test_the_map_checks_find_what_they_look_for(tmp_path):
    for rel in ("service/a.py", "service/c/b.h", "service/c/b.c", "service/rpc/_proto/x_pb2.py",
                "drivers/sim/d.py", "proto/dqpose/v1/e.proto", "proto/dqpose/v1/README.md"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("")
    text = "| `service/c/b.h`, `b.c` | `x` |\n| `drivers/sim/` | d.py |\n" + "y" * (MAX_LINE + 1)
    assert undocumented(tmp_path, text) == ["drivers/sim/d.py", "proto/dqpose/v1/e.proto",
                                            "service/a.py"]
    assert long_lines(text) == [3]
