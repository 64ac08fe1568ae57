"""Calling an op again eagerly, with the same shapes, compiles nothing.

Found by the chain fuzzer (docs/fuzz.md, class RECOMPILE): ops that ran a ``lax`` loop built
from fresh closures outside ``jit`` were traced and compiled again on every eager call (1-2 s
each on this machine). Their loops now run in module-level jitted cores. These are the 14 ops
a scan of every op (called twice eagerly on its standard input) found recompiling.
"""

from __future__ import annotations

import jax
import jax.monitoring
import jax.numpy as jnp
import pytest

import fsjax
from fsjax.synth import standard_input

_COUNT = {"n": 0}


def _listener(event, duration, **kw):
    if event == "/jax/core/compile/backend_compile_duration":
        _COUNT["n"] += 1


jax.monitoring.register_event_duration_secs_listener(_listener)


def _compiles_on_second_call(fn, *args, **kwargs) -> int:
    jax.block_until_ready(fn(*args, **kwargs))
    before = _COUNT["n"]
    jax.block_until_ready(fn(*args, **kwargs))
    return _COUNT["n"] - before


def test_counter_sees_a_compile():
    # the null: a program built afresh on each call compiles every time
    x = jnp.arange(5.0)
    assert _compiles_on_second_call(lambda v: jax.jit(lambda u: u * 3.0 + 1.0)(v), x) >= 1


@pytest.mark.parametrize("name", ["li_level", "li", "hysteresis", "canny", "depth_to_points", "shade_depth",
                                  "photometric_stereo", "euclidean_cluster", "farthest_point_sample",
                                  "remove_ground", "backprojection", "filtered_backprojection", "volume_drr",
                                  "volume_mip"])
def test_second_eager_call_compiles_nothing(name):
    spec = fsjax.get_op(name)
    args = tuple(standard_input(t, i % 2) for i, t in enumerate(spec.takes))
    assert _compiles_on_second_call(spec.fn, *args) == 0
    # and the answer is the one the op gave before (same as a fresh eager call)
    a = jax.tree.leaves(spec.fn(*args))
    b = jax.tree.leaves(spec.fn(*args))
    assert all(bool(jnp.array_equal(u, v, equal_nan=True)) for u, v in zip(a, b))
