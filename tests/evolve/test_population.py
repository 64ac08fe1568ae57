"""Genomes, skeletons from the registry, and the one-call population evaluation.

The population call must equal, value for value, the per-individual evaluation
through the public :func:`fsjax.pipeline` for every member.
"""

from __future__ import annotations

import numpy as np
import pytest

import fsjax
from fsjax import Feature, Image, Region
from fsjax.evolve import genome as G
from fsjax.evolve.baselines import score_pipeline
from fsjax.evolve.population import Evaluator
from fsjax.evolve.problems import make_problem
from fsjax.evolve.search import search_batch

V = ["gaussian", "box_filter", "invert", "gamma", "threshold", "otsu", "region_open", "region_not", "count_obj"]


def test_stage_vocabulary_is_derived_from_the_registry():
    all_ii = [s.name for s in fsjax.list_ops(takes=Image, gives=Image)]
    v = G.stage_vocabulary(Image, Image, all_ii)
    assert v[0] == G.IDENTITY and list(v[1:]) == sorted(all_ii)
    # a sort change has no identity; ops of other signatures never enter
    v2 = G.stage_vocabulary(Image, Region, V)
    assert v2 == ("otsu", "threshold")
    assert G.stage_vocabulary(Region, Feature, V) == ("count_obj",)
    # the default vocabulary: every name is registered with a state-sort signature, and
    # a stage's vocabulary only holds ops of exactly that signature
    for name in G.DEFAULT_VOCABULARY:
        s = fsjax.get_op(name)
        assert s.linear and s.takes[0] in G.STATE_SORTS and s.gives in G.STATE_SORTS
    sk = G.type_skeleton([Image, Image, Region, Region, Feature])
    for s, voc in enumerate(sk.vocabs):
        for name in voc:
            if name != G.IDENTITY:
                assert fsjax.get_op(name).takes == (sk.sorts[s],) and fsjax.get_op(name).gives is sk.sorts[s + 1]
    print(f"default vocabulary sizes per stage (I->I, I->R, R->R, R->F): {sk.sizes.tolist()}")


def test_empty_vocabulary_and_bad_skeletons_raise():
    with pytest.raises(ValueError, match=r"stage 2 \(Image -> Region\).*empty vocabulary"):
        G.type_skeleton([Image, Image, Region], vocabulary=["gaussian"])
    with pytest.raises(ValueError, match="at least 2 sorts"):
        G.type_skeleton([Image])
    with pytest.raises(ValueError, match="cannot be a stage state"):
        G.type_skeleton([Image, fsjax.Labels])
    with pytest.raises(KeyError, match="unknown op"):
        G.type_skeleton([Image, Image], vocabulary=["gausian"])
    sks = G.enumerate_skeletons(Image, Region, 3, V)
    assert {sk.describe() for sk in sks} == {"Image -> Image -> Image -> Region", "Image -> Image -> Region -> Region",
                                             "Image -> Region -> Region -> Region"}


def test_champion_stored_by_name_survives_a_vocabulary_change():
    sk = G.type_skeleton([Image, Image, Image, Region], V)
    rng = np.random.default_rng(3)
    ops, knobs = G.random_population(rng, sk, 5)
    for o, k in zip(ops, knobs):
        rec = G.champion_record(sk, o, k)
        # a bigger vocabulary shifts indices; the record decodes to the same ops and parameters
        sk2 = G.type_skeleton([Image, Image, Image, Region], V + ["bilateral", "erosion", "canny"])
        o2, k2 = G.encode(sk2, rec)
        assert [s["op"] for s in G.decode(sk2, o2, k2)] == [s["op"] for s in rec["stages"]]
        assert G.decode(sk2, o2, k2) == rec["stages"]
    rec = {"skeleton": ["Image", "Image"], "stages": [{"op": "gaussian", "a": 0.2, "b": None}]}
    with pytest.raises(ValueError, match="stage 1: op 'gaussian' is not in"):
        G.encode(G.type_skeleton([Image, Image], ["box_filter"]), rec)


@pytest.fixture(scope="module")
def count_case():
    pr = make_problem("count", size=(24, 24), n_train=3, n_holdout=2, n_locked=5, n_stages=4)
    sk = pr.skeleton(V)
    return pr, sk, Evaluator(sk, pr.metric_fn, floor=pr.floor)


def _per_individual(pr, sk, ops, knobs, x, t):
    out = []
    for o, k in zip(ops, knobs):
        stages = G.pipeline_stages(G.decode(sk, o, k))
        out.append(score_pipeline(pr, stages, x, t))
    return np.stack(out)


@pytest.mark.parametrize("name", ["denoise", "count"])
def test_population_call_equals_per_individual_pipelines(name, count_case):
    if name == "count":
        pr, sk, ev = count_case
    else:
        pr = make_problem("denoise", size=(24, 24), n_train=3, n_holdout=2, n_locked=5, n_stages=3)
        sk = pr.skeleton(V)
        ev = Evaluator(sk, pr.metric_fn, floor=pr.floor)
    x, t, _ = search_batch(pr, np.float64)
    ops, knobs = G.random_population(np.random.default_rng(7), sk, 5)
    ops[0] = 0  # all-identity first stages where possible (count: stage 1 is Image -> Image)
    pop = ev(ops, knobs, x, t)
    ref = _per_individual(pr, sk, ops, knobs, x, t)
    d = np.abs(pop - ref).max()
    print(f"{name}: population call vs {len(ops)} per-individual fsjax.pipeline runs over {x.shape[0]} images: "
          f"max |diff| = {d:.2e}")
    assert pop.shape == (5, x.shape[0])
    np.testing.assert_allclose(pop, ref, rtol=1e-7, atol=1e-9)
    assert np.ptp(pop.mean(axis=1)) > 0  # the members really differ


def test_vmap_mode_and_unrolled_stages_equal_map_mode():
    pr = make_problem("binarize", size=(24, 24), n_train=2, n_holdout=1, n_locked=3, n_stages=3)
    sk = pr.skeleton(["gaussian", "invert", "threshold", "region_not"])
    x, t, _ = search_batch(pr, np.float64)
    ops, knobs = G.random_population(np.random.default_rng(11), sk, 6)
    ev = Evaluator(sk, pr.metric_fn, floor=pr.floor)
    a = ev(ops, knobs, x, t)
    b = Evaluator(sk, pr.metric_fn, floor=pr.floor, mode="vmap")(ops, knobs, x, t)
    c = Evaluator(sk, pr.metric_fn, floor=pr.floor, scan=False)(ops, knobs, x, t)
    np.testing.assert_allclose(a, b, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(a, c, rtol=1e-7, atol=1e-9)
    assert np.ptp(a.mean(axis=1)) > 0
    assert ev.n_evaluations == 6 and ev.n_calls == 1 and len(ev.compile_seconds) == 1


def test_evaluator_rejects_bad_genomes(count_case):
    pr, sk, ev = count_case
    x, t, _ = search_batch(pr, np.float64)
    ops, knobs = G.random_population(np.random.default_rng(0), sk, 2)
    bad = ops.copy()
    bad[0, 1] = sk.sizes[1]
    with pytest.raises(ValueError, match="outside its stage's vocabulary"):
        ev(bad, knobs, x, t)
    with pytest.raises(ValueError, match=r"in \[0, 1\]"):
        ev(ops, knobs + 2.0, x, t)
    with pytest.raises(ValueError, match="stages"):
        ev(ops[:, :2], knobs[:, :2], x, t)
