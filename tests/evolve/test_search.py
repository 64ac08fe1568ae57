"""The GA: determinism under a key, selection blind to the held-out split, operators, refinement."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

from fsjax.evolve import genome as G
from fsjax.evolve.population import Evaluator
from fsjax.evolve.problems import Split, make_problem
from fsjax.evolve.search import GAConfig, evolve, next_generation, random_search, refine

V = ["gaussian", "box_filter", "invert", "gamma", "threshold", "otsu", "region_open", "region_not"]
CFG = GAConfig(pop=8, gens=4, elite=1)


@pytest.fixture(scope="module")
def case():
    pr = make_problem("binarize", size=(24, 24), n_train=3, n_holdout=2, n_locked=5, n_stages=3)
    sk = pr.skeleton(V)
    return pr, sk, Evaluator(sk, pr.metric_fn, floor=pr.floor)


def _trajectory(r):
    return [(g.best_train, g.mean_train) for g in r.log]


def test_ga_is_deterministic_under_a_key(case):
    pr, sk, ev = case
    a = evolve(jax.random.key(5), pr, sk, ev, CFG, progress=False, dtype=np.float64)
    b = evolve(jax.random.key(5), pr, sk, ev, CFG, progress=False, dtype=np.float64)
    c = evolve(jax.random.key(6), pr, sk, ev, CFG, progress=False, dtype=np.float64)
    assert a.log == [dataclasses.replace(g, seconds=h.seconds) for g, h in zip(b.log, a.log)]
    np.testing.assert_array_equal(a.ops, b.ops)
    np.testing.assert_array_equal(a.knobs, b.knobs)
    assert _trajectory(a) != _trajectory(c) or not np.array_equal(a.knobs, c.knobs)
    best = [g.best_train for g in a.log]
    print(f"GA binarize 24x24, pop 8 x 4 gens: best train IoU per generation {np.round(best, 4).tolist()}")
    assert best == sorted(best)  # elitism: the best never gets worse
    assert a.train == pytest.approx(max(best)) and a.evaluations == CFG.pop * CFG.gens


def test_selection_never_reads_the_held_out_split(case):
    pr, sk, ev = case
    rng = np.random.default_rng(1)
    poisoned = dataclasses.replace(pr, holdout=Split(rng.uniform(size=pr.holdout.inputs.shape),
                                                     ~pr.holdout.targets))
    a = evolve(jax.random.key(2), pr, sk, ev, CFG, progress=False, dtype=np.float64)
    b = evolve(jax.random.key(2), poisoned, sk, ev, CFG, progress=False, dtype=np.float64)
    ha, hb = [g.holdout_of_best for g in a.log], [g.holdout_of_best for g in b.log]
    print(f"held-out poisoned: tracked held-out IoU {np.round(ha, 3).tolist()} -> {np.round(hb, 3).tolist()}; "
          f"train trajectory unchanged")
    assert ha != hb  # the poison reaches the log ...
    assert _trajectory(a) == _trajectory(b)  # ... but not selection
    np.testing.assert_array_equal(a.ops, b.ops)
    np.testing.assert_array_equal(a.knobs, b.knobs)
    # and the converse: poisoning one train image changes the run
    tr = pr.train.targets.copy()
    tr[0] = ~tr[0]
    c = evolve(jax.random.key(2), dataclasses.replace(pr, train=Split(pr.train.inputs, tr)), sk, ev, CFG,
               progress=False, dtype=np.float64)
    assert _trajectory(c) != _trajectory(a)


def test_operators_preserve_types_and_elites(case):
    _, sk, _ = case
    rng = np.random.default_rng(0)
    ops, knobs = G.random_population(rng, sk, 16)
    fit = rng.uniform(size=16)
    cfg = GAConfig(pop=16, gens=2, elite=3, p_op=0.9, p_knob=0.9, knob_sigma=0.5)
    o2, k2 = next_generation(rng, sk, ops, knobs, fit, cfg)
    assert o2.shape == ops.shape and k2.shape == knobs.shape
    assert np.all((o2 >= 0) & (o2 < sk.sizes[None])) and np.all((k2 >= 0) & (k2 <= 1))
    top = np.argsort(-fit)[:3]
    np.testing.assert_array_equal(o2[:3], ops[top])
    assert not np.array_equal(o2[3:], ops[3:])  # mutation acted
    for o, k in zip(o2, k2):  # every child decodes to a type-correct pipeline
        import fsjax

        stages = G.pipeline_stages(G.decode(sk, o, k))
        if stages:
            p = fsjax.pipeline(stages)
            assert p.gives in (fsjax.Region, fsjax.Image)


def test_random_search_and_refinement_use_train_only(case):
    pr, sk, ev = case
    rs = random_search(jax.random.key(0), pr, sk, ev, 20, batch=8, dtype=np.float64)
    assert rs.evaluations == 20 and np.isfinite(rs.train)
    rf = refine(jax.random.key(1), pr, sk, ev, rs.ops, rs.knobs, steps=6, pop=8, dtype=np.float64)
    print(f"local-search refinement (IoU, not differentiable): train {rf.train_before:.4f} -> {rf.train_after:.4f}")
    assert rf.method == "local" and rf.train_after >= rf.train_before


def test_gradient_refinement_on_a_differentiable_champion():
    pr = make_problem("denoise", size=(24, 24), n_train=3, n_holdout=1, n_locked=4, n_stages=2)
    sk = pr.skeleton(["gaussian", "gamma"])
    ev = Evaluator(sk, pr.metric_fn, floor=pr.floor)
    ops = np.array([sk.vocabs[0].index("gaussian"), 0], np.int32)
    knobs = np.array([[0.05, 0.5], [0.5, 0.5]])  # sigma far too small
    rf = refine(jax.random.key(0), pr, sk, ev, ops, knobs, steps=15, pop=4, dtype=np.float64)
    print(f"gradient refinement of gaussian sigma: train PSNR {rf.train_before:.3f} -> {rf.train_after:.3f} dB, "
          f"knob a {knobs[0, 0]} -> {rf.knobs[0, 0]:.3f}")
    assert rf.method == "grad" and rf.train_after > rf.train_before + 0.1 and rf.knobs[0, 0] > knobs[0, 0]
