"""The library imports only its core dependencies (what ``pip install fsjax`` installs).

The README's main job (``pip install -e . && fsjax tour``) once died at section 14 of 30
on ``ModuleNotFoundError: matplotlib`` because the test extras hid the missing core
dependency. This test reads every module of ``fsjax/`` (module-level *and* function-level
imports) and fails if one imports a third-party package that is not a core dependency in
``pyproject.toml``, unless the import sits in a ``try`` that handles ``ImportError``
(an optional comparison that the code then leaves out, saying so).
``.ci/run`` also runs the tour itself on a bare install.
"""

from __future__ import annotations

import ast
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# distribution name (as in pyproject) -> import name, where the two differ
_IMPORT_NAME = {"pillow": "PIL", "opencv-python-headless": "cv2", "scikit-image": "skimage",
                "pywavelets": "pywt", "jaxlib": "jaxlib"}


def _core_modules() -> set[str]:
    text = (ROOT / "pyproject.toml").read_text()
    block = re.search(r"^dependencies\s*=\s*\[(.*?)^\]", text, re.S | re.M).group(1)
    names = set()
    for line in block.splitlines():
        m = re.match(r'\s*"([A-Za-z0-9_.\-]+)', line)
        if m:
            dist = m.group(1).lower()
            names.add(_IMPORT_NAME.get(dist, dist.replace("-", "_")))
    return names


def _guarded(node: ast.AST, parents: dict) -> bool:
    """True if ``node`` is inside a ``try`` body whose handlers catch ImportError."""
    p = parents.get(node)
    child = node
    while p is not None:
        if isinstance(p, ast.Try) and child in p.body:
            for h in p.handlers:
                names = []
                if h.type is None:
                    return True
                for t in (h.type.elts if isinstance(h.type, ast.Tuple) else [h.type]):
                    if isinstance(t, ast.Name):
                        names.append(t.id)
                if {"ImportError", "ModuleNotFoundError", "Exception"} & set(names):
                    return True
        child, p = p, parents.get(p)
    return False


def _third_party_imports(path: Path):
    tree = ast.parse(path.read_text(), filename=str(path))
    parents = {c: n for n in ast.walk(tree) for c in ast.iter_child_nodes(n)}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            mods = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            mods = [node.module]
        else:
            continue
        for m in mods:
            top = m.split(".")[0]
            if top in sys.stdlib_module_names or top in ("fsjax", "__future__"):
                continue
            yield top, node.lineno, _guarded(node, parents)


def test_core_dependency_list_is_read():
    core = _core_modules()
    assert {"jax", "numpy", "equinox", "optimistix", "PIL", "matplotlib"} <= core, core


def test_library_imports_only_core_dependencies():
    core = _core_modules()
    bad = []
    n_files = 0
    for path in sorted((ROOT / "fsjax").rglob("*.py")):
        n_files += 1
        for top, line, guarded in _third_party_imports(path):
            if top not in core and not guarded:
                bad.append(f"{path.relative_to(ROOT)}:{line}: imports {top!r} (not a core dependency)")
    assert n_files > 80
    assert not bad, "imports outside the core dependencies (add to pyproject or guard):\n" + "\n".join(bad)


def test_checker_flags_an_unguarded_optional_import(tmp_path):
    # the checker itself can fail: an unguarded cv2 import is reported, a guarded one is not
    f = tmp_path / "m.py"
    f.write_text("def g():\n    import cv2\n\ndef h():\n    try:\n        import skimage\n"
                 "    except ImportError:\n        skimage = None\n")
    found = {(top, guarded) for top, _, guarded in _third_party_imports(f)}
    assert found == {("cv2", False), ("skimage", True)}
