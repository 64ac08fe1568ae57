"""The chain fuzzer is itself tested: planted bugs are each caught in their class.

Planted ops are registered inside :func:`fsjax.fuzz.temporary_ops` and removed on exit, so
they never leak into the registry other tests see. Inputs are tiny (8 x 8, 7 x 9) and the
chains short: every test compiles a handful of small programs.
"""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import pytest

import fsjax
import fsjax.fuzz as fz
from fsjax import Contour, Image, Region
from fsjax.registry import register

PLANTED = ("planted_wrong_sort", "planted_odd_index", "planted_recompile", "planted_overflow",
           "planted_nan_grad", "planted_traced_nan", "planted_jit_differs", "planted_match_nan", "planted_instances",
           "planted_jitter", "planted_amplify")


def _plant():
    @register(family="planted", takes=Image, gives=Image)
    def planted_wrong_sort(img: Image) -> Image:
        """Planted bug: declares Image, returns Region."""
        return Region(img.data > 0.5)

    @register(family="planted", takes=Image, gives=Image)
    def planted_odd_index(img: Image) -> Image:
        """Planted bug: a raw IndexError on odd sizes."""
        h = img.data.shape[0]
        if h % 2:
            raise IndexError(f"index {h} is out of bounds for axis 0 with size {h}")
        return Image(img.data[::-1])

    @register(family="planted", takes=Image, gives=Image)
    def planted_recompile(img: Image) -> Image:
        """Planted bug: compiles a fresh closure on every call."""
        return Image(jax.jit(lambda d: d * 0.5)(img.data))

    @register(family="planted", takes=Image, gives=Contour)
    def planted_overflow(img: Image, *, capacity: int = 64) -> Contour:
        """Planted bug: keeps the first ``capacity`` bright pixels and never sets ``truncated``."""
        r, c = jnp.nonzero(img.data > 0.5, size=capacity, fill_value=-1)
        valid = r >= 0
        pts = jnp.stack([r, c], axis=-1).astype(img.data.dtype)
        return Contour(pts, valid=valid, truncated=False)

    @register(family="planted", takes=Image, gives=Image, differentiable=True)
    def planted_nan_grad(img: Image) -> Image:
        """Planted bug: sqrt(x^2) with x = 0 somewhere: finite forward, NaN gradient."""
        d = img.data - img.data[0, 0]
        return Image(jnp.sqrt(d * d))

    @register(family="planted", takes=Image, gives=Image)
    def planted_traced_nan(img: Image) -> Image:
        """Planted bug: NaN under a trace where the eager call is finite (an Image has no NaN flag)."""
        return Image(img.data if fsjax.types.is_concrete(img.data) else img.data * jnp.nan)

    @register(family="planted", takes=Image, gives=fsjax.Match3D)
    def planted_match_nan(img: Image, *, flag: bool = False) -> fsjax.Match3D:
        """A record with NaN pose: explained when its ``valid`` is False (``flag``), a bug when True."""
        nan = jnp.full((), jnp.nan, img.data.dtype)
        return fsjax.Match3D(jnp.full((3, 3), nan), jnp.full((3,), nan), nan,
                             jnp.asarray(flag), jnp.asarray(0 if flag else 1, jnp.int32))

    @register(family="planted", takes=Image, gives=fsjax.Match3D)
    def planted_instances(img: Image, *, max_instances: int = 2, extra: int = 0) -> fsjax.Match3D:
        """Instance slots as generalised_hough3d returns them: batch (max_instances,); ``extra``
        adds slots beyond the declared number (a contract break)."""
        n = max_instances + extra
        z = jnp.zeros((n,), img.data.dtype)
        return fsjax.Match3D(jnp.broadcast_to(jnp.eye(3, dtype=z.dtype), (n, 3, 3)), jnp.zeros((n, 3), z.dtype),
                             z + 1, jnp.ones((n,), bool), jnp.zeros((n,), jnp.int32))

    @register(family="planted", takes=Image, gives=Image)
    def planted_jit_differs(img: Image) -> Image:
        """Planted bug: another answer under a trace than eagerly."""
        k = 1.0 if fsjax.types.is_concrete(img.data) else 1.5
        return Image(img.data * k)


    @register(family="planted", takes=Image, gives=Image)
    def planted_jitter(img: Image) -> Image:
        """Not a bug: a traced program whose round-off differs from the eager one (1e-9 relative,
        inside the float64 tolerance)."""
        return Image(img.data if fsjax.types.is_concrete(img.data) else img.data * (1.0 + 1e-9))

    @register(family="planted", takes=Image, gives=Image)
    def planted_amplify(img: Image) -> Image:
        """Not a bug: an ill-conditioned op (the fractional part of ``1e9 x``: a multiply and a
        floor, exact in any program), the same result both ways on the same input."""
        y = img.data * 1e9
        return Image(y - jnp.floor(y))


@pytest.fixture(scope="module")
def planted():
    with fz.temporary_ops():
        _plant()
        specs = fsjax.list_ops(family="planted") + [fsjax.get_op(n) for n in ("gaussian", "otsu", "mean")]
        assert {s.name for s in specs} >= set(PLANTED)
        yield fz.Runner(specs), specs
    assert not set(PLANTED) & {s.name for s in fsjax.list_ops()}  # nothing leaks into the registry


def _chain(ops, kind="scene", size=(8, 8), dtype="float64", params=None):
    params = params or {}
    return fz.Chain.from_json({
        "input": {"sort": "Image", "kind": kind, "size": list(size), "dtype": dtype, "variant": 0},
        "stages": [{"op": op, "a": None, "b": None, "params": params.get(op, {}), "slot": 0} for op in ops]})


@pytest.mark.parametrize("ops, kw, cls, op", [
    (["planted_wrong_sort"], {}, "CONTRACT", "planted_wrong_sort"),
    (["gaussian", "planted_odd_index"], {"size": (7, 9)}, "SUSPECT", "planted_odd_index"),
    (["planted_recompile"], {}, "RECOMPILE", "planted_recompile"),
    (["planted_overflow"], {"params": {"planted_overflow": {"capacity": 2}}}, "SILENT_OVERFLOW",
     "planted_overflow"),
    (["planted_nan_grad"], {}, "GRADNAN", "planted_nan_grad"),
    (["planted_jit_differs"], {}, "MISMATCH", "planted_jit_differs"),
    (["planted_traced_nan"], {}, "NONFINITE", "planted_traced_nan"),
], ids=["wrong_sort", "odd_index", "recompile", "overflow", "nan_grad", "jit_differs", "traced_nan"])
def test_planted_bug_caught_in_its_class(planted, ops, kw, cls, op):
    runner, _ = planted
    o = runner.run(_chain(ops, **kw))
    assert o.status == "failed", o
    assert (o.cls, o.op) == (cls, op), o
    assert o.signature.startswith(f"{cls} {op} ")


def test_clean_chains_pass_and_odd_size_alone_is_fine(planted):
    runner, _ = planted
    # the odd-index op on an even size, and a real chain: no failure
    assert runner.run(_chain(["planted_odd_index"])).status == "ok"
    o = runner.run(_chain(["gaussian", "mean"], dtype="float32"))
    assert o.status == "ok", o
    assert o.executed == ("gaussian", "mean")
    # an overflow that is flagged is not a failure: the same op at its default capacity
    assert runner.run(_chain(["planted_overflow"])).status == "ok"


def test_stage_programs_repeat_across_chains(planted):
    """The per-stage compiled programs are reused when an op meets the same shapes again (knob
    values are traced), and a chain made only of seen stages compiles nothing new in the traced
    ways; the null, compiling the chain whole, compiles again for every new chain."""
    _, specs = planted
    runner = fz.Runner(specs)
    c1 = _chain(["gaussian", "mean"], size=(9, 8))
    c2 = fz.Chain.from_json({**c1.to_json(), "stages": [{"op": "gaussian", "a": 0.7, "b": None, "params": {},
                                                          "slot": 0}, {"op": "mean", "a": None, "b": None,
                                                                       "params": {}, "slot": 0}]})
    c1 = fz.Chain.from_json({**c1.to_json(), "stages": [{**s.to_json(), "a": 0.2 if s.op == "gaussian" else None}
                                                         for s in c1.stages]})
    o1 = runner.run(c1)
    assert o1.status == "ok", o1
    assert runner.stats["stage_hits"] == 0 and runner.stats["stage_calls"] == 2
    o2 = runner.run(c2)  # another knob value: the same two stage programs and grad programs
    assert o2.status == "ok", o2
    assert runner.stats["stage_hits"] == 2 and runner.stats["grad_hits"] == runner.stats["grad_calls"] // 2
    staged_compiles = o2.times["compiles"]
    o3 = runner.run(c2, whole=True)  # the null: the chain compiled whole (jit(vmap), jit, grad)
    assert o3.status == "ok", o3
    assert runner.stats["whole"] == 1
    print(f"compiles: first chain {o1.times['compiles']}, same stages again {staged_compiles}, "
          f"compiled whole {o3.times['compiles']}")
    assert o3.times["compiles"] >= staged_compiles + 2  # the whole chain: at least jit(vmap) and grad


def test_prefix_results_reused_and_bugs_after_them_still_caught(planted):
    """A chain that extends an earlier chain's prefix (the generator's reuse phase) takes the
    prefix's eager results and stage-program batches instead of running them again; the stage
    after the prefix runs every way, so a planted bug there is caught in its class, and the
    grad way still runs the whole chain (its cotangent depends on the last stage)."""
    _, specs = planted
    runner = fz.Runner(specs)
    g = {"op": "gaussian", "a": 0.2, "b": None, "params": {}, "slot": 0}

    def chain(*ops):
        return fz.Chain.from_json({"input": {"sort": "Image", "kind": "scene", "size": [7, 6], "dtype": "float64",
                                             "variant": 0},
                                   "stages": [g] + [{"op": op, "a": None, "b": None, "params": {}, "slot": 0}
                                                    for op in ops]})

    assert runner.run(chain("mean")).status == "ok"
    assert runner.stats["eager_hits"] == 0 and runner.stats["staged_prefix_hits"] == 0
    grads = runner.stats["grad_calls"]
    o = runner.run(chain("planted_nan_grad"))
    assert runner.stats["eager_hits"] == 1 and runner.stats["staged_prefix_hits"] == 1  # the gaussian stage
    assert (o.status, o.cls, o.op, o.stage) == ("failed", "GRADNAN", "planted_nan_grad", 1), o
    assert runner.stats["grad_calls"] > grads
    o = runner.run(chain("planted_jit_differs"))
    assert runner.stats["eager_hits"] == 2
    assert (o.status, o.cls, o.op, o.stage) == ("failed", "MISMATCH", "planted_jit_differs", 1), o
    o = runner.run(chain("planted_wrong_sort"))
    assert (o.status, o.cls, o.op) == ("failed", "CONTRACT", "planted_wrong_sort"), o


def test_prefix_from_a_failed_chain_after_a_release_is_not_a_recompile(planted, monkeypatch):
    """The fourth full run's false RECOMPILE (vesselness3d, eager): a prefix stored by a chain
    that failed later (so its eager recompile check never ran), reused after the compiled
    programs were released; the check now calls such a stage once before the checked call."""
    import fsjax._cache as fc

    _, specs = planted
    runner = fz.Runner(specs, grad=False)
    g = {"op": "gaussian", "a": 0.3, "b": None, "params": {}, "slot": 0}

    def chain(op):
        return fz.Chain.from_json({"input": {"sort": "Image", "kind": "scene", "size": [5, 5], "dtype": "float64",
                                             "variant": 0},
                                   "stages": [g, {"op": op, "a": None, "b": None, "params": {}, "slot": 0}]})

    o = runner.run(chain("planted_wrong_sort"))
    assert (o.cls, o.stage) == ("CONTRACT", 1), o
    monkeypatch.setattr(fc, "near_map_limit", lambda: True)
    assert runner.release_if_needed()
    o = runner.run(chain("mean"))
    assert runner.stats["eager_hits"] == 1
    assert o.status == "ok", o


def test_coverage_phase_then_draws_with_replacement():
    """With a DrawState, every op is drawn once (at the canonical size, an op not drawn yet
    first) before any chain extends an earlier prefix; after that ops repeat, chains reuse
    prefixes, and (op, sort, size, dtype) combinations drawn before weigh more."""
    import random

    from fsjax.fuzz._gen import SIZES, DrawState

    gen = [fsjax.get_op(n) for n in ("gaussian", "otsu", "mean", "region_not", "boundary", "sobel_amp")]
    graph = fz.SortGraph(gen, fz.pool_sorts(gen))
    rng, state = random.Random(1), DrawState()
    chains = []
    while not state.covered:
        chains.append(fz.generate_chain(graph, rng, 4, state))
        assert all(c.inp["size"] == SIZES[0] for c in chains)   # canonical size while covering
    n_cover = len(chains)
    assert set(state.uses) == {s.name for s in gen}
    stages_cover = sum(len(c.stages) for c in chains)
    assert stages_cover <= 2 * len(gen)   # the null (least-used-first, 1/(1+u)^2) repeats more
    later = [fz.generate_chain(graph, rng, 4, state) for _ in range(60)]
    reused = sum(1 for j, c in enumerate(later) if any(
        c.inp == p.inp and c.stages[:k] == p.stages[:k] for p in chains + later[:j]
        for k in range(1, min(len(c.stages), len(p.stages) + 1))))

    print(f"coverage phase {n_cover} chains ({stages_cover} stages for {len(gen)} ops); {reused} of 60 later "
          f"chains extend an earlier prefix")
    assert reused >= 15


def test_reuse_draws_fewer_distinct_stage_programs_than_the_null():
    """Over the whole registry (generation only, nothing runs), 200 chains drawn with the
    coverage phase and reuse need far fewer distinct (op, running sort, size, dtype) stage
    combinations, i.e. compiled programs, than the null (least-used-first throughout, every
    size): 275 distinct in 454 stages against 386 in 508 (seed 0, printed)."""
    import random

    from fsjax.fuzz._gen import DrawState

    specs = fsjax.list_ops()
    graph = fz.SortGraph(specs, fz.pool_sorts(specs))

    def distinct(cs):
        keys = {(st.op, graph.sorts_after(c.inp["sort"], c.stages[:k]), c.inp["size"], c.inp["dtype"])
                for c in cs for k, st in enumerate(c.stages)}
        return len(keys), sum(len(c.stages) for c in cs)

    rng, state = random.Random(0), DrawState()
    ours = distinct([fz.generate_chain(graph, rng, 6, state) for _ in range(200)])
    rng, uses = random.Random(0), {}
    null = distinct([fz.generate_chain(graph, rng, 6, uses) for _ in range(200)])
    print(f"distinct stage combinations in 200 chains: {ours[0]} of {ours[1]} stages (null {null[0]} of {null[1]})")
    assert state.covered   # every op drawn
    assert ours[0] < 0.85 * null[0]


def test_two_level_draw_bounds_new_combinations_and_knob_values(monkeypatch):
    """The reuse phase draws a new (op, running sort, size, dtype) combination, an input off the
    canonical size or new knob values at ``NEW_COMBO_RATE``, else one drawn before. Over the
    whole registry (generation only), 600 chains after the coverage phase reach far fewer new
    stage keys (op, knobs, parameters, sort, size, dtype: what the eager and traced programs
    depend on) than the null, the one-level weighting (``NEW_COMBO_RATE = None``). Printed."""
    import random

    from fsjax.fuzz import _gen

    specs = fsjax.list_ops()
    graph = fz.SortGraph(specs, fz.pool_sorts(specs))

    def new_keys(rate):
        monkeypatch.setattr(_gen, "NEW_COMBO_RATE", rate)
        rng, state = random.Random(0), _gen.DrawState()
        keys = set()

        def add(c):
            n = 0
            for k, st in enumerate(c.stages):
                key = (st.op, st.a, st.b, st.params, graph.sorts_after(c.inp["sort"], c.stages[:k]), c.inp["size"],
                       c.inp["dtype"])
                n += key not in keys
                keys.add(key)
            return n

        while not state.covered:
            add(fz.generate_chain(graph, rng, 6, state))
        return sum(add(fz.generate_chain(graph, rng, 6, state)) for _ in range(600))

    ours, null = new_keys(0.05), new_keys(None)
    print(f"new stage keys in 600 reuse-phase chains: {ours} (null, one-level weighting: {null})")
    assert ours < 0.5 * null


def test_workers_share_the_coverage_and_interleave(planted):
    """Worker ``w`` of ``W`` (``fuzz(workers=W)`` runs each in its own process) covers every
    ``W``-th op first and runs the chains ``w, w + W, ...``; the shares are disjoint and cover
    the drawable ops. Run here in one process, generation and eager only."""
    _, specs = planted
    gen = [s for s in specs if s.name in ("gaussian", "otsu", "mean", "planted_odd_index")]
    covers = []
    for w in range(2):
        run = fz.fuzz(3, 2, seed=4, specs=gen, grad=False, vmap=False, minimise_failures=False, _part=(w, 2))
        assert len(run.results) == 3
        names = {st.op for c, _ in run.results for st in c.stages}
        covers.append(names)
    graph = fz.SortGraph(gen, fz.pool_sorts(gen))
    drawable = sorted(s.name for s in gen if graph.runnable(s))
    assert covers[0] >= set(drawable[0::2]) and covers[1] >= set(drawable[1::2])
    with pytest.raises(ValueError, match="fuzz: argument 'workers' must be 1 when 'specs' is given"):
        fz.fuzz(2, 2, specs=gen, workers=2)
    with pytest.raises(ValueError, match="fuzz: argument 'coverage_share' must be in"):
        fz.fuzz(2, 2, specs=gen, coverage_share=0.0)


def test_programs_released_near_the_map_limit(planted, monkeypatch):
    """Past half of vm.max_map_count the runner drops its compiled programs (the second full run
    died at the limit: "Failed to materialize symbols"); the next chain compiles again, cleanly."""
    import fsjax._cache as fc

    _, specs = planted
    runner = fz.Runner(specs)
    c = _chain(["gaussian"], size=(5, 4))
    assert runner.run(c).status == "ok" and runner._vprog
    assert not runner.release_if_needed()  # far below the limit
    monkeypatch.setattr(fc, "near_map_limit", lambda: True)  # as past half of vm.max_map_count
    assert runner.release_if_needed() and not runner._vprog and runner.stats["released"] == 1
    o = runner.run(c)
    assert o.status == "ok", o
    assert runner.stats["stage_hits"] == 0  # compiled again after the release


def test_whole_chain_way_catches_the_planted_bugs_too(planted):
    runner, _ = planted
    for ops, cls in ((["planted_jit_differs"], "MISMATCH"), (["planted_nan_grad"], "GRADNAN")):
        o = runner.run(_chain(ops, size=(6, 6)), whole=True)
        assert (o.status, o.cls, o.op) == ("failed", cls, ops[0]), o


def test_record_valid_flag_explains_nan(planted):
    """Match3D's scalar ``valid`` False explains its NaN pose (the full run's moments_pose3d and
    lm_rotation_z3d were reported NONFINITE for it); NaN with ``valid`` True is still caught."""
    runner, _ = planted
    o = runner.run(_chain(["planted_match_nan"], size=(4, 4)))
    assert o.status == "ok", o
    o = runner.run(_chain(["planted_match_nan"], size=(4, 4), params={"planted_match_nan": {"flag": True}}))
    assert (o.status, o.cls, o.op) == ("failed", "NONFINITE", "planted_match_nan"), o


def test_instance_batch_declared_by_max_instances(planted):
    """An op with a static ``max_instances`` declares an output batch of that many slots
    (generalised_hough3d, reported CONTRACT in the fourth full run); more slots are still a
    CONTRACT break."""
    runner, _ = planted
    o = runner.run(_chain(["planted_instances"], size=(4, 4), params={"planted_instances": {"max_instances": 3}}))
    assert o.status == "ok", o
    o = runner.run(_chain(["planted_instances"], size=(4, 4), params={"planted_instances": {"extra": 1}}))
    assert (o.status, o.cls, o.op) == ("failed", "CONTRACT", "planted_instances"), o
    assert "expected (2,)" in o.message


def test_all_nan_refused_at_the_door(planted):
    runner, _ = planted
    o = runner.run(_chain(["gaussian", "otsu"], kind="nan"))
    assert o.status == "refused"
    assert o.refused[0] == "gaussian" and "NaN" in o.refused[1]


def test_minimiser_shrinks_and_replay_reproduces(planted, tmp_path, capsys):
    runner, specs = planted
    long = _chain(["gaussian", "gaussian", "planted_wrong_sort", "otsu"], dtype="float32")
    o = runner.run(long)
    assert (o.cls, o.op, o.stage) == ("CONTRACT", "planted_wrong_sort", 2)
    m = fz.minimise(runner, long, o)
    assert [s.op for s in m.stages] == ["planted_wrong_sort"]
    assert m.inp["dtype"] == "float64"
    f = tmp_path / "repro.jsonl"
    f.write_text(json.dumps({"class": o.cls, "chain": long.to_json(), "minimised": m.to_json()}) + "\n")
    outs = fz.replay(f, specs=specs)
    assert [(x.cls, x.op) for x in outs] == [("CONTRACT", "planted_wrong_sort")]
    # and through the command line (planted ops are registered while the fixture lives)
    from fsjax.cli import main

    assert main(["fuzz", "--replay", str(f)]) == 1
    assert "1 still failing" in capsys.readouterr().out


def test_generated_chains_type_correct_and_report(planted, tmp_path):
    _, specs = planted
    gen = [s for s in specs if s.name in ("gaussian", "otsu", "mean", "planted_wrong_sort")]
    graph = fz.SortGraph(gen, fz.pool_sorts(gen))
    assert {t.__name__ for t in graph.reachable} >= {"Image", "Region", "Feature"}
    import random

    rng, uses = random.Random(3), {}
    for _ in range(30):
        c = fz.generate_chain(graph, rng, 4, uses)
        cur = getattr(fsjax, c.inp["sort"])
        for st in c.stages:
            spec = fsjax.get_op(st.op)
            assert issubclass(cur, spec.takes[st.slot]), c.describe()
            cur = spec.gives
    assert set(uses) == {s.name for s in gen}  # least-used-first drawing reaches every op
    run = fz.fuzz(4, 2, seed=5, specs=gen, grad=False, vmap=False, max_minimise_trials=2)
    path = fz.write_report(run, tmp_path)
    text = path.read_text()
    assert "## Failure classes" in text and "## Coverage per family" in text
    assert len(run.results) == 4
    lines = (tmp_path / "failures.jsonl").read_text().splitlines()
    assert len(lines) == sum(run.class_counts().values())
    for line in lines:
        assert fz.Chain.from_json(json.loads(line)["chain"]).stages


# ---------------------------------------------------------------------------
# the bounded fuzz CI runs: a fixed seed over the whole registry
# ---------------------------------------------------------------------------

BOUNDED_CHAINS = 200
BOUNDED_LENGTH = 4
BOUNDED_SEED = 2026
BOUNDED_COVERAGE = 0.05   # the coverage phase draws 5 % of the ops (12 of ~230, drawn from the seed) first


@pytest.mark.slow
def test_bounded_fuzz_whole_registry():
    """A fixed-seed fuzz over the registry fails on any blocking class (SUSPECT, TYPEMISS,
    MISMATCH, SILENT_OVERFLOW, GRADNAN).

    Sized for the suite (docs/fuzz.md): a cold coverage phase costs ~3-4 s of CPU per chain, so
    the run covers a seeded 5 % of the ops first (``coverage_share``, 10 chains) and then repeats
    what it drew, reaching other ops, inputs and knob values at the generator's
    ``NEW_COMBO_RATE``: 200 chains of length <= 4 (32 before) cost 96 s of CPU cold (292 s of
    wall time at load 7-12; 96 chains: 64 s). Chains whose draw says so also run compiled
    whole. Each failure's replayable chain is in the assertion message.
    """
    import random

    run = fz.fuzz(BOUNDED_CHAINS, BOUNDED_LENGTH, seed=BOUNDED_SEED, minimise_failures=False,
                  coverage_share=BOUNDED_COVERAGE)
    print(f"bounded fuzz: {len(run.results)} chains in {run.seconds:.0f} s ({run.cpu_seconds:.0f} s CPU), "
          f"coverage phase {run.stats.get('coverage_chains')} chains, "
          f"stage programs {run.stats['stage_calls']} calls, {run.stats['stage_hits']} reused, "
          f"{run.stats['whole']} chain(s) compiled whole, ops executed {100 * run.executed_fraction():.0f} %")
    assert len(run.results) == BOUNDED_CHAINS
    assert sum(len(o.executed) for _, o in run.results) >= BOUNDED_CHAINS  # it did run ops
    assert run.stats.get("coverage_chains"), "the coverage phase did not end: no reuse phase"
    # chains drawn to be compiled whole (the draw repeated here, independently of the run): those whose
    # first op ran (a chain refused at its first op has nothing to compile) and that did not fail before
    # the whole-chain step are compiled whole; one that fails in that step is counted too
    drawn = [random.Random(f"{BOUNDED_SEED}:{k}").random() < 0.05 for k in range(BOUNDED_CHAINS)]
    assert [bool(o.times.get("whole")) for _, o in run.results] == drawn
    lo = sum(d and bool(o.executed) and o.cls is None for d, (_, o) in zip(drawn, run.results, strict=True))
    hi = sum(d and bool(o.executed) for d, (_, o) in zip(drawn, run.results, strict=True))
    assert run.stats["stage_calls"] >= BOUNDED_CHAINS and lo <= run.stats["whole"] <= hi and run.stats["whole"] >= 1
    bad = [f"{o.signature}\n  {json.dumps(c.to_json())}" for c, o in run.failures if o.cls in fz.BLOCKING]
    assert not bad, "\n".join(bad)


def test_exact_repeats_are_drawn_again(monkeypatch):
    """An exact repeat of an earlier chain (input, stages, knob values, parameters) tests nothing
    new and costs ~0 s (its results come from the earlier prefix): it only inflated the count (the
    fifth full run: 59 of 359). The generator draws again; the null, one draw, repeats."""
    import random

    from fsjax.fuzz import _gen
    from fsjax.fuzz._gen import DrawState
    from fsjax.fuzz._report import _default_specs

    specs = list(_default_specs())
    graph = fz.SortGraph(specs, fz.pool_sorts(specs))

    def draw(n):
        st, rng = DrawState(), random.Random(0)
        chains = [fz.generate_chain(graph, rng, 6, st) for _ in range(n)]
        return len(set(chains)), st.repeats

    distinct, left = draw(600)
    assert (distinct, left) == (600, 0)
    monkeypatch.setattr(_gen, "REPEAT_REDRAWS", 1)   # the null: no second draw
    distinct0, left0 = draw(600)
    assert distinct0 < 570 and left0 == 600 - distinct0, (distinct0, left0)


def test_worker_xla_flags_add_level_0_and_keep_an_explicit_level():
    """Worker processes compile at XLA's backend level 0 (``WORKER_XLA_FLAGS``, set in their
    environment by the parent); the parent's other flags are kept, and a level the user set
    explicitly wins. The chain compiled whole asks for XLA's default level explicitly."""
    from fsjax.fuzz._report import WORKER_XLA_FLAGS, _worker_xla_flags
    from fsjax.fuzz._run import WHOLE_COMPILER_OPTIONS

    assert _worker_xla_flags(None) == WORKER_XLA_FLAGS == "--xla_backend_optimization_level=0"
    assert _worker_xla_flags("--xla_dump_to=/tmp/d") == "--xla_dump_to=/tmp/d --xla_backend_optimization_level=0"
    assert _worker_xla_flags("--xla_backend_optimization_level=2") == "--xla_backend_optimization_level=2"
    assert WHOLE_COMPILER_OPTIONS == {"xla_backend_optimization_level": 3}


@pytest.mark.slow
def test_planted_bugs_caught_under_the_worker_xla_flags():
    """The planted bugs are caught in their classes in a process whose every program compiles at
    the workers' level 0 (the eager way's primitives and op programs included)."""
    import os
    import subprocess
    import sys

    from fsjax.fuzz._report import _worker_xla_flags

    env = {**os.environ, "XLA_FLAGS": _worker_xla_flags(os.environ.get("XLA_FLAGS"))}
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-n", "0", "-p", "no:cacheprovider",
                        f"{__file__}::test_planted_bug_caught_in_its_class",
                        f"{__file__}::test_whole_chain_way_catches_the_planted_bugs_too"],
                       env=env, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-2000:]
    assert "8 passed" in r.stdout, r.stdout[-2000:]


def test_stage_programs_called_with_device_arrays_no_false_recompile(planted, monkeypatch):
    """This branch's full run reported RECOMPILE watershed_split: its program was first called
    with a batch stacked on the host (numpy) and, 29 chains later, with a stage's output (a
    device array); jit's fast path keys on the argument's type, and JAX's bounded trace caches
    had dropped the program's entry by then, so it traced and compiled again. Stage programs
    are now always called with device arrays. Eviction is simulated by clearing JAX's Python-
    level caches (its compiled-executable fast path kept); the null (host arrays passed as they
    are) reports the false RECOMPILE."""
    from jax._src import util as jax_util

    from fsjax.fuzz import _run

    _, specs = planted

    def chain(*knobs):
        return fz.Chain.from_json({"input": {"sort": "Image", "kind": "scene", "size": [6, 7], "dtype": "float64",
                                             "variant": 0},
                                   "stages": [{"op": "gaussian", "a": a, "b": None, "params": {}, "slot": 0}
                                              for a in knobs]})

    def second_chain_outcome():
        runner = fz.Runner(specs, grad=False)
        assert runner.run(chain(0.2)).status == "ok"
        jax_util.clear_all_caches()   # as JAX's LRU caches drop the entry after ~2000 other programs
        return runner.run(chain(0.2, 0.4))   # stage 2: the same program, fed a device array

    o = second_chain_outcome()
    assert o.status == "ok", o
    monkeypatch.setattr(_run, "_device", lambda tree: tree)   # the null: numpy batches as they are
    o = second_chain_outcome()
    assert (o.status, o.cls, o.stage) == ("failed", "RECOMPILE", 1), o


def test_triangulate_column_runs_on_the_pool_at_every_raster_size():
    """The pool's structured-light rig takes the raster size of the chain's column map (its
    camera was 32 x 24 whatever the map, so ``triangulate_column`` was always refused): at the
    canonical size, an edge size, and with the rig as the running value, it now executes in
    every way (eager, jit, vmap, grad) and passes, and the rig at the default size is unchanged."""
    from fsjax.synth import standard_input
    from fsjax.types import StructuredLightRig

    spec = fsjax.get_op("triangulate_column")
    runner = fz.Runner([spec, fsjax.get_op("gaussian")])
    chains = [_chain(["triangulate_column"], size=(16, 16)),
              _chain(["gaussian", "triangulate_column"], kind="odd", size=(3, 5), dtype="float32"),
              fz.Chain.from_json({"input": {"sort": "StructuredLightRig", "kind": "scene", "size": [16, 16],
                                            "dtype": "float64", "variant": 0},
                                  "stages": [{"op": "triangulate_column", "params": {}, "slot": 1}]})]
    for c in chains:
        o = runner.run(c)
        assert o.status == "ok", (c.describe(), o)
        assert "triangulate_column" in o.executed
    cam = standard_input(StructuredLightRig, 0).camera
    assert (cam.width, cam.height) == (32, 24)
    assert [float(v) for v in cam.K[0]] == [40.0, 0.0, 15.5] and float(cam.K[1, 2]) == 11.5


def test_conditioning_is_not_a_mismatch_but_a_differing_op_still_is(planted, monkeypatch):
    """Upstream round-off amplified by an ill-conditioned op is recorded as conditioned (the op's
    program agrees on the eager input); an op that computes otherwise under the trace after the
    same upstream round-off is still a MISMATCH; the null (no same-input judgement) fails both."""
    _, specs = planted
    runner = fz.Runner(specs)   # its own caches: other tests release and recompile the shared one's
    o = runner.run(_chain(["planted_jitter", "planted_amplify"]))
    assert o.status == "ok" and o.conditioned is not None and o.conditioned[:2] == ("planted_amplify", 1), o
    o = runner.run(_chain(["planted_jitter", "planted_jit_differs"]))
    assert (o.status, o.cls, o.op, o.stage) == ("failed", "MISMATCH", "planted_jit_differs", 1), o
    monkeypatch.setattr(fz.Runner, "_same_input_agrees", lambda self, *a: False)
    o = runner.run(_chain(["planted_jitter", "planted_amplify"], size=(8, 9)))
    assert (o.status, o.cls, o.op, o.stage) == ("failed", "MISMATCH", "planted_amplify", 1), o
