"""solderpyro's modules depend on each other one way, and only through public names.

The check parses every module of the package with :mod:`ast` (nothing is imported or run) and
applies two rules.

**Import graph.** Nodes are the package's modules: every ``*.py`` file under ``solderpyro/``,
a package being its ``__init__.py``. An edge ``A -> B`` is any ``import`` statement in ``A``
that names ``B``, wherever it sits: at module level, inside a function or class, under
``if TYPE_CHECKING:`` or in a ``try``. Relative imports are resolved against ``A``'s package.
``import a.b.c`` names the module ``a.b.c``; ``from X import Y`` names the module ``X.Y``
when that is a module of the package (a submodule import), else the module ``X`` (a name
defined in ``X``, a package's ``__init__`` included). The parent packages that Python
initializes on the way to a submodule are not edges (every submodule would otherwise be in a
circle with a package ``__init__`` that imports it), and imports made by ``importlib`` at
run time are not seen. **The graph must have no cycle**: a function-local import that closes a
circle still couples the two modules both ways, it only hides it.

**Private names.** A name with a leading underscore that is not a dunder (``_x``, not
``__version__``) belongs to its module. No module may take one from another module of the
package: not by ``from X import _x`` (a name, or a private submodule as ``import X._m``
also takes), nor as an attribute ``m._x`` of a module ``m`` it imported
(``import solderpyro.x as m``, ``from solderpyro import x``, ``from . import x``; a module-level
import binds its name in the whole module, one in a function in that function and the ones
nested in it, and a parameter of the same name hides it). A public name of a private module
(``from X._m import y``) is that module's interface. The exception is the package of C kernels,
``solderpyro._native``: importing it is allowed (it is a private subpackage of solderpyro as
a whole), its own private names are not. Imports from outside the package are not checked
(``from scipy.stats import chi2 as _chi2`` is fine), nor is the name a public import is bound
to (``from m import f as _f``).

A failure lists every violation: each cycle with the files and lines of its imports, each
private name with the file and line that takes it.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2] / "solderpyro"
#: private modules that other modules may import
ALLOWED_PRIVATE_MODULES = ("solderpyro._native",)


@dataclass(frozen=True)
class Edge:
    """``src`` imports ``dst`` at ``src``'s ``line``."""

    src: str
    dst: str
    line: int


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def modules_of(root: Path, package: str) -> dict[str, Path]:
    """Dotted module name -> file, for every ``*.py`` under the package directory ``root``."""
    out = {}
    for p in sorted(root.rglob("*.py")):
        parts = [package, *p.relative_to(root).with_suffix("").parts]
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def _resolve_from(node: ast.ImportFrom, module: str, is_package: bool) -> str | None:
    """The absolute module that ``from ... import`` names (None: above the top package)."""
    if not node.level:
        return node.module or ""
    base = module.split(".") if is_package else module.split(".")[:-1]
    if node.level - 1 > len(base) - 1:
        return None
    base = base[:len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


class _Scan(ast.NodeVisitor):
    """One module's import edges and private-name uses, with per-scope module bindings."""

    def __init__(self, module: str, is_package: bool, mods: dict[str, Path], package: str,
                 allowed: tuple[str, ...]) -> None:
        self.module, self.is_package, self.mods = module, is_package, mods
        self.package, self.allowed = package, allowed
        self.edges: list[Edge] = []
        self.private: list[tuple[int, str]] = []
        self.scopes: list[dict[str, str]] = [{}]  # name -> dotted module it is bound to

    def _ours(self, name: str) -> bool:
        return name == self.package or name.startswith(self.package + ".")

    def _edge(self, dst: str, line: int) -> None:
        if dst != self.module:
            self.edges.append(Edge(self.module, dst, line))

    def _flag(self, line: int, what: str) -> None:
        self.private.append((line, what))

    def visit_Import(self, node: ast.Import) -> None:
        for a in node.names:
            if not self._ours(a.name):
                continue
            parts = a.name.split(".")
            target = next((".".join(parts[:i]) for i in range(len(parts), 0, -1)
                           if ".".join(parts[:i]) in self.mods), a.name)
            self._edge(target, node.lineno)
            for i in range(1, len(parts)):
                if _is_private(parts[i]) and ".".join(parts[:i + 1]) not in self.allowed:
                    self._flag(node.lineno, f"import {a.name}")
                    break
            self.scopes[-1][a.asname or parts[0]] = a.name if a.asname else parts[0]

    def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
        src = _resolve_from(node, self.module, self.is_package)
        if src is None or not self._ours(src):
            return
        for a in node.names:
            sub = f"{src}.{a.name}"
            if sub in self.mods:  # a submodule
                self._edge(sub, node.lineno)
                if _is_private(a.name) and sub not in self.allowed:
                    self._flag(node.lineno, f"from {src} import {a.name} (a private module)")
                self.scopes[-1][a.asname or a.name] = sub
            else:
                self._edge(src, node.lineno)
                if _is_private(a.name) and src != self.module:
                    self._flag(node.lineno, f"from {src} import {a.name}")

    def _scoped(self, node: ast.AST) -> None:
        scope = dict(self.scopes[-1])
        args = getattr(node, "args", None)
        if isinstance(args, ast.arguments):  # parameters shadow the enclosing bindings
            for arg in (*args.posonlyargs, *args.args, *args.kwonlyargs, args.vararg,
                        args.kwarg):
                if arg is not None:
                    scope.pop(arg.arg, None)
        self.scopes.append(scope)
        self.generic_visit(node)
        self.scopes.pop()

    visit_FunctionDef = visit_AsyncFunctionDef = visit_ClassDef = visit_Lambda = _scoped

    def visit_Attribute(self, node: ast.Attribute) -> None:
        chain, v = [], node.value
        while isinstance(v, ast.Attribute):
            chain.append(v.attr)
            v = v.value
        if isinstance(v, ast.Name) and v.id in self.scopes[-1] and _is_private(node.attr):
            mod = ".".join([self.scopes[-1][v.id], *reversed(chain)])
            if mod in self.mods and mod != self.module:
                self._flag(node.lineno, f"{ast.unparse(node)} (a private name of {mod})")
        self.generic_visit(node)


def _module_level(tree: ast.Module) -> list[ast.stmt]:
    """The import statements of the module's own scope (in ``if``/``try`` blocks too, not in
    function or class bodies)."""
    out: list[ast.stmt] = []
    todo: list[ast.AST] = list(tree.body)
    while todo:
        node = todo.pop(0)
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            out.append(node)
        elif not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            todo.extend(c for c in ast.iter_child_nodes(node) if isinstance(c, ast.stmt))
    return out


def scan(root: Path, package: str, allowed: tuple[str, ...] = ()
         ) -> tuple[dict[str, Path], list[Edge], list[str]]:
    """Parse every module of the package at ``root``: its modules, the import edges between
    them, and the private-name violations as ``"file:line: what"`` strings."""
    mods = modules_of(root, package)
    edges: list[Edge] = []
    private: list[str] = []
    for name, path in mods.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        s = _Scan(name, path.name == "__init__.py", mods, package, allowed)
        # module-level imports bind in every function of the module, wherever they stand
        top = _Scan(name, path.name == "__init__.py", mods, package, allowed)
        for stmt in _module_level(tree):
            top.visit(stmt)
        s.scopes = [dict(top.scopes[0])]
        s.visit(tree)
        edges += s.edges
        private += [f"{path}:{line}: {what}" for line, what in s.private]
    return mods, edges, private


def cycles(edges: list[Edge]) -> list[list[Edge]]:
    """One cycle (its edges, in order) per strongly connected component of more than one
    module (Tarjan's algorithm, iterative)."""
    graph: dict[str, dict[str, Edge]] = {}
    for e in edges:
        graph.setdefault(e.src, {}).setdefault(e.dst, e)
        graph.setdefault(e.dst, {})
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    comps: list[list[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    comps.append(sorted(comp))
    out = []
    for comp in comps:  # a shortest circle through the component's first module
        members, start = set(comp), comp[0]
        parent: dict[str, Edge] = {}
        frontier, seen, closing = [start], {start}, None
        while closing is None:
            nxt = []
            for v in frontier:
                for w, e in sorted(graph[v].items()):
                    if w == start:
                        closing = e
                        break
                    if w in members and w not in seen:
                        seen.add(w)
                        parent[w] = e
                        nxt.append(w)
                if closing is not None:
                    break
            frontier = nxt
        path, v = [closing], closing.src
        while v != start:
            path.append(parent[v])
            v = parent[v].src
        out.append(path[::-1])
    return out


def _describe(cycle: list[Edge], mods: dict[str, Path], root: Path) -> str:
    return "cycle: " + " -> ".join(
        f"{mods[e.src].relative_to(root.parent)}:{e.line}" for e in cycle) + \
        f" -> {mods[cycle[0].src].relative_to(root.parent)}"


def test_solderpyro_has_no_import_cycle_and_takes_no_private_name_across_modules() -> None:
    mods, edges, private = scan(ROOT, "solderpyro", ALLOWED_PRIVATE_MODULES)
    assert len(mods) > 50 and len(edges) > 100  # the scan saw the package
    problems = [_describe(c, mods, ROOT) for c in cycles(edges)]
    problems += [f"private name: {Path(p).relative_to(ROOT.parent)}" for p in private]
    assert not problems, "\n".join(problems)


def test_the_checker_finds_a_cycle_and_private_names_in_synthetic_sources(tmp_path) -> None:
    """The detector on a small package: a circle closed by a function-local relative import,
    private names taken by import and as a module attribute, and what the rules allow."""
    pkg = tmp_path / "pkg"
    (pkg / "_native").mkdir(parents=True)
    files = {
        "__init__.py": "",
        "_native/__init__.py": "def ptr(t): return t\ndef _raw(t): return t\n",
        "a.py": "from pkg.b import f\n_hidden = 1\n",
        "b.py": "def f():\n    from . import a\n    return a\n",
        "c.py": "from pkg.a import _hidden\n",
        "d.py": ("from scipy.stats import chi2 as _chi2\n"
                 "from pkg import _native\n"
                 "from pkg.b import f as _f\n"
                 "import pkg.a as m\n"
                 "def g():\n    return m._hidden, _native.ptr, _native._raw\n"),
        "e.py": "def h():\n    from pkg import a\n    return a\ndef k(a):\n    return a._x\n",
    }
    for name, text in files.items():
        (pkg / name).write_text(text)
    mods, edges, private = scan(pkg, "pkg", ("pkg._native",))
    assert set(mods) == {"pkg", "pkg._native", "pkg.a", "pkg.b", "pkg.c", "pkg.d", "pkg.e"}
    (cyc,) = cycles(edges)
    assert [(e.src, e.dst, e.line) for e in cyc] == [("pkg.a", "pkg.b", 1),
                                                     ("pkg.b", "pkg.a", 2)]
    assert "pkg/a.py:1 -> pkg/b.py:2 -> pkg/a.py" in _describe(cyc, mods, pkg)
    got = sorted(p.replace(str(pkg), "pkg") for p in private)
    assert got == ["pkg/c.py:1: from pkg.a import _hidden",
                   "pkg/d.py:6: _native._raw (a private name of pkg._native)",
                   "pkg/d.py:6: m._hidden (a private name of pkg.a)"]
    # without the circle, no cycle
    (pkg / "b.py").write_text("def f():\n    return 1\n")
    assert cycles(scan(pkg, "pkg")[1]) == []
