"""``fsjax.enable_compile_cache``: a second process loads compiled programs instead of compiling.

Both checks run in fresh subprocesses: the cache is process-global JAX state, and the test
process has its own cache configured by ``conftest.py``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import fsjax

ROOT = Path(__file__).resolve().parents[1]

_PROBE = textwrap.dedent(
    """
    import json, sys
    import jax, jax.numpy as jnp
    events = []
    jax.monitoring.register_event_listener(lambda name, **kw: events.append(name))
    import fsjax
    d = fsjax.enable_compile_cache(sys.argv[1], min_compile_time_s=0.0)
    img = fsjax.Image(jnp.linspace(0.0, 1.0, 48 * 40).reshape(48, 40))
    out = jax.jit(lambda x: fsjax.ops.gaussian(x, sigma=1.5).data.sum())(img)
    print(json.dumps({"dir": str(d), "value": float(out),
                      "hits": events.count("/jax/compilation_cache/cache_hits"),
                      "misses": events.count("/jax/compilation_cache/cache_misses")}))
    """
)


def _run(*args, env=None):
    e = dict(os.environ, PYTHONPATH=str(ROOT), **(env or {}))
    e.pop("XLA_FLAGS", None)
    r = subprocess.run([sys.executable, "-c", *args], capture_output=True, text=True, env=e, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout


def test_second_process_loads_from_the_cache(tmp_path):
    first = json.loads(_run(_PROBE, str(tmp_path)).strip().splitlines()[-1])
    n_files = sum(1 for _ in tmp_path.rglob("*") if _.is_file())
    second = json.loads(_run(_PROBE, str(tmp_path)).strip().splitlines()[-1])
    print(f"compile cache: first process {first['misses']} misses / {first['hits']} hits, {n_files} files; "
          f"second process {second['misses']} misses / {second['hits']} hits")
    assert first["dir"] == str(tmp_path)
    assert first["misses"] >= 1 and first["hits"] == 0  # cold: compiled and written
    assert n_files >= 1
    assert second["hits"] >= 1 and second["misses"] == 0  # warm: every program loaded
    assert second["value"] == first["value"]  # the loaded program computes the same number


def test_cache_dir_resolution_and_off_switch(monkeypatch, tmp_path):
    monkeypatch.setenv("FSJAX_CACHE_DIR", "off")
    assert fsjax.compile_cache_dir() is None
    assert fsjax.enable_compile_cache() is None  # off: nothing changed, nothing created
    monkeypatch.setenv("FSJAX_CACHE_DIR", str(tmp_path / "c"))
    assert fsjax.compile_cache_dir() == tmp_path / "c"
    monkeypatch.delenv("FSJAX_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    if sys.platform.startswith("linux"):
        assert fsjax.compile_cache_dir() == tmp_path / "xdg" / "fsjax" / "xla"
    assert fsjax.compile_cache_dir(tmp_path / "x") == tmp_path / "x"
    with pytest.raises(ValueError, match="enable_compile_cache: argument 'min_compile_time_s'"):
        fsjax.enable_compile_cache(tmp_path, min_compile_time_s=-1.0)


def test_import_leaves_jax_state_alone_and_docstring_examples_run(tmp_path):
    # one subprocess for both (importing fsjax is the cost): first the state after import,
    # then the module's doctests (which do enable a cache, in that throwaway process)
    out = _run("import doctest, jax, fsjax, fsjax._cache as m\n"
               "print(repr(jax.config.jax_compilation_cache_dir))\n"
               "r = doctest.testmod(m); print(r.failed, r.attempted)",
               env={"FSJAX_CACHE_DIR": str(tmp_path)})
    state, counts = out.strip().splitlines()[-2:]
    assert state == "None"  # import fsjax enabled no cache, although FSJAX_CACHE_DIR is set
    assert not any(tmp_path.iterdir())
    failed, attempted = map(int, counts.split())
    assert attempted >= 6 and failed == 0
