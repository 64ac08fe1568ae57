"""Small dense linear algebra in plain ``jax.numpy`` (no LAPACK custom calls).

Why this exists: jaxlib 0.10's CPU LAPACK kernels (``eigh``, ``solve``/LU, QR,
Cholesky, triangular solve, ...) split a *batched* call across XLA:CPU's intra-op
thread pool and then block the calling thread until the pieces are done. The
call itself runs on a thread of that same pool, so when as many batched LAPACK
calls as the pool has threads run at once (independent calls in one program;
``vmap`` makes every call batched), every pool thread waits for work that no
thread is left to run: the process hangs with all threads idle
(tools/repro_xla_hang.py reproduces it in ~20 lines of pure JAX). The 3-D
primitive fits and :func:`fsjax.fit.select_model` work on 3x3 to 7x7 matrices,
where a few Jacobi rotations or an unrolled elimination cost less than the
custom call; writing them here keeps those fits free of LAPACK, so they cannot
hang under ``vmap`` whatever jaxlib does. It sits in the bottom layer (imports nothing of
fsjax) because ops (photometric stereo) and fits both use it.

All functions take leading batch dimensions (``(..., n, n)``), are
differentiable, and have a static size ``n`` (the matrices are tiny: ``n <= 8``
is what they are written for; the loops over ``n`` are unrolled).

References: G. H. Golub, C. F. Van Loan, *Matrix Computations*, 4th ed., Johns
Hopkins 2013: the symmetric Schur decomposition by cyclic Jacobi (Alg. 8.5.2 and
8.5.3), Gaussian elimination with partial pivoting (Alg. 3.4.1), Householder QR and
least squares (Alg. 5.2.1, 5.3.2).
"""

from __future__ import annotations

import functools
from typing import Any

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from lineax._solver.misc import (  # the helpers lineax's own dense solvers use
    pack_structures,
    ravel_vector,
    transpose_packed_structures,
    unravel_solution,
)

__all__ = ["eigh_small", "solve_spd_eig", "solve_small", "lstsq_small", "SmallQR", "levenberg_marquardt",
           "quat_to_rotmat", "jit_fast_compile"]

# XLA:CPU compiles the same HLO 30-45 % faster with its older loop emitters than with its MLIR
# fusion emitters (the default). For the small fits below, which compile for seconds and run in
# milliseconds, that is most of a first call. Measured in one process each way, float32, load
# ~12, CPU seconds (python benchmarks/bench_fast_compile.py): fit_ellipse 5.60 -> 3.14 s,
# fit_circle 2.43 -> 1.86, fit_cylinder 5.16 -> 2.91, select_model 8.18 -> 5.91; run times equal
# within noise; results bit-identical or within float32 rounding. ICP's program too (fsjax.fit.icp,
# 20,000 points: compile 4.7 -> 2.7 s point-to-plane float32, run 10-18 % less CPU; python
# benchmarks/compile_knn.py --ab; the per-program level 2 overrides a level 0 in XLA_FLAGS, shown by
# benchmarks/icp_trajectory.py under it). Not used on image filters,
# where the default emitters run up to 3x faster (a 1024^2 Gaussian 2.35 vs 6.67 ms).
# The optimisation level is pinned to XLA's default (2): the older emitters at level 0 (which a
# user or a test suite may set in XLA_FLAGS) miscompile (tools/repro_xla_emitters_level0.py).
FAST_COMPILE = {"xla_cpu_use_fusion_emitters": False, "xla_backend_optimization_level": 2}


def _has_tracer(tree) -> bool:
    """True when a leaf of ``tree`` is a tracer (the call is inside a user's jit, vmap or grad)."""
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(tree))


def jit_fast_compile(fun=None, /, **jit_kwargs):
    """``jax.jit(fun, **jit_kwargs)`` compiled with :data:`FAST_COMPILE` when called at top level.

    jax refuses ``compiler_options`` on a jit nested in another jit (the fits are called inside
    users' ``jit``, ``vmap`` and ``grad``), so the wrapper keeps two jitted functions and calls
    the one with the options only when no argument is a tracer; under a transformation the plain
    one is traced into the enclosing program, whose options apply. Usable as a decorator, with
    or without keyword arguments.
    """
    if fun is None:
        return functools.partial(jit_fast_compile, **jit_kwargs)
    plain = jax.jit(fun, **jit_kwargs)
    fast = jax.jit(fun, compiler_options=FAST_COMPILE, **jit_kwargs)

    @functools.wraps(fun)
    def call(*args, **kwargs):
        return (plain if _has_tracer((args, kwargs)) else fast)(*args, **kwargs)

    call.fast, call.plain = fast, plain   # the two jitted functions (introspection, tests)
    return call


def filter_jit_fast_compile(fun):
    """:func:`jit_fast_compile` for functions whose arguments mix arrays with Python values (as
    ``equinox.filter_jit``): the arrays are traced, every other leaf (ints, floats, strings,
    tuples of them) is static. At top level compiled with :data:`FAST_COMPILE`; with a tracer
    among the arguments ``equinox.filter_jit``'s program, traced into the enclosing one."""
    import equinox as eqx

    plain = eqx.filter_jit(fun)

    @functools.partial(jax.jit, static_argnums=(1, 2), compiler_options=FAST_COMPILE)
    def fast(dynamic, static_leaves, static_def):
        args, kwargs = eqx.combine(dynamic, jax.tree_util.tree_unflatten(static_def, static_leaves))
        return fun(*args, **kwargs)

    @functools.wraps(fun)
    def call(*args, **kwargs):
        if _has_tracer((args, kwargs)):
            return plain(*args, **kwargs)
        dynamic, static = eqx.partition((args, kwargs), eqx.is_array)
        static_leaves, static_def = jax.tree_util.tree_flatten(static)
        return fast(dynamic, tuple(static_leaves), static_def)

    call.fast, call.plain = fast, plain
    return call


def _sweeps(n: int) -> int:
    # cyclic Jacobi converges quadratically; 6 sweeps reach float64 round-off for n <= 4, 10 for n <= 8
    return 6 if n <= 4 else 10


def eigh_small(a, *, sweeps: int | None = None):
    """Eigen-decomposition of symmetric ``a`` ``(..., n, n)`` by cyclic Jacobi rotations.

    Returns ``(w (..., n) ascending, v (..., n, n))`` with ``a = v diag(w) v^T``
    (columns of ``v`` are the eigenvectors), like ``jnp.linalg.eigh``. Only the
    symmetric part of ``a`` is used. One rotation per loop step (a ``fori_loop``
    over sweeps x pairs, the pair picked by one-hot masks), so the program stays
    small whatever ``n``.
    """
    a = jnp.asarray(a)
    a = 0.5 * (a + jnp.swapaxes(a, -1, -2))
    n = a.shape[-1]
    v = jnp.broadcast_to(jnp.eye(n, dtype=a.dtype), a.shape)
    if n == 1:
        return a[..., 0], v
    pairs = jnp.array([(p, q) for p in range(n - 1) for q in range(p + 1, n)], jnp.int32)
    idx = jnp.arange(n)

    def rotate(i, av):
        a, v = av
        pq = pairs[i % pairs.shape[0]]
        ep, eq = (idx == pq[0]).astype(a.dtype), (idx == pq[1]).astype(a.dtype)
        cp, cq = jnp.sum(a * ep, -1), jnp.sum(a * eq, -1)  # columns p, q
        app, aqq, apq = jnp.sum(cp * ep, -1), jnp.sum(cq * eq, -1), jnp.sum(cq * ep, -1)
        nz = apq != 0
        tau = (aqq - app) / (2 * jnp.where(nz, apq, 1.0))
        t = jnp.where(tau >= 0, 1.0, -1.0) / (jnp.abs(tau) + jnp.sqrt(1 + tau * tau))
        t = jnp.where(nz, t, 0.0)
        c = (1 / jnp.sqrt(1 + t * t))[..., None]
        s = t[..., None] * c
        # A <- J^T A J, J the rotation in the (p, q) plane: columns, then rows; V <- V J
        a = a + (c * cp - s * cq - cp)[..., :, None] * ep + (s * cp + c * cq - cq)[..., :, None] * eq
        rp, rq = jnp.sum(a * ep[:, None], -2), jnp.sum(a * eq[:, None], -2)
        a = a + ep[:, None] * (c * rp - s * rq - rp)[..., None, :] + eq[:, None] * (s * rp + c * rq - rq)[..., None, :]
        vp, vq = jnp.sum(v * ep, -1), jnp.sum(v * eq, -1)
        v = v + (c * vp - s * vq - vp)[..., :, None] * ep + (s * vp + c * vq - vq)[..., :, None] * eq
        return a, v

    steps = (_sweeps(n) if sweeps is None else sweeps) * pairs.shape[0]
    a, v = jax.lax.fori_loop(0, steps, rotate, (a, v))
    w = jnp.diagonal(a, axis1=-2, axis2=-1)
    order = jnp.argsort(w, axis=-1)
    w = jnp.take_along_axis(w, order, axis=-1)
    v = jnp.take_along_axis(v, order[..., None, :], axis=-1)
    return w, v


def solve_spd_eig(w, v, b):
    """Solve ``a x = b`` given ``a = v diag(w) v^T`` (from :func:`eigh_small`); ``w <= 0`` gives non-finite x."""
    y = jnp.einsum("...ji,...j->...i", v, b)
    return jnp.einsum("...ij,...j->...i", v, y / w)


def solve_small(a, b):
    """Solve ``a x = b`` for square ``a`` ``(..., n, n)`` and ``b`` ``(..., n)``.

    Gaussian elimination with partial pivoting, unrolled over ``n``. A singular
    ``a`` gives non-finite entries (as LAPACK's ``gesv`` result would be unusable
    too); callers guard the matrix beforehand.
    """
    a, b = jnp.asarray(a), jnp.asarray(b)
    n = a.shape[-1]
    m = jnp.concatenate([a, b[..., None]], axis=-1)  # augmented (..., n, n + 1)
    rows = jnp.arange(n)
    for k in range(n):
        col = jnp.where(rows >= k, jnp.abs(m[..., :, k]), -1.0)
        piv = jnp.argmax(col, axis=-1)
        rk = m[..., k, :]
        rp = jnp.take_along_axis(m, piv[..., None, None], axis=-2)[..., 0, :]
        sel = (rows == piv[..., None])[..., None]
        m = jnp.where(sel, rk[..., None, :], m)  # row piv <- row k
        m = m.at[..., k, :].set(rp)  # row k <- old row piv
        pivot = m[..., k, k]
        f = jnp.where(rows > k, m[..., :, k] / pivot[..., None], 0.0)
        m = m - f[..., :, None] * m[..., k, :][..., None, :]
    x = [None] * n
    for k in range(n - 1, -1, -1):
        s = m[..., k, n]
        for j in range(k + 1, n):
            s = s - m[..., k, j] * x[j]
        x[k] = s / m[..., k, k]
    return jnp.stack(x, axis=-1)


def _householder_qr(a):
    """Thin QR of ``a`` ``(m, n)``, ``m >= n``: ``(q (m, n), r (n, n))``; one reflector per loop step."""
    m, n = a.shape
    rows = jnp.arange(m)
    cols = jnp.arange(n)

    def reflect(k, rh):
        r, h = rh
        x = jnp.where(rows >= k, jnp.sum(r * (cols == k), -1), 0.0)
        xk = jnp.sum(jnp.where(rows == k, x, 0.0))
        alpha = -jnp.where(xk >= 0, 1.0, -1.0) * jnp.sqrt(jnp.sum(x * x))
        u = x - jnp.where(rows == k, alpha, 0.0)
        un = jnp.sum(u * u)
        ok = un > 0
        u = jnp.where(ok, u / jnp.sqrt(jnp.where(ok, un, 1.0)), 0.0)
        return r - 2 * jnp.outer(u, u @ r), h.at[k].set(u)

    r, h = jax.lax.fori_loop(0, n, reflect, (a, jnp.zeros((n, m), a.dtype)))

    def accumulate(j, q):
        u = h[n - 1 - j]
        return q - 2 * jnp.outer(u, u @ q)

    q = jax.lax.fori_loop(0, n, accumulate, jnp.eye(m, n, dtype=a.dtype))
    return q, jnp.triu(r[:n])


def _back(r, y):
    """Solve ``r x = y`` (``r`` upper triangular ``(n, n)``)."""
    n = r.shape[-1]

    def step(j, x):
        k = n - 1 - j
        return x.at[k].set((y[k] - r[k] @ x) / r[k, k])  # x[j] is still 0 for j <= k

    return jax.lax.fori_loop(0, n, step, jnp.zeros_like(y))


def _forward_t(r, y):
    """Solve ``r^T z = y`` (``r`` upper triangular)."""
    n = r.shape[-1]

    def step(k, z):
        return z.at[k].set((y[k] - r[:, k] @ z) / r[k, k])  # z[j] is still 0 for j >= k

    return jax.lax.fori_loop(0, n, step, jnp.zeros_like(y))


def lstsq_small(a, b):
    """Least-squares solution of ``a x ~ b`` for full-rank ``a`` ``(m, n)``, ``m >= n``, by Householder QR."""
    q, r = _householder_qr(jnp.asarray(a))
    return _back(r, q.T @ jnp.asarray(b))


class SmallQR(lx.AbstractLinearSolver):
    """A ``lineax`` solver like ``lineax.QR`` (full-rank, non-square allowed) in plain ``jax.numpy``.

    For the few-parameter Levenberg-Marquardt solves of the 3-D fits (see the
    module docstring for why no LAPACK). Overdetermined: least squares;
    underdetermined: minimum norm. Unrolled over the smaller dimension, so only for
    small operators.
    """

    def init(self, operator, options):
        del options
        matrix = operator.as_matrix()
        m, n = matrix.shape
        transpose = n > m
        q, r = _householder_qr(matrix.T if transpose else matrix)
        return (q, r), eqxi.Static(transpose), pack_structures(operator)

    def compute(self, state, vector, options: dict[str, Any]):
        del options
        (q, r), transpose, packed = state
        b = ravel_vector(vector, packed)
        if transpose.value:  # minimum norm: A = R^T Q^T, x = Q R^{-T} b
            x = q @ _forward_t(r, b)
        else:
            x = _back(r, q.T @ b)
        return unravel_solution(x, packed), lx.RESULTS.successful, {}

    def transpose(self, state, options: dict[str, Any]):
        (q, r), transpose, packed = state
        return ((q, r), eqxi.Static(not transpose.value), transpose_packed_structures(packed)), {}

    def conj(self, state, options: dict[str, Any]):
        (q, r), transpose, packed = state
        return ((q.conj(), r.conj()), transpose, packed), {}

    def assume_full_rank(self):
        return True


class _TrustRegionInDtype(optx.ClassicalTrustRegion):
    """optimistix's trust region with its step size in the dtype of ``y``.

    The stock one starts from ``jnp.array(1.0)``: float64 whenever x64 is on, which makes
    Levenberg-Marquardt's damping rows float64 beside float32 residuals, and lineax then
    refuses the solve with a raw ``ValueError`` ("Vector and operator structures do not
    match") for float32 data.
    """

    def init(self, y, f_info_struct):
        state = super().init(y, f_info_struct)
        dt = jnp.result_type(*jax.tree_util.tree_leaves(y))
        return eqx.tree_at(lambda s: s.step_size, state, state.step_size.astype(dt))


def _lm_progress(**kw):
    """Progress line of a Levenberg-Marquardt step (optimistix's ``verbose`` callable; the
    parameter vectors it also offers are left out)."""
    jax.debug.print("  LM step {}: loss {} (last accepted {}), step size {}", kw["num_steps"][1],
                    kw["loss_this_step"][1], kw["loss_last_accepted_step"][1], kw["step_size"][1])


def levenberg_marquardt(rtol, atol, *, linear_solver=None, verbose=False):
    """``optimistix.LevenbergMarquardt`` that keeps the dtype of its parameters.

    Float32 data stays float32 whether or not x64 is enabled (the stock solver fails on
    float32 parameters with x64 on; see :class:`_TrustRegionInDtype`). Every
    Levenberg-Marquardt fit of the library builds its solver here.
    """
    kw = {} if linear_solver is None else {"linear_solver": linear_solver}
    if verbose:  # one line per step (loss, step size) from inside the compiled solve
        kw["verbose"] = _lm_progress
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol, **kw)
    return eqx.tree_at(lambda s: s.search, solver, _TrustRegionInDtype())


def quat_to_rotmat(q):
    """Rotation matrix of a unit quaternion ``(w, x, y, z)`` (Hamilton, active), batched over leading axes."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return jnp.stack([
        jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)
