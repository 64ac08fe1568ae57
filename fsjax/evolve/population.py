"""Population evaluation: every genome of one skeleton over every image of a split, in one call.

:class:`Evaluator` compiles, once per (skeleton, metric, population size, batch
shape), a function ``(ops (P, S), knobs (P, S, 2), inputs (N, H, W),
targets (N, ...)) -> fitness (P, N)``: each individual runs its pipeline on the
whole batch and the per-image fitness is computed inside the same program.

Design (measured in ``benchmarks/bench_evolve.py``, see
``docs/benchmarks_evolve.md``):

* Each stage is a ``lax.switch`` over the stage's vocabulary; every branch is
  the op ``vmap``-ped over the ``N`` images, with the individual's knobs as
  traced scalars.
* Consecutive stages with the same vocabulary are one ``lax.scan`` over the
  stages, so every op is traced and compiled once per *segment*, not once per
  stage (a 6-stage ``Image -> Image`` skeleton compiles each op once).
* ``mode="map"`` (the default) runs the individuals one after another with
  ``lax.map``: the switch index is then a scalar, and XLA executes only the
  chosen branch. ``mode="vmap"`` batches the individuals with ``jax.vmap``; a
  switch on a batched index becomes a select over *all* branches on the whole
  population, so every stage costs the sum of all the vocabulary's ops. On a
  CPU the map form is the faster one (the images already give each op a
  batch); the benchmark reports both.
* With more than one device (``jax.devices()``), the population axis is split
  across a 1-D mesh with ``jax.shard_map`` (each device maps over its share);
  the population is padded to a multiple of the device count with copies of
  its first genome, and the padding is dropped from the result.

State between stages is one array per sort: ``Image.data`` (float, the
inputs' dtype), ``Region.data`` (bool), ``Feature.value`` (float). Every op
output is checked at trace time to have the stage's sort and the input's shape.
A non-finite fitness (e.g. a NaN from a degenerate op) is replaced by the
metric's floor (:data:`fsjax.evolve.problems.METRIC_FLOOR`), so a broken
individual scores worst, never best.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ..registry import get_op
from ..types import Image, Region
from .genome import IDENTITY, STATE_SORTS, Skeleton

__all__ = ["Evaluator", "run_individual"]


def _branch(name: str, takes: type, gives: type, fdtype) -> Callable:
    """Stage branch ``(x (N, ...), knob (2,)) -> y (N, ...)`` for op ``name``."""
    if name == IDENTITY:
        return lambda x, k: x
    spec = get_op(name)
    field = STATE_SORTS[gives]

    def one(xi, k):
        y = spec.raw(takes(xi), **spec.knob_params(k[0], k[1], strict=False))
        if not isinstance(y, gives):
            raise TypeError(f"evolve: op {name!r} returned {type(y).__name__}, declared {gives.__name__}")
        return getattr(y, field)

    def f(x, k):
        y = jax.vmap(one, in_axes=(0, None))(x, k)
        want = x.shape if gives in (Image, Region) else x.shape[:1]
        if y.shape != want:
            raise ValueError(f"evolve: op {name!r} maps shape {x.shape[1:]} to {y.shape[1:]}; a stage must keep the "
                             f"image shape (leave {name!r} out of the vocabulary)")
        return y.astype(bool) if gives is Region else y.astype(fdtype)

    return f


def run_individual(sk: Skeleton, ops: Any, knobs: Any, x: Any, *, scan: bool = True) -> Any:
    """Run one genome (``ops (S,)``, ``knobs (S, 2)``, traced or not) on a batch state ``x (N, ...)``."""
    fdtype = x.dtype if jnp.issubdtype(x.dtype, jnp.floating) else jnp.result_type(float)
    for a, b in sk.segments():
        branches = [_branch(n, sk.sorts[a], sk.sorts[a + 1], fdtype) for n in sk.vocabs[a]]

        def step(x, g, branches=branches):
            return lax.switch(g[0], branches, x, g[1]), None

        if scan and b - a > 1:
            x, _ = lax.scan(step, x, (ops[a:b], knobs[a:b]))
        else:
            for s in range(a, b):
                x, _ = step(x, (ops[s], knobs[s]))
    return x


class Evaluator:
    """Compiled population fitness for one skeleton and one per-image metric.

    Args:
      sk: the type skeleton.
      metric: per-image fitness ``metric(pred, target) -> scalar`` (higher is better),
        on the final state array of one image (``(H, W)`` or a scalar).
      floor: the fitness given to a non-finite result.
      mode: ``"map"`` (individuals in sequence, one branch executed) or ``"vmap"``
        (individuals batched; the switch evaluates every branch).
      scan: fold runs of same-vocabulary stages into a ``lax.scan`` (compile each op once).
      devices: devices to shard the population over (``None``: all of ``jax.devices()``;
        one device: no sharding).

    Call ``ev(ops, knobs, inputs, targets)`` -> per-image fitness ``(P, N)`` as a NumPy array.
    """

    def __init__(self, sk: Skeleton, metric: Callable, *, floor: float, mode: str = "map", scan: bool = True,
                 devices: list | None = None):
        if mode not in ("map", "vmap"):
            raise ValueError(f"Evaluator: mode must be 'map' or 'vmap', got {mode!r}")
        self.sk, self.metric, self.floor, self.mode, self.scan = sk, metric, float(floor), mode, scan
        self.devices = list(jax.devices() if devices is None else devices)
        self.compile_seconds: dict[tuple, float] = {}  # per call signature, measured apart (AOT)
        self._compiled: dict[tuple, Any] = {}
        self.n_calls = 0
        self.n_evaluations = 0  # genomes evaluated (a genome over a whole split counts once)
        self._fn = self._build()

    # -- the program -------------------------------------------------------
    def _population(self, ops, knobs, inputs, targets):
        sk, metric, floor = self.sk, self.metric, self.floor

        def one(g):
            y = run_individual(sk, g[0], g[1], inputs, scan=self.scan)
            f = jax.vmap(metric)(y, targets)
            return jnp.where(jnp.isfinite(f), f, jnp.asarray(floor, f.dtype))

        if self.mode == "map":
            return lax.map(one, (ops, knobs))
        return jax.vmap(one)((ops, knobs))

    def _build(self):
        if len(self.devices) <= 1:
            return jax.jit(self._population)
        mesh = Mesh(np.asarray(self.devices), ("pop",))
        pop, rep = PartitionSpec("pop"), PartitionSpec()
        sharded = jax.shard_map(self._population, mesh=mesh, in_specs=(pop, pop, rep, rep), out_specs=pop,
                                check_vma=False)
        self._mesh = mesh
        return jax.jit(sharded, in_shardings=(NamedSharding(mesh, pop), NamedSharding(mesh, pop),
                                              NamedSharding(mesh, rep), NamedSharding(mesh, rep)),
                       out_shardings=NamedSharding(mesh, pop))

    def _prepare(self, ops, knobs, inputs, targets):
        ops = np.asarray(ops, dtype=np.int32)
        P, S = ops.shape
        if S != self.sk.n_stages:
            raise ValueError(f"Evaluator: genomes have {S} stages, the skeleton {self.sk.n_stages}")
        if np.any(ops < 0) or np.any(ops >= self.sk.sizes[None, :]):
            raise ValueError("Evaluator: op index outside its stage's vocabulary")
        inputs = jnp.asarray(inputs)
        knobs = np.asarray(knobs, dtype=inputs.dtype if jnp.issubdtype(inputs.dtype, jnp.floating) else float)
        if knobs.shape != (P, S, 2):
            raise ValueError(f"Evaluator: knobs must have shape {(P, S, 2)}, got {knobs.shape}")
        if np.any(~np.isfinite(knobs)) or np.any((knobs < 0) | (knobs > 1)):
            raise ValueError("Evaluator: knobs must be finite and in [0, 1]")
        pad = (-P) % max(len(self.devices), 1)
        if pad:
            ops = np.concatenate([ops, np.repeat(ops[:1], pad, 0)])
            knobs = np.concatenate([knobs, np.repeat(knobs[:1], pad, 0)])
        return jnp.asarray(ops), jnp.asarray(knobs), inputs, jnp.asarray(targets), P

    def lower(self, ops, knobs, inputs, targets):
        """The lowered program for these shapes (``.compile()`` it to time compilation)."""
        o, k, x, t, _ = self._prepare(ops, knobs, inputs, targets)
        return self._fn.lower(o, k, x, t)

    def compiled(self, ops, knobs, inputs, targets):
        """The compiled executable for these shapes (compiled ahead of time on first use and cached)."""
        o, k, x, t, _ = self._prepare(ops, knobs, inputs, targets)
        return self._get(o, k, x, t)

    def _get(self, o, k, x, t):
        key = tuple((a.shape, str(a.dtype)) for a in (o, k, x, t))
        if key not in self._compiled:
            t0 = time.perf_counter()
            self._compiled[key] = self._fn.lower(o, k, x, t).compile()
            self.compile_seconds[key] = time.perf_counter() - t0
        return self._compiled[key]

    def __call__(self, ops, knobs, inputs, targets) -> np.ndarray:
        o, k, x, t, P = self._prepare(ops, knobs, inputs, targets)
        out = np.asarray(self._get(o, k, x, t)(o, k, x, t))[:P]
        self.n_calls += 1
        self.n_evaluations += P
        return out
