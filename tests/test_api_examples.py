"""Docstring examples of the library beyond registered ops (cameras, renderers, fits, evolution, I/O) run and hold.

Every module that gets an API page (``tools/gen_docs.py``: ``API_ROOTS``) has its doctest
examples executed here in float64, with the globals ``fsjax``, ``jnp``, ``np`` and ``jax``.
"""

from __future__ import annotations

import doctest
import importlib.util
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fsjax

REPO = Path(__file__).resolve().parents[1]


def _gen():
    spec = importlib.util.spec_from_file_location("fsjax_tools_gen_docs_api", REPO / "tools" / "gen_docs.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


MODULES = _gen().api_modules()

# Docstring examples run by another test, in the same process as that test's further checks on the
# example's own result, instead of here: the example would repeat that test's costliest call.
# docstring (doctest name) -> the test that runs it (tests/fit/test_cross.py: run_docstring_example)
RUN_ELSEWHERE = {
    "fsjax.fit.cross.register_cross":
        "tests/fit/test_cross.py::test_cad_mesh_against_partial_scan_50deg_and_wrong_object",
}


@pytest.mark.parametrize("mod", MODULES, ids=lambda m: m.__name__)
def test_module_examples(mod):
    finder = doctest.DocTestFinder()
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    globs = {"fsjax": fsjax, "jnp": jnp, "np": np, "jax": jax}
    tests = [t for t in finder.find(mod, globs=dict(globs)) if t.examples and t.name not in RUN_ELSEWHERE]
    for t in tests:
        runner.run(t)
    res = runner.summarize(verbose=False)
    assert res.failed == 0, f"{mod.__name__}: {res.failed} of {res.attempted} docstring examples failed"


def test_examples_run_elsewhere_are_run_there():
    """Each docstring left out above exists, has an example, and its test names the function and runs
    its docstring (a renamed function or test cannot drop the example silently)."""
    finder = doctest.DocTestFinder()
    by_name = {t.name: t for m in MODULES for t in finder.find(m) if t.examples}
    for name, where in RUN_ELSEWHERE.items():
        assert name in by_name, f"{name}: no docstring example (RUN_ELSEWHERE is stale)"
        path, test = where.split("::")
        body = (REPO / path).read_text().split(f"\ndef {test}(")[1].split("\ndef ")[0]
        assert f"run_docstring_example({name.rsplit('.', 1)[1]})" in body, f"{where} does not run {name}'s example"
