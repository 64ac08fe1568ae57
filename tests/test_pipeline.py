"""Pipelines and the uniform call."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fsjax
from fsjax.synth import standard_input


@pytest.fixture
def img():
    return standard_input(fsjax.Image)


def test_type_error_before_tracing(monkeypatch):
    traced = []
    monkeypatch.setattr(jax, "jit", lambda *a, **k: traced.append(1))
    with pytest.raises(fsjax.PipelineTypeError) as ei:
        fsjax.pipeline(["otsu", "sobel_amp"])
    e = ei.value
    print("\n", e)
    assert str(e) == "stage 2 (sobel_amp) takes Image but stage 1 (otsu) gives Region"
    assert (e.index, e.prev_index, e.op, e.prev_op, e.expected, e.got) == (
        1, 0, "sobel_amp", "otsu", "Image", "Region")
    assert not traced


def test_multi_input_ops_refused_by_linear_pipelines():
    two = [s for s in fsjax.list_ops() if not s.linear]
    assert two, "expected at least one two-input op"
    with pytest.raises(fsjax.PipelineTypeError) as ei:
        fsjax.pipeline(["gaussian", two[0].name])
    assert ei.value.index == 1


def test_gaussian_vmap_16_knobs_compiles_once_equals_separate_calls(img):
    traces = []

    def f(a):
        traces.append(1)
        return fsjax.apply(img, "gaussian", a=a).data

    a = jnp.linspace(0.0, 1.0, 16)
    batched = jax.jit(jax.vmap(f))(a)
    sep = jnp.stack([fsjax.apply(img, "gaussian", a=float(ai)).data for ai in a])
    diff = float(jnp.max(jnp.abs(batched - sep)))
    print(f"\nvmap over 16 gaussian knobs: {len(traces)} trace(s), max |diff| vs separate calls = {diff:.2e}")
    assert len(traces) == 1
    assert diff < 1e-12


def test_grad_wrt_knob_nonzero(img):
    g = jax.grad(lambda a: jnp.sum(fsjax.apply(img, "gaussian", a=a).data ** 2))(0.3)
    assert np.isfinite(float(g)) and abs(float(g)) > 1e-6


def test_stage_forms_and_knobs_array(img):
    p = fsjax.pipeline(["gaussian", ("gaussian", 0.5), ("gaussian", {"sigma": 2.0})])
    assert p.sorts == (fsjax.Image,) * 3
    y = p(img)
    # first stage default sigma=1, second knob 0.5, third sigma=2
    ref = fsjax.ops.gaussian(fsjax.apply(fsjax.ops.gaussian(img, sigma=1.0), "gaussian", a=0.5), sigma=2.0)
    np.testing.assert_allclose(y.data, ref.data, atol=1e-12)
    knobs = jnp.array([[0.1, 0.0], [0.9, 0.0], [0.5, 0.0]])
    yk = p(img, knobs)
    ref = fsjax.ops.gaussian(
        fsjax.apply(fsjax.apply(img, "gaussian", a=0.1), "gaussian", a=0.9), sigma=2.0)  # named param wins
    np.testing.assert_allclose(yk.data, ref.data, atol=1e-12)
    # vmap over knob sets
    ks = jnp.stack([knobs, knobs * 0.5])
    yv = jax.vmap(lambda k: p(img, k))(ks)
    np.testing.assert_allclose(yv.data[0], yk.data, atol=1e-12)


def test_run_pipeline_and_trace(img):
    y = fsjax.run_pipeline(img, ["gaussian", "gaussian"])
    outs = fsjax.pipeline(["gaussian", "gaussian"]).trace(img)
    assert len(outs) == 2
    np.testing.assert_allclose(outs[-1].data, y.data, atol=1e-12)


def test_pipeline_bad_calls(img):
    p = fsjax.pipeline(["gaussian"])
    with pytest.raises(TypeError, match="stage 1 \\(gaussian\\) takes Image, got Region"):
        p(fsjax.Region(jnp.zeros((4, 4), bool)))
    with pytest.raises(ValueError, match="expected shape \\(1, 2\\)"):
        p(img, jnp.zeros((2, 2)))
    with pytest.raises(ValueError, match="stage 1 \\(gaussian\\), knob 'a' must be in \\[0, 1\\], got 1.5"):
        p(img, jnp.array([[1.5, 0.0]]))
    with pytest.raises(ValueError, match="needs at least one stage"):
        fsjax.pipeline([])
    with pytest.raises(fsjax.UnknownOpError, match="did you mean 'gaussian'"):
        fsjax.pipeline(["gausian"])
    with pytest.raises(TypeError, match="pipeline stage 1 \\(gaussian\\): unknown parameter"):
        fsjax.pipeline([("gaussian", {"sgma": 1.0})])
    with pytest.raises(ValueError, match="pipeline stage 1 \\(gaussian\\): knob 'a' \\(sigma\\) must be in"):
        fsjax.pipeline([("gaussian", 2.0)])


def test_traced_out_of_range_knobs_fail_closed():
    """Issue 20 item 3: a traced knob outside [0, 1] poisons the output (before: a clamped,
    plausible image). Float sorts become NaN; a Region result raises at run time."""
    x = fsjax.Image(jnp.linspace(0.0, 1.0, 12 * 12, dtype=jnp.float32).reshape(12, 12))
    f = jax.jit(lambda a: fsjax.apply(x, "gaussian", a=a).data)
    assert bool(jnp.all(jnp.isnan(f(1.5)))) and bool(jnp.all(jnp.isnan(f(-0.1)))) and bool(jnp.all(jnp.isnan(f(jnp.nan))))
    good = f(0.5)
    assert bool(jnp.all(jnp.isfinite(good)))
    assert bool(jnp.allclose(good, fsjax.apply(x, "gaussian", a=0.5).data, atol=1e-6))
    # vmap: only the bad member is poisoned
    v = jax.vmap(lambda a: fsjax.apply(x, "gaussian", a=a).data)(jnp.array([0.5, 1.5], jnp.float32))
    assert bool(jnp.all(jnp.isfinite(v[0]))) and bool(jnp.all(jnp.isnan(v[1])))
    # pipelines: an Image result is NaN; the poison survives a later stage that would hide it
    p = fsjax.pipeline(["gaussian", "sobel_amp"])
    y = jax.jit(lambda k: p(x, k).data)(jnp.full((2, 2), 2.0, jnp.float32))
    assert bool(jnp.all(jnp.isnan(y)))
    pr = fsjax.pipeline(["gaussian", "sobel_amp", "otsu"])
    run = jax.jit(lambda k: pr(x, k).data)
    assert int(run(jnp.full((3, 2), 0.5, jnp.float32)).sum()) > 0
    with pytest.raises(Exception, match="out of range"):
        jax.block_until_ready(run(jnp.full((3, 2), 2.0, jnp.float32)))
    # a knob row of a stage without knobs is ignored, as documented
    y2 = jax.jit(lambda k: p(x, k).data)(jnp.array([[0.5, 0.5], [7.0, 7.0]], jnp.float32))
    assert bool(jnp.all(jnp.isfinite(y2)))


def test_trace_reports_each_stage_as_it_finishes():
    """Issue 20 item 6: `fsjax run` printed nothing until every stage had run; Pipeline.trace now
    calls on_stage(i, stage, out) after each stage (the CLI prints a timed line per stage)."""
    seen = []
    p = fsjax.pipeline(["gaussian", "sobel_amp", "otsu"])
    x = fsjax.Image(jnp.linspace(0, 1, 24 * 32).reshape(24, 32))
    outs = p.trace(x, on_stage=lambda i, st, y: seen.append((i, st.spec.name, y)))
    assert [(i, n) for i, n, _ in seen] == [(0, "gaussian"), (1, "sobel_amp"), (2, "otsu")]
    assert all(y is o for (_, _, y), o in zip(seen, outs))


def test_top_level_call_uses_the_fast_compile_program_with_the_same_result(img):
    """A pipeline called at top level runs its FAST_COMPILE program (fsjax._linalg.jit_fast_compile);
    the plain program (what a user's jit or vmap traces) gives the same numbers."""
    from fsjax._linalg import FAST_COMPILE

    p = fsjax.pipeline(["gaussian", "sobel_amp", "otsu", "count_obj"])
    k = jnp.full((4, 2), 0.4)
    before = p._compiled.fast._cache_size()
    y = p(img, k)
    assert p._compiled.fast._cache_size() == before + 1   # the fast program was compiled and used
    assert FAST_COMPILE["xla_cpu_use_fusion_emitters"] is False
    yp = p._compiled.plain(img, k)
    (a,), (b,) = jax.tree_util.tree_leaves(y), jax.tree_util.tree_leaves(yp)
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12)
    assert float(np.asarray(a)) > 0
    yv = jax.vmap(lambda kk: p(img, kk))(jnp.stack([k, k]))   # under vmap: the plain program, traced
    np.testing.assert_allclose(np.asarray(jax.tree_util.tree_leaves(yv)[0])[0], np.asarray(a), rtol=1e-12)
