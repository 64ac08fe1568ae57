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


@pytest.mark.parametrize("mod", MODULES, ids=lambda m: m.__name__)
def test_module_examples(mod):
    finder = doctest.DocTestFinder()
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    globs = {"fsjax": fsjax, "jnp": jnp, "np": np, "jax": jax}
    tests = [t for t in finder.find(mod, globs=dict(globs)) if t.examples]
    for t in tests:
        runner.run(t)
    res = runner.summarize(verbose=False)
    assert res.failed == 0, f"{mod.__name__}: {res.failed} of {res.attempted} docstring examples failed"
