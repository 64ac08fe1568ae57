"""Small dense linear algebra without LAPACK (fsjax/_linalg.py) against numpy's LAPACK,
in float64 and float32, including repeated eigenvalues, singular-adjacent and non-square cases."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import pytest

from fsjax._linalg import SmallQR, eigh_small, lstsq_small, solve_small, solve_spd_eig


def _sym(rng, b, n):
    a = rng.normal(size=(b, n, n))
    return a + np.swapaxes(a, -1, -2)


@pytest.mark.parametrize("dtype,tol", [(jnp.float64, 1e-12), (jnp.float32, 2e-5)])
def test_eigh_small_matches_lapack(dtype, tol):
    rng = np.random.default_rng(0)
    q = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    mats = [_sym(rng, 20, 3), _sym(rng, 10, 4), _sym(rng, 10, 6),
            (q @ np.diag([1.0, 1.0, 2.0]) @ q.T)[None],  # repeated eigenvalue
            np.eye(3)[None], np.zeros((1, 3, 3)), np.diag([3.0, -1.0, 2.0])[None]]  # already diagonal
    worst = 0.0
    for a in mats:
        w, v = eigh_small(jnp.asarray(a, dtype))
        w, v = np.asarray(w, np.float64), np.asarray(v, np.float64)
        scale = max(1.0, np.abs(a).max())
        assert np.all(np.diff(w, axis=-1) >= -tol * scale)  # ascending
        err_w = np.abs(w - np.linalg.eigvalsh(a)).max() / scale
        recon = np.abs(v @ (w[..., None] * np.swapaxes(v, -1, -2)) - a).max() / scale
        orth = np.abs(np.swapaxes(v, -1, -2) @ v - np.eye(a.shape[-1])).max()
        worst = max(worst, err_w, recon, orth)
    print(f"eigh_small ({jnp.dtype(dtype).name}): worst eigenvalue / reconstruction / orthogonality error "
          f"{worst:.1e} (relative to max |a|) over n = 3, 4, 6 incl. repeated and zero eigenvalues")
    assert worst < tol * 10


def test_solvers_match_lapack():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(30, 5, 5)) + 5 * np.eye(5)
    b = rng.normal(size=(30, 5))
    x = np.asarray(solve_small(jnp.asarray(a), jnp.asarray(b)))
    assert np.abs(x - np.linalg.solve(a, b[..., None])[..., 0]).max() < 1e-12
    # partial pivoting: a zero leading entry is handled
    p = np.array([[0.0, 1.0, 2.0], [1.0, 0.0, 3.0], [4.0, 5.0, 0.0]])
    assert np.allclose(np.asarray(solve_small(jnp.asarray(p), jnp.ones(3))), np.linalg.solve(p, np.ones(3)),
                       atol=1e-14)
    spd = a @ np.swapaxes(a, -1, -2)
    w, v = eigh_small(jnp.asarray(spd))
    assert np.abs(np.asarray(solve_spd_eig(w, v, jnp.asarray(b))) - np.linalg.solve(spd, b[..., None])[..., 0]).max() < 1e-10
    m = rng.normal(size=(40, 4))
    y = rng.normal(size=40)
    ref = np.linalg.lstsq(m, y, rcond=None)[0]
    assert np.abs(np.asarray(lstsq_small(jnp.asarray(m), jnp.asarray(y))) - ref).max() < 1e-12
    # as a lineax solver: overdetermined (least squares) and underdetermined (minimum norm), and its transpose
    op = lx.MatrixLinearOperator(jnp.asarray(m))
    assert np.abs(np.asarray(lx.linear_solve(op, jnp.asarray(y), SmallQR()).value) - ref).max() < 1e-12
    opt = lx.MatrixLinearOperator(jnp.asarray(m.T))
    z = rng.normal(size=4)
    assert np.abs(np.asarray(lx.linear_solve(opt, jnp.asarray(z), SmallQR()).value) - np.linalg.pinv(m.T) @ z
                  ).max() < 1e-12
    # differentiable: d/dy of the least-squares solution is pinv(m), finite and non-zero
    g = jax.jacobian(lambda yy: lstsq_small(jnp.asarray(m), yy))(jnp.asarray(y))
    assert np.abs(np.asarray(g) - np.linalg.pinv(m)).max() < 1e-12 and np.abs(np.asarray(g)).max() > 0


def test_jit_fast_compile_options_only_at_top_level():
    """The fits' compile option (``FAST_COMPILE``) goes only to top-level calls: jax refuses
    ``compiler_options`` on a jit nested in another jit (the null below), and the fits are called
    inside users' jit, vmap and grad. Same values every way."""
    from fsjax._linalg import FAST_COMPILE, jit_fast_compile

    def f(x, *, p):
        return jnp.sin(x) * p + jnp.sum(x**2)

    g = jit_fast_compile(f, static_argnames=("p",))
    x = jnp.linspace(0.0, 1.0, 7)
    ref = np.sin(np.linspace(0.0, 1.0, 7)) * 3 + np.sum(np.linspace(0.0, 1.0, 7) ** 2)
    np.testing.assert_allclose(g(x, p=3), ref, rtol=1e-12)   # top level: the fast program
    assert g.fast._cache_size() == 1 and g.plain._cache_size() == 0
    np.testing.assert_allclose(jax.jit(lambda y: g(y, p=3))(x), ref, rtol=1e-12)   # nested: traced plain
    np.testing.assert_allclose(jax.vmap(lambda y: g(y, p=3))(jnp.stack([x, x]))[1], ref, rtol=1e-12)
    gr = jax.grad(lambda y: jnp.sum(g(y, p=3)))(x)
    np.testing.assert_allclose(gr, 3 * np.cos(np.linspace(0.0, 1.0, 7)) + 2 * 7 * np.linspace(0.0, 1.0, 7), rtol=1e-12)
    assert float(jnp.max(jnp.abs(gr))) > 0
    assert g.__wrapped__ is f and g.__name__ == "f"
    bare = jax.jit(f, static_argnames=("p",), compiler_options=FAST_COMPILE)
    with pytest.raises(ValueError, match="compiler_options"):   # the null: options on a nested jit
        jax.jit(lambda y: bare(y, p=3))(x)


def test_filter_jit_fast_compile_mixed_arguments():
    """The filter form: arrays traced, Python values (ints, tuples, strings, bools) static, as
    ``equinox.filter_jit``; the fast program at top level (one per static value), the plain one
    traced under jit and grad. Same values every way."""
    from fsjax._linalg import filter_jit_fast_compile

    def f(x, args, keep, mode="sum"):
        a, (w, h) = args
        y = jnp.sin(x[jnp.asarray(keep)]) * a * w + h
        return jnp.sum(y) if mode == "sum" else y

    g = filter_jit_fast_compile(f)
    x = jnp.linspace(0.0, 1.0, 7)
    xn = np.linspace(0.0, 1.0, 7)
    ref = np.sin(xn[[0, 2, 5]]) * 2.0 * 3 + 4
    np.testing.assert_allclose(g(x, (jnp.asarray(2.0), (3, 4)), (0, 2, 5)), ref.sum(), rtol=1e-12)
    np.testing.assert_allclose(g(x, (jnp.asarray(2.0), (3, 4)), (0, 2, 5), mode="each"), ref, rtol=1e-12)
    assert g.fast._cache_size() == 2   # a program per static value
    np.testing.assert_allclose(jax.jit(lambda y: g(y, (2.0 * jnp.ones(()), (3, 4)), (0, 2, 5)))(x), ref.sum(),
                               rtol=1e-12)
    gr = jax.grad(lambda y: g(y, (jnp.asarray(2.0), (3, 4)), (0, 2, 5)))(x)
    want = np.zeros(7)
    want[[0, 2, 5]] = 6.0 * np.cos(xn[[0, 2, 5]])
    np.testing.assert_allclose(gr, want, rtol=1e-12)
    assert float(jnp.max(jnp.abs(gr))) > 0
    assert g.fast._cache_size() == 2 and g.__name__ == "f"
