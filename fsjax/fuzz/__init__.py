"""The chain fuzzer: random typed pipelines over the registry, run four ways, nothing silent.

Users build chains of ops; each op is tested alone elsewhere. The fuzzer draws random
chains that are type-correct by construction (the registry's sort graph; the sorts
reachable from the input pool are a fixed point), with random knobs and, for boolean
named parameters, random legal values, on a pool of inputs of several sizes and dtypes
(the standard scene of :func:`fsjax.synth.standard_input`, a real photograph from
``skimage.data``, a constant image, 1 x 1, 3 x 5, very large values, a single bright
pixel; an all-NaN image must be refused at the door). Each chain runs eagerly, under
``jit``, under ``vmap`` over a batch of two, and, when every stage is declared
differentiable, under ``grad`` of a scalar of its output.

What "under jit" means. Compilation is what a chain costs, so the traced ways run
**stage by stage through compiled programs that repeat across chains**:

* every stage is one ``jit(vmap(stage))`` program over the batch ``[x, x2]`` (member 0 must
  equal the eager result), cached per (op, input slot, non-knob parameters, which knobs are
  given, dtype, input shapes/dtypes/tree structure): knob *values* are traced arguments, so
  the same op meeting the same shapes again reuses its program. The running batch of one
  stage's program feeds the next stage's program. Plain ``jit(stage)`` is compiled only to
  say which way broke (jit or vmap);
* ``grad`` is the chain rule stage by stage: each stage's cached ``jit(vjp(stage))`` at the
  eager inputs pulls the cotangent back; the first stage turning a finite cotangent into a
  NaN is blamed;
* RECOMPILE: a cached program that compiles again when called with the shapes it was built
  for; a new program is called a second time (batch reversed: a member's answer must not
  depend on its position); an eager stage is called a second time the first time its (op,
  knob values, parameters, input shapes) is seen in a run;
* the chain compiled **whole** (``jit(vmap(chain))``, ``jit(chain)`` to attribute, and
  ``jit(value_and_grad)`` of the chain, as before) runs for the fraction
  ``whole_chain_fraction`` of chains (:func:`fuzz`, default 0.05, drawn from ``(seed,
  index)``) and for every replayed chain. Only those chains test what XLA does *across*
  stages (fusion, simplification of one op's output by the next).

How chains are drawn so that compiled programs repeat (the cost of a chain is compiling):

* a **coverage phase**: while some drawable op has not been drawn, an op not drawn yet is
  drawn first (weight 1 against ``COVERAGE_USED_WEIGHT / (1 + uses)^2``), on inputs of the
  canonical size 16 x 16 (both dtypes, every kind of content); about 110 chains cover the
  registry's ~228 ops;
* then a **reuse phase**, drawing **with replacement**: with probability ``PREFIX_REUSE``
  (0.6) a chain starts from an earlier chain's input and a prefix of its stages, knob values
  included (a prefix that was refused or failed is cut before the stage that stopped it), and
  is extended with new stages; each stage is drawn in two levels: with probability
  ``NEW_COMBO_RATE`` (0.05) among the (op, running sort, size, dtype) combinations not drawn
  before, else among those drawn before, whose knob values and parameters it takes again with
  the same probability (a knob that sizes an array gives the shapes every later program depends
  on); inputs leave the canonical size at that rate too (``NEW_COMBO_RATE = None``: the old
  one-level weighting, a drawn combination ``SEEN_WEIGHT`` (4) times an unseen one);
* an exact repeat of a chain drawn before in the run (the same input, stages, knob values and
  parameters) is drawn again (up to ``REPEAT_REDRAWS`` times): it would test nothing new;
* ``workers`` processes (``fsjax fuzz --workers``, default ``min(2, CPU count)``) run the
  chains side by side, each covering every ``W``-th op first; ``coverage_share`` (a bounded
  run) covers a seeded share of the ops first. A worker compiles **every** program at XLA's
  backend (LLVM) optimisation level 0 (``WORKER_XLA_FLAGS`` in its environment), the eager
  way's op-by-op primitives and the ops' own jit programs included: cold, the eager way is
  over half of a chain's CPU, nearly all compiling. What is not exercised there is LLVM's
  optimised code of the ops' programs; the chains compiled whole keep XLA's default level
  (explicitly). An in-process run (``workers=1``) leaves the process's XLA flags alone;
* the pool's sizes: the canonical 16 x 16, the odd 15 x 17 for 15 % of scene/raster inputs,
  and the edge inputs 1 x 1 and 3 x 5 (rarer than before);
* the runner keeps the **eager results and stage-program batches of every chain prefix that
  passed** every check, keyed by (input, stages so far): a chain extending that prefix takes
  them instead of running those stages again; the stage after the prefix, the grad way (its
  cotangent comes from the chain's end) and the chain compiled whole always run;
* ``fsjax fuzz`` switches on JAX's persistent compile cache (``--compile-cache DIR``,
  default :func:`fsjax.enable_compile_cache`'s directory, ``off`` disables); the report
  states whether it was warm (held programs at the start) or cold.

Knob values are drawn on a grid of ``1 / KNOB_STEPS`` (concrete values that size kernels
compile the eager primitives again). Every failure lands in exactly one class with a
signature that groups duplicates:

``CONTRACT``  a declared sort, batch shape or dtype not kept (or an all-NaN input accepted)
``SUSPECT``   a raw exception that is not fsjax's own clear error (``IndexError``, an XLA
              error, a tracer-conversion error)
``TYPEMISS``  the pipeline checker refused a type-correct chain, or an op refused a sort
              the checker accepted
``NONFINITE`` NaN/inf from finite input not explained by a flag (``converged``/``found``
              False, ``truncated`` True, a ``valid`` mask or a record's scalar ``valid`` False,
              a NaN ``Feature`` = "could not measure")
``MISMATCH``  eager, ``jit`` and ``vmap`` disagree beyond the stated tolerance
``GRADNAN``   finite forward, NaN gradient
``RECOMPILE`` a second call with the same shapes compiles again (eager op-by-op, a stage
              program, or the chain compiled whole)
``GROWTH``    output more than 64 x the input's bytes (+1 MiB)
``SILENT_OVERFLOW`` a truncated input whose flag is not passed on, or, for an op with a
              ``capacity`` (drawn small now and then), fewer items kept than the same call at
              the default capacity finds, with ``truncated`` unset

An op's clear refusal (a ``ValueError``/``TypeError`` whose message names the op) is not a
failure: the chain is cut there, counted as refused, and its prefix still runs the other ways.

Usage::

    run = fsjax.fuzz.fuzz(200, max_length=6, seed=0)
    fsjax.fuzz.write_report(run, "fuzz-out")       # report.md, failures.jsonl, minimised.jsonl
    fsjax.fuzz.replay("fuzz-out/minimised.jsonl")

or ``fsjax fuzz --chains 200 --length 6 --seed 0 --out DIR`` and
``fsjax fuzz --replay DIR/minimised.jsonl``.
"""

from ._gen import Chain as Chain
from ._gen import SortGraph as SortGraph
from ._gen import Stage as Stage
from ._gen import build_input as build_input
from ._gen import generate_chain as generate_chain
from ._report import BLOCKING as BLOCKING
from ._report import FuzzRun as FuzzRun
from ._report import fuzz as fuzz
from ._report import load_journal as load_journal
from ._report import minimise as minimise
from ._report import pool_sorts as pool_sorts
from ._report import replay as replay
from ._report import temporary_ops as temporary_ops
from ._report import write_report as write_report
from ._run import CLASSES as CLASSES
from ._run import Outcome as Outcome
from ._run import Runner as Runner

__all__ = ["BLOCKING", "CLASSES", "Chain", "FuzzRun", "Outcome", "Runner", "SortGraph", "Stage", "build_input",
           "fuzz", "generate_chain", "load_journal", "minimise", "pool_sorts", "replay", "temporary_ops", "write_report"]
