"""The shape of the project: imports flow one way (DESIGN.md), with no cycle anywhere.

Two packages: ``wallcull`` (the server and its pipeline) and ``wallcull_clients`` (``clients/``,
the programs that talk to it, installed apart). The clients may use wallcull's core (the wire
codecs above all); wallcull never imports the clients, and the clients never import the server
or the command line. Every import counts, at module level or inside a function: a lazy import
still ties two modules together.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
#: each package and the folder that holds it
PACKAGES = {"wallcull": ROOT, "wallcull_clients": ROOT / "clients"}

#: Modules of the pipeline (scene -> frusta -> cull -> fit -> encode) and their helpers: they
#: never reach for a shell around them.
CORE = ("bounds", "scene", "wall", "screens", "stereo", "validate", "cull", "projection", "quad",
        "lowilie", "fit", "pipeline", "protocol", "encode", "workers", "settings", "oracle",
        "paths", "errors", "documents")
SHELLS = ("cli", "server", "service", "bench", "experiments")


def _module_name(path: Path, top: Path) -> str:
    parts = path.relative_to(top).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_module(name: str) -> bool:
    top = PACKAGES.get(name.split(".")[0])
    if top is None:
        return False
    path = top / name.replace(".", "/")
    return path.with_suffix(".py").exists() or path.is_dir()


def _imports(path: Path, name: str) -> set[str]:
    tree = ast.parse(path.read_text())
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            # ``from X import a``: the module X.a when a is one, else X
            out.update(f"{target}.{a.name}" if _is_module(f"{target}.{a.name}") else target
                       for a in node.names)
    return {m for m in out if m.split(".")[0] in PACKAGES}


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    files = {_module_name(p, top): p for package, top in PACKAGES.items()
             for p in (top / package).rglob("*.py")}
    out = {}
    for name, path in files.items():
        # an import of a name inside a module counts as an import of the module
        deps = set()
        for m in _imports(path, name):
            while m not in files and "." in m:
                m = m.rpartition(".")[0]
            # a module's own enclosing packages are loaded before it: not an edge
            if m in files and m != name and not name.startswith(m + "."):
                deps.add(m)
        out[name] = deps
    return out


def test_no_import_cycle(graph):
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for d in sorted(graph[m]):
            if state.get(d) == 1:
                cycle = stack[stack.index(d):] + [d]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if d not in state:
                visit(d)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)


@pytest.mark.parametrize("core", CORE)
def test_core_modules_never_import_a_shell(graph, core):
    name = f"wallcull.{core}"
    shells = {f"wallcull.{s}" for s in SHELLS}
    bad = {d for d in graph[name] if d in shells or any(d.startswith(s + ".") for s in shells)}
    assert not bad, f"{name} imports {sorted(bad)}"


def test_clients_never_import_the_server_or_the_command_line(graph):
    clients = [name for name in graph if name.startswith("wallcull_clients")]
    assert len(clients) > 5  # the test sees the clients' package
    for name in clients:
        bad = {d for d in graph[name] if d.split(".")[:2] in (["wallcull", "server"],
                                                              ["wallcull", "service"],
                                                              ["wallcull", "cli"])}
        assert not bad, f"{name} imports {sorted(bad)}"


def test_the_server_never_imports_the_clients(graph):
    for name, deps in graph.items():
        if name.split(".")[0] == "wallcull":
            bad = {d for d in deps if d.split(".")[0] == "wallcull_clients"}
            assert not bad, f"{name} imports {sorted(bad)}"


def test_no_generic_top_level_names():
    """What an install puts in site-packages is named for the project."""
    assert not (ROOT / "clients" / "__init__.py").exists()
    assert not (ROOT / "scenes" / "__init__.py").exists()
    for folder in PACKAGES.values():
        tops = {p.parent.name for p in folder.glob("*/__init__.py")} - {"tests"}  # not installed
        assert tops <= set(PACKAGES), tops
