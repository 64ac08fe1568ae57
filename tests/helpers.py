"""Shared test helpers: tolerances, tree comparison, standard inputs."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import fsjax
from fsjax.synth import standard_input

# dtype-keyed tolerances (rtol, atol)
TOL = {
    jnp.dtype("float64"): (1e-7, 1e-9),
    jnp.dtype("float32"): (1e-4, 1e-5),
}


def tree_allclose(a, b, rtol=None, atol=None) -> bool:
    """Structure and leaves equal: floats within tolerance (NaN == NaN), others exactly."""
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    if ta != tb:
        return False
    for x, y in zip(la, lb):
        x, y = np.asarray(x), np.asarray(y)
        if x.shape != y.shape:
            return False
        if np.issubdtype(x.dtype, np.inexact):
            r, t = TOL.get(jnp.dtype(x.dtype), (1e-7, 1e-9))
            if not np.allclose(x, y, rtol=rtol or r, atol=atol or t, equal_nan=True):
                return False
        elif not np.array_equal(x, y):
            return False
    return True


def tree_max_diff(a, b) -> float:
    la = jax.tree_util.tree_leaves(a)
    lb = jax.tree_util.tree_leaves(b)
    d = 0.0
    for x, y in zip(la, lb):
        x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        m = np.isfinite(x) & np.isfinite(y)
        if m.any():
            d = max(d, float(np.max(np.abs(x[m] - y[m]))))
    return d


def float_leaves(tree):
    return [x for x in jax.tree_util.tree_leaves(tree) if jnp.issubdtype(jnp.result_type(x), jnp.inexact)]


def inputs_for(spec, variant=0, size=None):
    kw = {} if size is None else {"size": size}
    # the i-th input of a multi-input op uses the next variant, so a two-input op
    # (a metric against a reference, a difference) never compares an image with itself
    return tuple(standard_input(t, (variant + i) % 2, **kw) for i, t in enumerate(spec.takes))


def stack_trees(trees):
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *trees)


def unstack_tree(tree, i):
    return jax.tree_util.tree_map(lambda x: x[i], tree)


__all__ = ["TOL", "tree_allclose", "tree_max_diff", "float_leaves", "inputs_for", "stack_trees",
           "unstack_tree", "fsjax"]


_COMPILE_EVENTS = [0]
_LISTENING: list[bool] = []


def _on_compile_event(name, *_a, **_kw):
    # a backend compile, or a program loaded from the persistent cache: either way the
    # in-memory cache missed and a program was built for this call
    if name in ("/jax/core/compile/backend_compile_duration", "/jax/compilation_cache/cache_hits"):
        _COMPILE_EVENTS[0] += 1


def programs_built(fn):
    """``(result, n)``: ``fn()``'s result and how many programs JAX compiled (or loaded from the
    persistent cache) while it ran. A second call with inputs of the same shapes should build 0."""
    if not _LISTENING:
        jax.monitoring.register_event_duration_secs_listener(_on_compile_event)
        jax.monitoring.register_event_listener(_on_compile_event)
        _LISTENING.append(True)
    n0 = _COMPILE_EVENTS[0]
    out = jax.block_until_ready(fn())
    return out, _COMPILE_EVENTS[0] - n0
