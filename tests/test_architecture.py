"""The house plan (shared/docs/architecture.md) holds in the code.

Every ``spctool`` module's imports are read with :mod:`ast` -- including the lazy
ones inside functions, which still make a circle a reader has to untangle -- and
checked for two things:

* no import circles: the module graph has no strongly connected component of
  more than one module (and no module imports itself);
* floors: a lower floor never imports an upper one.  Bottom to top:
  ``errors``, ``jsonsafe``, ``workers`` (and the package root) < ``formats`` < ``geometry`` <
  ``photometry`` < ``stages`` < ``sim``, ``batch``, ``figures`` < ``cli``.

Run as a script (``python tests/test_architecture.py``) to print the graph's
circles and floor breaches.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = "spctool"
ROOT = Path(__file__).resolve().parent.parent / PACKAGE

# Floor of each top-level room under spctool/; a module may import its own floor or lower ones.
FLOORS = {
    "": 0,  # spctool/__init__.py (__version__)
    "errors": 0,
    "jsonsafe": 0,  # JSON values of results (numpy only)
    "workers": 0,  # how local worker processes start (batch, the Monte Carlo)
    "threads": 0,  # numba's thread count without starting its pool
    "formats": 1,
    "geometry": 2,
    "photometry": 3,
    "stages": 4,
    "sim": 5,
    "batch": 5,
    "figures": 5,  # every picture: figures/__init__ (the canvas, overlays, pose and batch plots),
    # figures/register (surfaces, panels), figures/heights (lithos), figures/refine (geometry --plot)
    "cli": 6,
}


def module_files(root: Path = ROOT) -> dict[str, Path]:
    """Dotted module name -> file, for every ``.py`` file of the package."""
    modules = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        modules[".".join(parts)] = path
    return modules


def _resolve(name: str, modules: dict[str, Path]) -> str | None:
    """The package module ``name`` refers to: itself, or its nearest enclosing module."""
    while name:
        if name in modules:
            return name
        name = name.rpartition(".")[0]
    return None


def imports_of(module: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """Package modules that ``module`` imports anywhere in its file (module level or lazily)."""
    is_package = path.name == "__init__.py"
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                target = _resolve(alias.name, modules)
                if target:
                    found.add(target)
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: from .x import y
                base = module.split(".") if is_package else module.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            if source.split(".")[0] != PACKAGE:
                continue
            for alias in node.names:  # `from spctool.formats import atomic` imports a module
                target = _resolve(f"{source}.{alias.name}", modules)
                if target and target != _resolve(source, modules):
                    found.add(target)
                    continue
                target = _resolve(source, modules)
                if target:
                    found.add(target)
    return found


def import_graph(root: Path = ROOT) -> dict[str, set[str]]:
    modules = module_files(root)
    return {name: imports_of(name, path, modules) for name, path in modules.items()}


def strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's strongly connected components (iterative), each sorted, largest first."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []
    counter = 0
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            for child in children:
                if child not in graph:
                    continue
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                    break
                if child in on_stack:
                    low[node] = min(low[node], index[child])
            else:
                work.pop()
                if work:
                    parent = work[-1][0]
                    low[parent] = min(low[parent], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    components.append(sorted(component))
    return sorted(components, key=lambda c: (-len(c), c))


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Components that are circles: several modules, or one importing itself."""
    return [c for c in strongly_connected(graph) if len(c) > 1 or c[0] in graph[c[0]]]


def floor_of(module: str) -> int:
    parts = module.split(".")
    room = parts[1] if len(parts) > 1 else ""
    return FLOORS[room]


def floor_breaches(graph: dict[str, set[str]]) -> list[str]:
    return [
        f"{source} (floor {floor_of(source)}) imports {target} (floor {floor_of(target)})"
        for source in sorted(graph)
        for target in sorted(graph[source])
        if floor_of(target) > floor_of(source)
    ]


# ----------------------------------------------------------------------------- tests


def test_every_room_has_a_floor():
    for module in import_graph():
        floor_of(module)  # KeyError names a room the plan does not know


def test_no_import_circles():
    found = circles(import_graph())
    assert not found, "import circles: " + "; ".join(" <-> ".join(c) for c in found)


def test_lower_floors_never_import_upper_ones():
    breaches = floor_breaches(import_graph())
    assert not breaches, "\n".join(breaches)


def test_reader_sees_lazy_and_package_imports(tmp_path):
    """The checker itself: lazy, `from pkg import module`, relative imports and circles are seen."""
    pkg = tmp_path / PACKAGE
    (pkg / "formats").mkdir(parents=True)
    (pkg / "cli").mkdir()
    (pkg / "__init__.py").write_text('__version__ = "0"\n')
    (pkg / "formats" / "__init__.py").write_text("")
    (pkg / "cli" / "__init__.py").write_text("")
    (pkg / "formats" / "a.py").write_text("def f():\n    from spctool.formats import b\n")
    (pkg / "formats" / "b.py").write_text("from .a import f\nfrom spctool import __version__\n")
    (pkg / "formats" / "c.py").write_text("import spctool.cli.main\n")
    (pkg / "cli" / "main.py").write_text("from spctool.formats.c import x\n")
    graph = import_graph(pkg)
    assert graph[f"{PACKAGE}.formats.a"] == {f"{PACKAGE}.formats.b"}
    assert graph[f"{PACKAGE}.formats.b"] == {f"{PACKAGE}.formats.a", PACKAGE}
    assert circles(graph) == [
        [f"{PACKAGE}.cli.main", f"{PACKAGE}.formats.c"],
        [f"{PACKAGE}.formats.a", f"{PACKAGE}.formats.b"],
    ]
    assert floor_breaches(graph) == [f"{PACKAGE}.formats.c (floor 1) imports {PACKAGE}.cli.main (floor 6)"]


if __name__ == "__main__":
    graph = import_graph()
    for component in circles(graph):
        print("circle:", " <-> ".join(component))
    for breach in floor_breaches(graph):
        print("floor:", breach)
