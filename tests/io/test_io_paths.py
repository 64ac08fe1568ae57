"""One path per I/O name: ``fsjax.io`` re-exports ``image``, ``mesh`` and ``splat``; the former
modules ``fsjax.io3d`` and ``fsjax.io_splat`` warn (naming the new path) and give the same objects."""

from __future__ import annotations

import importlib
import subprocess
import sys

import pytest

import fsjax.io
from fsjax.io import image, mesh, rle, splat


def test_package_reexports_every_public_name():
    for mod in (image, mesh, rle, splat):
        for name in mod.__all__:
            assert getattr(fsjax.io, name) is getattr(mod, name), (mod.__name__, name)
    assert sorted(fsjax.io.__all__) == sorted(image.__all__ + mesh.__all__ + rle.__all__ + splat.__all__)


@pytest.mark.parametrize("old,new,names", [
    ("fsjax.io3d", "fsjax.io.mesh", mesh.__all__),
    ("fsjax.io_splat", "fsjax.io", splat.__all__),
])
def test_old_module_paths_warn_and_give_the_same_objects(old, new, names):
    sys.modules.pop(old, None)  # a module warns once, when it is first imported
    with pytest.warns(DeprecationWarning, match=f"{old} is deprecated; use {new}"):
        shim = importlib.import_module(old)
    target = importlib.import_module(new)
    assert len(names) >= 4
    for name in names:
        assert getattr(shim, name) is getattr(target, name), name
    assert sorted(shim.__all__) == sorted(names)


def test_old_attribute_path_warns_in_a_fresh_process():
    """``fsjax.io3d`` as an attribute of the package (the lazy table) still resolves, with the warning."""
    code = ("import warnings, fsjax\n"
            "with warnings.catch_warnings(record=True) as w:\n"
            "    warnings.simplefilter('always')\n"
            "    f = fsjax.io3d.read_points\n"
            "import fsjax.io.mesh\n"
            "print(f is fsjax.io.mesh.read_points, [str(x.message) for x in w if x.category is DeprecationWarning])\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("True [") and "fsjax.io3d is deprecated; use fsjax.io.mesh" in out.stdout
