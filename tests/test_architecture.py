"""The house rules of docs/architecture.md, checked.

* **Layering**: each package imports only the layers below it (the table ``ALLOWED`` is the
  one in docs/architecture.md; a test checks the two agree). ``types`` imports nothing of
  fsjax but the bottom-layer checks, ``ops`` imports no fit, synth, tour or evolve, and
  nothing but the command line imports the tour.
* **No import cycles** between fsjax modules (module- and function-level imports).
* **One path per public name**: across the public namespaces a name means one object, and
  doctests import public paths only.

The import graph is read from the source (AST), so the checks cost no JAX import.
"""

from __future__ import annotations

import ast
import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "fsjax"

# layer -> the fsjax layers it may import (the top-level package fsjax/__init__.py wires them all
# and is exempt; "fsjax" as a target means importing the top-level package itself).
ALLOWED: dict[str, set[str]] = {
    "_checks": set(),
    "_linalg": set(),
    "_cache": set(),
    "types": {"_checks"},
    "registry": {"types", "_checks", "fsjax"},  # fsjax: only to read the OP_PROVIDERS wiring
    "data": {"types", "_checks"},
    "render": {"types", "_checks", "_linalg"},
    "ops": {"types", "_checks", "_linalg", "registry", "render"},
    "pipeline": {"types", "_checks", "_linalg", "registry"},
    "io": {"types", "_checks", "ops", "render"},
    "fit": {"types", "_checks", "_linalg", "registry", "render", "ops", "data"},
    "synth": {"types", "_checks", "_linalg", "registry", "render", "ops", "fit", "data", "io"},
    "evolve": {"types", "_checks", "registry", "pipeline", "ops", "synth", "data"},
    "fuzz": {"types", "_checks", "registry", "pipeline", "ops", "synth", "data", "render", "fit", "_cache"},
    "tour": {"types", "_checks", "_linalg", "registry", "pipeline", "ops", "render", "fit", "synth", "data",
             "io", "evolve", "_cache", "fsjax"},
    "io3d": {"io"},  # deprecated shims of fsjax.io.mesh / fsjax.io.splat, gone next release
    "io_splat": {"io"},
    "sfm": {"types", "_checks", "_linalg", "registry", "render", "ops", "fit", "data", "io"},
    "cli": {"fsjax", "_cache", "tour", "evolve", "io", "fuzz", "registry", "types", "pipeline", "sfm"},
}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in PKG.rglob("*.py")}


def _layer(module: str) -> str:
    parts = module.split(".")
    return "fsjax" if len(parts) == 1 else parts[1]


def _in_type_checking(node: ast.AST, parents: dict[ast.AST, ast.AST]) -> bool:
    while node in parents:
        node = parents[node]
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            return True
    return False


def _imports(module: str, path: Path, known: dict[str, Path]) -> set[str]:
    """fsjax modules imported by ``module`` (at any level of the file, outside TYPE_CHECKING),
    resolved to modules: ``from a.b import c`` counts ``a.b.c`` when that is a module, else ``a.b``."""
    tree = ast.parse(path.read_text())
    parents = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    out: set[str] = set()
    for node in ast.walk(tree):
        if _in_type_checking(node, parents):
            continue
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.split(".")[0] == "fsjax"}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != "fsjax":
                continue
            subs = {f"{target}.{a.name}" for a in node.names if f"{target}.{a.name}" in known}
            out |= subs if subs and len(subs) == len(node.names) else subs | {target}
    return out


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    known = _modules()
    return {m: _imports(m, p, known) for m, p in known.items()}


def test_every_layer_is_in_the_table(graph):
    unknown = sorted({_layer(m) for m in graph} - set(ALLOWED) - {"fsjax"})
    assert not unknown, (f"new top-level module(s) {unknown}: add the layer to ALLOWED here and to the "
                         f"layer table of docs/architecture.md")


def _violations(graph: dict[str, set[str]]) -> list[str]:
    bad = []
    for module, targets in sorted(graph.items()):
        layer = _layer(module)
        if layer == "fsjax":
            continue
        for t in sorted(targets):
            tl = _layer(t)
            if tl != layer and tl not in ALLOWED[layer]:
                bad.append(f"{module} imports {t} ({layer} -> {tl})")
    return bad


def test_layering(graph):
    bad = _violations(graph)
    assert not bad, "imports against the layering of docs/architecture.md:\n" + "\n".join(bad)


def test_nothing_but_the_command_line_imports_the_tour(graph):
    users = sorted(m for m, ts in graph.items() if _layer(m) not in ("tour", "cli")
                   and any(_layer(t) == "tour" for t in ts))
    assert users == []


def test_checker_flags_an_op_importing_a_fit(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text("def f():\n    from ..fit import icp\n    from ..types import Image\n")
    known = {"fsjax.ops._probe": probe, "fsjax.fit.icp": Path("icp.py"), "fsjax.types": Path("t.py")}
    got = _imports("fsjax.ops._probe", probe, known)
    assert got == {"fsjax.fit.icp", "fsjax.types"}
    assert _violations({"fsjax.ops._probe": got}) == ["fsjax.ops._probe imports fsjax.fit.icp (ops -> fit)"]


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in graph:
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycles(graph):
    # a package's __init__ re-exporting its own modules is not a cycle with them: drop the edges
    # from a module to the package(s) that contain it (Python has imported those first anyway)
    g = {m: {t for t in ts if not m.startswith(t + ".")} for m, ts in graph.items()}
    assert _cycles(g) == []


def test_cycle_finder_finds_one():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


# --- one path per public name --------------------------------------------------------------

NAMESPACES = ("fsjax", "fsjax.types", "fsjax.registry", "fsjax.pipeline", "fsjax.ops", "fsjax.fit",
              "fsjax.render", "fsjax.synth", "fsjax.io", "fsjax.evolve", "fsjax.data")


def _public(modname: str) -> dict[str, object]:
    mod = importlib.import_module(modname)
    names = getattr(mod, "__all__", None)
    if names is None:
        names = [n for n in vars(mod) if not n.startswith("_")]
    out = {}
    for n in names:
        obj = getattr(mod, n)
        if isinstance(obj, type(importlib)) or isinstance(obj, (int, float, str, tuple, dict)):
            continue
        out[n] = obj
    return out


def test_one_object_per_public_name():
    seen: dict[str, tuple[str, object]] = {}
    clashes = []
    for ns in NAMESPACES:
        for name, obj in _public(ns).items():
            if name in seen and seen[name][1] is not obj:
                clashes.append(f"{name}: {seen[name][0]}.{name} is not {ns}.{name}")
            seen.setdefault(name, (ns, obj))
    assert not clashes, "one public name, two meanings:\n" + "\n".join(clashes)


def test_no_name_in_two_public_lists_of_one_namespace():
    # e.g. ops' families each list their ops in __all__; a name listed by two families is
    # defined (or re-exported) twice
    import fsjax.ops as ops

    owners: dict[str, list[str]] = {}
    for modname in sorted(m for m in _modules() if m.startswith("fsjax.ops.") and "._" in m):
        mod = importlib.import_module(modname)
        for n in getattr(mod, "__all__", ()):
            owners.setdefault(n, []).append(modname)
    twice = {n: ms for n, ms in owners.items() if len(ms) > 1}
    assert not twice, f"ops listed by two family modules: {twice}"
    assert set(owners) <= {n for n in vars(ops) if not n.startswith("_")}


def test_every_sort_is_reachable_from_the_package():
    import fsjax
    import fsjax.types as types

    sorts = [n for n in types.__all__ if isinstance(getattr(types, n), type) and issubclass(getattr(types, n), types.Sort)]
    assert len(sorts) >= 27
    missing = [n for n in sorts if getattr(fsjax, n, None) is not getattr(types, n)]
    assert missing == []


_DOC_IMPORT = re.compile(r"^\s*(?:>>>|\.\.\.)\s+(?:from\s+(\S+)\s+import\s+(.+)|import\s+(\S+))")


def _private_doctest_imports() -> list[str]:
    bad = []
    for path in sorted(PKG.rglob("*.py")):
        for i, line in enumerate(path.read_text().splitlines(), 1):
            m = _DOC_IMPORT.match(line)
            if not m:
                continue
            module = m.group(1) or m.group(3)
            names = [n.strip().split(" as ")[0] for n in (m.group(2) or "").strip("()").split(",") if n.strip()]
            if any(part.startswith("_") for part in module.split(".")) or any(n.startswith("_") for n in names):
                bad.append(f"{path.relative_to(ROOT)}:{i}: {line.strip()}")
    return bad


def test_doctests_import_public_paths_only():
    bad = _private_doctest_imports()
    assert not bad, "doctests importing private modules or names:\n" + "\n".join(bad)


def test_doctest_scanner_flags_a_private_import(tmp_path, monkeypatch):
    line = "        >>> from fsjax.synth._inspection import step_edge"
    m = _DOC_IMPORT.match(line)
    assert m and m.group(1) == "fsjax.synth._inspection"


def test_architecture_doc_states_the_same_layers():
    text = (ROOT / "docs" / "architecture.md").read_text()
    table = {}
    for row in re.findall(r"^\| `([\w.]+)` \| ([^|]*) \|", text, re.M):
        layer, may = row
        table[layer.removeprefix("fsjax.")] = {x.strip().strip("`").removeprefix("fsjax.")
                                               for x in may.split(",") if x.strip() and x.strip() != "nothing"}
    missing = sorted(set(ALLOWED) - set(table))
    assert not missing, f"docs/architecture.md has no layer row for {missing}"
    differ = {k: (sorted(table[k]), sorted(ALLOWED[k])) for k in ALLOWED if table[k] != ALLOWED[k]}
    assert not differ, f"docs/architecture.md and this test disagree (doc, test): {differ}"
