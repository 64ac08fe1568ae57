"""The registry, knobs and bad-input errors of the uniform call."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fsjax
from fsjax.registry import IntKnob, LinKnob, LogKnob, register
from fsjax.synth import standard_input


def test_list_ops_filters():
    allops = fsjax.list_ops()
    assert [s.name for s in fsjax.list_ops(family="filters")] == sorted(
        s.name for s in allops if s.family == "filters")
    assert all(s.takes == (fsjax.Image,) for s in fsjax.list_ops(takes=fsjax.Image))
    assert all(s.gives is fsjax.Region for s in fsjax.list_ops(gives=fsjax.Region))
    assert "gaussian" in [s.name for s in fsjax.list_ops(search="GAUSS")]
    with pytest.raises(ValueError, match="unknown family"):
        fsjax.list_ops(family="nope")


def test_spec_fields():
    s = fsjax.get_op("gaussian")
    assert (s.name, s.family, s.takes, s.gives) == ("gaussian", "filters", (fsjax.Image,), fsjax.Image)
    assert s.differentiable and s.refs and s.summary.startswith("Gaussian")
    assert list(s.knobs) == ["sigma"]


def test_knob_maps():
    assert LinKnob(2.0, 4.0).to_param(0.5) == 3.0
    assert float(LogKnob(1.0, 100.0).to_param(0.5)) == pytest.approx(10.0)
    assert float(IntKnob(1, 5).to_param(0.6)) == 3.0
    with pytest.raises(ValueError):
        LogKnob(0.0, 1.0)
    with pytest.raises(ValueError):
        LinKnob(1.0, 1.0)


def test_bad_input_errors():
    img = standard_input(fsjax.Image)
    with pytest.raises(fsjax.UnknownOpError, match="unknown op 'gausian'; did you mean 'gaussian'"):
        fsjax.apply(img, "gausian")
    with pytest.raises(TypeError, match="gaussian: argument 'img' must be Image, got Region"):
        fsjax.ops.gaussian(fsjax.Region(img.data > 0.5))
    with pytest.raises(TypeError, match="gaussian: argument 'img' must be Image, got ndarray"):
        fsjax.ops.gaussian(np.zeros((4, 4)))
    with pytest.raises(ValueError, match="expected at least 2 dimensions, got shape \\(5,\\)"):
        fsjax.Image(jnp.zeros(5))
    with pytest.raises(ValueError, match="gaussian: argument 'img' has batch shape \\(2,\\)"):
        fsjax.ops.gaussian(fsjax.Image(jnp.zeros((2, 4, 4))))
    nan = fsjax.Image(jnp.zeros((4, 4)).at[1, 1].set(jnp.nan))
    with pytest.raises(ValueError, match="gaussian: argument 'img' \\(Image.data\\) contains 1 NaN"):
        fsjax.ops.gaussian(nan)
    with pytest.raises(ValueError, match="apply\\('gaussian'\\): knob 'a' \\(sigma\\) must be in \\[0, 1\\], got 1.5"):
        fsjax.apply(img, "gaussian", a=1.5)
    with pytest.raises(ValueError, match="knob 'b' is not defined"):
        fsjax.apply(img, "gaussian", a=0.1, b=0.2)
    with pytest.raises(ValueError, match="set both by knob and by name"):
        fsjax.apply(img, "gaussian", a=0.1, sigma=2.0)
    with pytest.raises(TypeError, match="unknown parameter"):
        fsjax.apply(img, "gaussian", sgma=2.0)
    with pytest.raises(ValueError, match="gaussian: argument 'sigma' must be > 0, got -1"):
        fsjax.ops.gaussian(img, sigma=-1.0)
    with pytest.raises(ValueError, match="argument 'mode' must be one of"):
        fsjax.ops.gaussian(img, mode="bogus")


def test_register_rules():
    with pytest.raises(TypeError, match="must be keyword-only"):
        @register(family="t", takes=fsjax.Image, gives=fsjax.Image)
        def _bad1(img, sigma=1.0):
            """Doc."""
    with pytest.raises(ValueError, match="needs a docstring"):
        @register(family="t", takes=fsjax.Image, gives=fsjax.Image)
        def _bad2(img):
            pass
    with pytest.raises(ValueError, match="knob 'q' is not a keyword parameter"):
        @register(family="t", takes=fsjax.Image, gives=fsjax.Image, knobs={"q": LinKnob(0, 1)})
        def _bad3(img, *, s=1.0):
            """Doc."""
    with pytest.raises(ValueError, match="already registered"):
        @register(family="t", takes=fsjax.Image, gives=fsjax.Image)
        def gaussian(img):
            """Doc."""


def test_compiled_calls_compiles_whole_and_matches_eager():
    import doctest

    from fsjax import registry as R

    # the docstring example runs and holds
    finder = doctest.DocTestFinder()
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    tests = finder.find(R.compiled_calls, globs={"fsjax": fsjax, "jnp": jnp, "np": np})
    for t in tests:
        runner.run(t)
    assert runner.summarize(verbose=False).failed == 0 and sum(len(t.examples) for t in tests) >= 3

    img = fsjax.Image(jnp.arange(64.0).reshape(8, 8) / 64.0)
    eager = fsjax.ops.gaussian(img, sigma=1.5)
    R._COMPILED.pop("gaussian", None)
    with fsjax.compiled_calls():
        y = fsjax.ops.gaussian(img, sigma=1.5)
        fsjax.ops.gaussian(img, sigma=1.5)
        # an array-valued parameter keeps the eager call (no static key possible)
        z = fsjax.ops.gaussian(img, sigma=jnp.asarray(1.5))
    assert not R._MODE["compiled"]  # restored on exit
    jf = R._COMPILED["gaussian"]
    assert jf._cache_size() == 1  # one program for the two equal calls
    np.testing.assert_allclose(np.asarray(y.data), np.asarray(eager.data), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(z.data), np.asarray(eager.data), rtol=0, atol=1e-12)
    # bad parameters are still refused, naming the op and the argument
    with fsjax.compiled_calls(), pytest.raises(ValueError, match="sigma"):
        fsjax.ops.gaussian(img, sigma=-1.0)


def test_traced_named_parameters_outside_their_domain_fail_closed():
    """Issue 20 item 3 sweep: a traced *named* parameter that the eager call refuses (its
    check_range / check_positive / the op's own check) poisons the op's output through the
    registry, for every op that checks it (found by sweeping each knob-mapped parameter past
    its knob range under jit: before, color_channel(channel=5) gave the blue channel and
    decorrelation_stretch(target_sigma=-0.075) and canny(sigma=-1.25) a normal-looking result).
    In range, the traced call equals the eager one; a check inside an op's inner trace
    records nothing (no leaked tracer)."""
    rgb = fsjax.Color(jnp.linspace(0.0, 1.0, 8 * 8 * 3, dtype=jnp.float32).reshape(8, 8, 3))
    ch = jax.jit(lambda c: fsjax.ops.color_channel(rgb, channel=c).data)
    assert bool(jnp.all(jnp.isnan(ch(5.0)))) and bool(jnp.all(jnp.isnan(ch(-1.0)))) and bool(jnp.all(jnp.isnan(ch(1.5))))
    assert bool(jnp.array_equal(ch(2.0), rgb.data[..., 2]))  # the null: in range, exact
    ds = jax.jit(lambda s: fsjax.ops.decorrelation_stretch(rgb, target_sigma=s).data)
    with pytest.raises(ValueError, match="target_sigma"):
        fsjax.ops.decorrelation_stretch(rgb, target_sigma=-0.075)
    assert bool(jnp.all(jnp.isnan(ds(-0.075))))
    good = ds(0.2)
    assert bool(jnp.all(jnp.isfinite(good)))
    assert bool(jnp.allclose(good, fsjax.ops.decorrelation_stretch(rgb, target_sigma=0.2).data, atol=1e-6))
    # vmap over the parameter: only the bad member is poisoned
    x = fsjax.Image(rgb.data[..., 0])
    g = jax.vmap(lambda s: fsjax.ops.gaussian(x, sigma=s).data)(jnp.array([1.0, -1.0, jnp.nan], jnp.float32))
    assert bool(jnp.all(jnp.isfinite(g[0]))) and bool(jnp.all(jnp.isnan(g[1:])))
    # a relation between two parameters (clip: lo <= hi), found by the same sweep
    cl = jax.jit(lambda lo: fsjax.ops.clip(x, lo=lo, hi=1.0).data)
    assert bool(jnp.all(jnp.isnan(cl(2.0)))) and bool(jnp.all(jnp.isfinite(cl(0.2))))
    # a sort with no float field cannot carry NaN: canny raises at run time
    cn = jax.jit(lambda s: fsjax.ops.canny(x, sigma=s).data)
    assert cn(1.0).dtype == jnp.bool_
    with pytest.raises(Exception, match="out of range"):
        jax.block_until_ready(cn(-1.25))


def test_default_capacity_grows_when_eager_and_is_flagged_under_jit():
    """Issue 20 item 4 (capacity defaults), the review of every capacity-bearing op: on the
    bundled left01 (640 x 512) the old defaults lost data -- iso_contour kept 2,048 of 9,821
    points, subpixel_edges 1,024 of 4,264, ncc_locate 8 of 17 instances -- reported only in
    ``truncated``. An eager call that leaves ``capacity`` at its default now re-runs with a
    larger one until nothing is lost; a capacity the caller gives is kept and flagged, and
    under jit the static buffer's overflow is flagged (numbers reduced from it are NaN).
    Small stand-ins here: 1,600 one-pixel components (label's default 1,024), an 80 x 80
    checker (iso_contour's 2,048 points), 16 copies of a template (ncc_locate's 8), two
    clusters of 40 points (euclidean_cluster's 32 neighbours)."""
    dots = np.zeros((80, 80), bool)
    dots[::2, ::2] = True
    lab = fsjax.ops.label(fsjax.Region(jnp.asarray(dots)))
    assert not bool(lab.truncated) and int(lab.count) == 1600
    assert bool(fsjax.ops.label(fsjax.Region(jnp.asarray(dots)), capacity=1024).truncated)  # the caller's
    chk = fsjax.Image(jnp.asarray(np.kron((np.indices((20, 20)).sum(0) % 2), np.ones((4, 4))), jnp.float32))
    c = fsjax.ops.iso_contour(chk, level=0.5)
    assert not bool(c.truncated) and int(jnp.sum(c.valid)) > 2048
    def under_jit(x):  # static buffer: flagged, and a number reduced from it is NaN
        ci = fsjax.ops.iso_contour(x, level=0.5)
        return ci.truncated, fsjax.ops.contour_length(ci).value

    tr, length = jax.jit(under_jit)(chk)
    assert bool(tr) and np.isnan(float(length))
    spot = np.zeros((8, 8), np.float32)
    spot[2:6, 3:5] = 1.0
    scene = fsjax.Image(jnp.asarray(np.kron(np.ones((4, 4)), np.pad(spot, 4)), jnp.float32))
    m = fsjax.ops.ncc_locate(scene, fsjax.Image(jnp.asarray(np.pad(spot, 1))), min_score=0.9)
    assert not bool(m.truncated) and int(jnp.sum(m.valid)) == 16
    # a neighbour-list capacity (euclidean_cluster's max_neighbors 32) grows the same way
    rng = np.random.default_rng(0)
    two = fsjax.Points(jnp.asarray(np.r_[rng.uniform(0, 0.1, (40, 3)), rng.uniform(5, 5.1, (40, 3))], jnp.float32))
    cl = fsjax.ops.euclidean_cluster(two, radius=0.2, min_size=5)
    assert not bool(cl.truncated) and int(cl.count) == 2
