"""The package layout by role (docs/architecture.md): size of modules, import direction, and no import circle.

The import graph is read from the source with ``ast`` (module-level imports only: an import inside a function runs
when it is called, after every module has loaded), so the test needs none of the packages installed.
"""

import ast
import os
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MAX_LINES = 600
LIBRARY = ("shield_nav.policies", "shield_nav.algorithms", "shield_nav.safety")
"""The method itself: it imports neither the harness (evaluation, training) nor the tools."""
HARNESS = ("shield_nav.evaluation", "shield_nav.training", "shield_nav.tools", "shield_nav.bench")


def _modules(package: str) -> dict[str, str]:
    """Dotted module name -> file, for every .py file under ``package``."""
    out = {}
    for folder, _, files in os.walk(os.path.join(ROOT, package)):
        for name in files:
            if name.endswith(".py"):
                path = os.path.join(folder, name)
                mod = os.path.relpath(path, ROOT)[:-3].replace(os.sep, ".")
                out[mod[: -len(".__init__")] if mod.endswith(".__init__") else mod] = path
    return out


def _imports(path: str, module: str, known: dict[str, str]) -> set[str]:
    """The known modules that ``path`` (module ``module``) imports at module level."""
    with open(path, encoding="utf-8") as f:
        tree = ast.parse(f.read())
    found = set()
    for node in tree.body:  # module level only
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: from the module's package
                pkg = module.split(".")[: -node.level] if not path.endswith("__init__.py") else module.split(".")
                if path.endswith("__init__.py") and node.level > 1:
                    pkg = pkg[: -(node.level - 1)]
                base = ".".join([*pkg, base]) if base else ".".join(pkg)
            names = [base, *(f"{base}.{a.name}" for a in node.names)]
        else:
            continue
        for name in names:
            while name and name not in known:
                name = name.rpartition(".")[0]
            if name and name != module:
                found.add(name)
    return found


@pytest.fixture(scope="module")
def graph():
    known = {**_modules("shield_nav"), **_modules("envs")}
    return {m: _imports(p, m, known) for m, p in known.items()}, known


def _lines(path: str) -> int:
    with open(path, encoding="utf-8") as f:
        return sum(1 for _ in f)


def find_circle(edges: dict[str, set[str]]) -> list[str] | None:
    """An import circle between distinct modules (``[a, b, ..., a]``), or None.

    A package's ``__init__`` importing its submodules, and them importing a sibling through it, is how Python packages
    re-export; an edge from a submodule into its own package's ``__init__`` is left out.
    """
    state: dict[str, int] = {}
    stack: list[str] = []

    def deps(m):
        return sorted(d for d in edges[m] if not (m.startswith(d + ".") and d in edges))

    def visit(m):
        state[m] = 1
        stack.append(m)
        for d in deps(m):
            if state.get(d) == 1:
                return [*stack[stack.index(d) :], d]
            if d not in state and (found := visit(d)):
                return found
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(edges):
        if m not in state and (found := visit(m)):
            return found
    return None


def test_no_module_over_the_line_limit():
    long = {m: n for m, p in _modules("shield_nav").items() if (n := _lines(p)) > MAX_LINES}
    assert not long, f"modules over {MAX_LINES} lines (split them by role): {long}"


def test_envs_never_imports_shield_nav(graph):
    edges, _ = graph
    up = {m: sorted(d for d in deps if d.startswith("shield_nav")) for m, deps in edges.items() if m.startswith("envs")}
    assert not {m: d for m, d in up.items() if d}


def test_the_library_does_not_import_the_harness_or_the_tools(graph):
    edges, _ = graph
    bad = {m: sorted(d for d in deps if d.startswith(HARNESS)) for m, deps in edges.items() if m.startswith(LIBRARY)}
    assert not {m: d for m, d in bad.items() if d}


def test_only_the_tools_and_benchmarks_import_the_tools():
    """The tools sit on top: nothing below them imports one, not even inside a function (the ``ast.walk`` here)."""
    below = {
        m: p for m, p in _modules("shield_nav").items() if not m.startswith(("shield_nav.tools", "shield_nav.bench"))
    }
    bad = {}
    for m, path in below.items():
        with open(path, encoding="utf-8") as f:
            tree = ast.parse(f.read())
        for node in ast.walk(tree):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
            if isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            bad.setdefault(m, []).extend(n for n in names if n.startswith("shield_nav.tools"))
    assert not {m: d for m, d in bad.items() if d}


def test_no_import_circle(graph):
    edges, _ = graph
    circle = find_circle(edges)
    assert circle is None, "import circle: " + " -> ".join(circle or [])


def test_the_graph_reader_finds_a_circle_and_the_re_export_of_a_package(tmp_path, monkeypatch):
    """The checks can fail: two modules that import each other are found; a package re-exporting its module is not."""
    pkg = tmp_path / "shield_nav"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from shield_nav.b import x\n")
    (pkg / "b.py").write_text("import shield_nav.a\nx = 1\n")
    (pkg / "sub" / "__init__.py").write_text("from .c import y\n")
    (pkg / "sub" / "c.py").write_text("from shield_nav.sub import d\ny = 1\n")
    (pkg / "sub" / "d.py").write_text("def f():\n    import shield_nav.a\n")  # inside a function: not an edge
    monkeypatch.setattr(sys.modules[__name__], "ROOT", str(tmp_path))
    known = _modules("shield_nav")
    edges = {m: _imports(p, m, known) for m, p in known.items()}
    assert edges["shield_nav.a"] == {"shield_nav.b"} and edges["shield_nav.b"] == {"shield_nav.a"}
    assert edges["shield_nav.sub"] == {"shield_nav.sub.c"} and edges["shield_nav.sub.d"] == set()
    assert edges["shield_nav.sub.c"] == {"shield_nav.sub", "shield_nav.sub.d"}
    assert find_circle(edges) == ["shield_nav.a", "shield_nav.b", "shield_nav.a"]
    del edges["shield_nav.a"], edges["shield_nav.b"]
    assert find_circle(edges) is None
