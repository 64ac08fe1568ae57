"""Bugs the chain fuzzer found, each pinned by its minimised chain (replayed four ways).

The chains are the fuzzer's JSON lines; ``fsjax fuzz --replay`` runs the same records.
"""

from __future__ import annotations

import jax.numpy as jnp
import pytest

import fsjax
import fsjax.fuzz as fz

# fit_circle / fit_ellipse on a float32 contour with x64 on: optimistix's trust region started
# its step size in float64, Levenberg-Marquardt's damping rows came out float64 beside float32
# residuals and lineax refused the solve with a raw ValueError (SUSPECT). Fixed in
# ops/measure2d/_fit2d.py (the trust region's step size takes the parameters' dtype).
F32_FITS = [
    {"input": {"sort": "Contour", "kind": "scene", "size": [16, 16], "dtype": "float32", "variant": 0},
     "stages": [{"op": op, "a": None, "b": None, "params": {}, "slot": 0}]}
    for op in ("fit_circle", "fit_ellipse")
]


@pytest.mark.parametrize("chain", [
    pytest.param(F32_FITS[0], id="fit_circle_f32"),
    pytest.param(F32_FITS[1], id="fit_ellipse_f32", marks=pytest.mark.slow),
])
def test_float32_contour_fits(chain):
    """The minimised chain's op on its input: no raw error, float32 kept, a close fit.

    (The four-way replay, ``fsjax fuzz --replay``, compiles the solver under vmap and grad
    too: a minute here, too dear for the suite.)"""
    c = fz.Chain.from_json(chain)
    spec = fsjax.get_op(c.stages[0].op)
    x = fz.build_input(fsjax.Contour, c.inp["kind"], c.inp["size"], c.inp["dtype"])
    r32 = spec.fn(x)
    assert r32.params.dtype == jnp.float32 and bool(r32.converged)
    assert bool(jnp.all(jnp.isfinite(r32.params))) and float(r32.rms) < 1.0


# distance_transform of a region with no background pixel returned +inf everywhere (the distance
# to an empty set), unflagged, into whatever came next (NONFINITE in the full run of docs/fuzz.md,
# there after ncc_map -> local_mean made the region all-foreground; minimised here to the
# complement of an empty region). Fixed in ops/image/_distance.py: the frame just outside the
# image is the background then, a documented finite value.
NO_BACKGROUND = {"input": {"sort": "Region", "kind": "empty", "size": [15, 17], "dtype": "float64", "variant": 0},
                 "stages": [{"op": "region_not", "a": None, "b": None, "params": {}, "slot": 0},
                            {"op": "distance_transform", "a": None, "b": None, "params": {}, "slot": 0}]}


def test_distance_transform_without_background_is_finite():
    """The chain replayed (eager, per-stage jit(vmap), the recompile checks) is
    clean, and the value is the documented one: the distance to the image frame."""
    import numpy as np

    c = fz.Chain.from_json(NO_BACKGROUND)
    runner = fz.Runner([fsjax.get_op("region_not"), fsjax.get_op("distance_transform")])
    o = runner.run(c)
    assert o.status == "ok", o
    x = fz.build_input(fsjax.Region, "empty", (15, 17), "float64")
    d = np.asarray(fsjax.ops.distance_transform(fsjax.ops.region_not(x)).data)
    i, j = np.mgrid[:15, :17]
    want = np.minimum(np.minimum(i + 1, 15 - i), np.minimum(j + 1, 17 - j))
    np.testing.assert_array_equal(d, want)
    assert d.max() == 8.0  # the centre row is 8 px from the top and bottom frames


# phase_correlation returned a float64 Match for float32 images when x64 is on (CONTRACT "dtype not
# kept", in the full run of docs/fuzz.md, minimised to the op alone on the pool's float32 scene):
# the peak normalisation divided by an integer count of the phase-carrying bins, which x64 makes
# int64. Fixed in ops/matching/_correlation.py (the normalisation in the image dtype).
PHASE_F32 = {"input": {"sort": "Image", "kind": "scene", "size": [16, 16], "dtype": "float32", "variant": 0},
             "stages": [{"op": "phase_correlation", "a": None, "b": None, "params": {}, "slot": 0}]}


def test_phase_correlation_keeps_float32():
    """The minimised chain's stage on its inputs: float32 kept, and the same shift as in float64
    (to float32 rounding)."""
    import numpy as np

    c = fz.Chain.from_json(PHASE_F32)
    spec = fsjax.get_op("phase_correlation")
    res = {}
    for dt in ("float32", "float64"):
        x = fz.build_input(fsjax.Image, c.inp["kind"], c.inp["size"], dt)
        moving = fz.build_input(fsjax.Image, "scene", c.inp["size"], dt, 1)  # the pool's second input
        res[dt] = spec.fn(x, moving)
    m32, m64 = res["float32"], res["float64"]
    assert m32.row.dtype == jnp.float32 and m32.score.dtype == jnp.float32
    assert m64.row.dtype == jnp.float64
    np.testing.assert_allclose(np.asarray(m32.row), np.asarray(m64.row), atol=1e-3)
    np.testing.assert_allclose(np.asarray(m32.col), np.asarray(m64.col), atol=1e-3)
    np.testing.assert_allclose(np.asarray(m32.score), np.asarray(m64.score), atol=1e-4)


# li (and li_level) on a single pixel: the default tolerance is half the smallest gap between
# sorted values, an empty minimum for one pixel, and jnp.min raised a raw "zero-size array to
# reduction operation min" (SUSPECT in the fourth full run of docs/fuzz.md: ncc_map on a 16 x 16
# image gives a 1 x 1 map). Fixed in ops/image/_threshold.py: the empty minimum is inf, and a
# single pixel is a constant image (NaN level, empty region), as documented.
NCC_LI = {"input": {"dtype": "float32", "kind": "photo", "size": [16, 16], "sort": "Image", "variant": 0},
          "stages": [{"op": "ncc_map", "a": None, "b": None, "params": {}, "slot": 0},
                     {"op": "li", "a": None, "b": None, "params": {}, "slot": 0}]}


def test_li_on_one_pixel_is_a_constant_image():
    import numpy as np

    pytest.importorskip("skimage")
    c = fz.Chain.from_json(NCC_LI)
    runner = fz.Runner([fsjax.get_op("ncc_map"), fsjax.get_op("li")])
    o = runner.run(c)
    assert o.status == "ok", o
    one = fsjax.Image(jnp.full((1, 1), 0.7))
    assert np.isnan(float(fsjax.ops.li_level(one).value))
    assert not bool(fsjax.ops.li(one).data.any())
    # the null of the fix: two distinct pixels still get Li's level between them
    two = fsjax.Image(jnp.array([[0.2, 0.8]]))
    lv = float(fsjax.ops.li_level(two).value)
    assert 0.2 <= lv < 0.8 and fsjax.ops.li(two).data.tolist() == [[False, True]]


# tsdf_fuse with fill_holes=False writes -inf for unobserved voxels, as its docstring says ("no
# data"); the fourth full run reported it NONFINITE (the fuzzer flips boolean parameters). Not a
# bug of the op: the fuzzer now reads the documented -inf of that parameter value
# (fsjax.fuzz._run.DOCUMENTED_NEG_INF); a NaN or +inf there would still fail.
TSDF_HOLES = {"input": {"dtype": "float32", "kind": "scene", "size": [16, 16], "sort": "DepthStack", "variant": 0},
              "stages": [{"op": "tsdf_fuse", "a": None, "b": None, "params": {"fill_holes": False}, "slot": 0}]}


def test_tsdf_unobserved_minus_inf_is_documented(monkeypatch):
    import numpy as np

    from fsjax.fuzz import _run

    c = fz.Chain.from_json(TSDF_HOLES)
    runner = fz.Runner([fsjax.get_op("tsdf_fuse")], grad=False, vmap=False)
    o = runner.run(c)
    assert o.status == "ok", o
    x = fz.build_input(fsjax.DepthStack, "scene", (16, 16), "float32")
    v = np.asarray(fsjax.ops.tsdf_fuse(x, fill_holes=False).data)
    assert np.isneginf(v).any() and not np.isnan(v).any()   # the documented -inf is there
    monkeypatch.setattr(_run, "DOCUMENTED_NEG_INF", {})   # the null: without the rule
    o = fz.Runner([fsjax.get_op("tsdf_fuse")], grad=False, vmap=False).run(c)
    assert (o.status, o.cls) == ("failed", "NONFINITE"), o


# generalised_hough3d returns max_instances slots (batch shape (4,) by default), as documented;
# the fourth full run reported CONTRACT ("output batch shape (4,), expected ()"). The fuzzer now
# takes an op's static ``max_instances`` as its declared output batch (planted test in
# test_fuzz.py::test_instance_batch_declared_by_max_instances).
GHOUGH = {"input": {"dtype": "float64", "kind": "scene", "size": [16, 16], "sort": "Volume", "variant": 0},
          "stages": [{"op": "generalised_hough3d", "a": 1.0, "b": None, "params": {"max_instances": 2}, "slot": 0}]}


# depth_to_tsdf documents the same -inf for fill_holes=False ("or both -inf, no data"); the warm-up
# run of branch fuzz19 (seed 1) reported it NONFINITE on a constant depth map
# (`Depth[constant 16x16 float32] -> depth_to_tsdf{fill_holes: False} -> fill_holes3d -> ...`).
DEPTH_TSDF_HOLES = {"input": {"dtype": "float32", "kind": "constant", "size": [16, 16], "sort": "Depth", "variant": 0},
                    "stages": [{"op": "depth_to_tsdf", "a": None, "b": None, "params": {"fill_holes": False},
                                "slot": 0}]}


def test_depth_to_tsdf_no_data_minus_inf_is_documented(monkeypatch):
    import numpy as np

    from fsjax.fuzz import _run

    c = fz.Chain.from_json(DEPTH_TSDF_HOLES)
    spec = fsjax.get_op("depth_to_tsdf")
    assert fz.Runner([spec], grad=False, vmap=False).run(c).status == "ok"
    x = fz.build_input(fsjax.Depth, "constant", (16, 16), "float32")
    v = np.asarray(fsjax.ops.depth_to_tsdf(x, fill_holes=False).data)
    assert np.isneginf(v).any() and not np.isnan(v).any() and not np.isposinf(v).any()
    monkeypatch.setattr(_run, "DOCUMENTED_NEG_INF", {})   # the null: without the rule
    o = fz.Runner([spec], grad=False, vmap=False).run(c)
    assert (o.status, o.cls) == ("failed", "NONFINITE"), o


def test_generalised_hough3d_instance_slots_are_its_contract():
    c = fz.Chain.from_json(GHOUGH)
    o = fz.Runner([fsjax.get_op("generalised_hough3d")], grad=False, vmap=False).run(c)
    assert o.status == "ok", o


# sobel_dir on a single bright pixel: NaN on the flat background, as its docstring says ("NaN
# where the gradient is zero up to rounding ... mask it with sobel_amp"); an Image has no flag,
# so the warm re-run of the fourth run reported NONFINITE. The fuzzer reads the documented NaN
# (fsjax.fuzz._run.DOCUMENTED_NAN); an inf would still fail.
SOBEL_DIR_SPIKE = {"input": {"dtype": "float64", "kind": "spike", "size": [16, 16], "sort": "Image", "variant": 0},
                   "stages": [{"op": "sobel_dir", "a": None, "b": None, "params": {}, "slot": 0}]}


def test_sobel_dir_documented_nan_on_flat_areas(monkeypatch):
    import numpy as np

    from fsjax.fuzz import _run

    c = fz.Chain.from_json(SOBEL_DIR_SPIKE)
    assert fz.Runner([fsjax.get_op("sobel_dir")], grad=False, vmap=False).run(c).status == "ok"
    x = fz.build_input(fsjax.Image, "spike", (16, 16), "float64")
    d = np.asarray(fsjax.ops.sobel_dir(x).data)
    amp = np.asarray(fsjax.ops.sobel_amp(x).data)
    assert np.isnan(d).any() and np.all(amp[np.isnan(d)] == 0)   # NaN exactly where flat
    monkeypatch.setattr(_run, "DOCUMENTED_NAN", frozenset())   # the null: without the rule
    o = fz.Runner([fsjax.get_op("sobel_dir")], grad=False, vmap=False).run(c)
    assert (o.status, o.cls) == ("failed", "NONFINITE"), o


# render_silhouette with a small capacity under jit: the rasteriser's candidate buffer overflowed
# and the Region came back with holes (MISMATCH jit vs eager in the fourth full run: 456 of 768
# pixels; an eager call sizes the buffer from the data). A Region has no flag and a bool no NaN:
# fixed in ops/measure3d/_render.py, the traced call raises through equinox.error_if (the fuzzer
# counts that as the op's own refusal, like an eager ValueError).
SILHOUETTE_CAP = {"input": {"dtype": "float64", "kind": "scene", "size": [16, 16], "sort": "Mesh", "variant": 0},
                  "stages": [{"op": "render_silhouette", "a": None, "b": None, "params": {"capacity": 4},
                              "slot": 0}]}


def test_render_silhouette_overflow_fails_closed_under_jit():
    import numpy as np

    c = fz.Chain.from_json(SILHOUETTE_CAP)
    mesh = fz.build_input(fsjax.Mesh, "scene", (16, 16), "float64")
    cam = fz.build_input(fsjax.Camera, "scene", (16, 16), "float64", 1)   # the pool's second input
    full = np.asarray(fsjax.ops.render_silhouette(mesh, cam).data)
    small = np.asarray(fsjax.ops.render_silhouette(mesh, cam, capacity=4).data)   # eager: sized from the data
    np.testing.assert_array_equal(small, full)
    assert 0 < full.sum() < full.size
    # the minimised chain, eager and under jit: refused under the trace (the op's own run-time
    # error, raised only when the buffer overflowed), not a failure; before the fix: MISMATCH
    o = fz.Runner([fsjax.get_op("render_silhouette")], grad=False, vmap=False).run(c)
    assert o.status == "ok" and o.refused_traced and "render_silhouette: capacity 4 exceeded" in o.refused_traced[1], o


# shape_locate with a template of vertical stripes (graycode_decode's column codes): MISMATCH jit
# vs eager in the warm re-run of the fourth full run (row 2.1e-5, col 1e-3 px). Not rounding in a
# score: every edge is parallel, so the row is undetermined; the refinement's normal matrix was
# singular (its smallest eigenvalue was the 1e-9 regularisation at every step) and the
# regularisation chose a pose that rounding moved. Fixed in ops/matching/_shape.py: an instance
# whose normal matrix does not determine every pose direction is not converged (no instance).
SHAPE_STRIPES = {"input": {"dtype": "float64", "kind": "scene", "size": [16, 16], "sort": "GrayStack", "variant": 0},
                 "stages": [{"op": "graycode_decode", "a": 0.5, "b": None, "params": {}, "slot": 0},
                            {"op": "shape_locate", "a": 0.8, "b": 0.4, "params": {}, "slot": 1}]}


def test_shape_locate_parallel_edges_fail_closed(monkeypatch):
    """No instance on the stripes; the null (the determinacy rule off) reports one there, at a
    row that the regularisation chose. Instances of a template with edges in every direction
    are unchanged: tests/ops/test_matching.py's alignment scene (three instances within 0.1 px)
    and the docstring example pass with the rule."""
    import numpy as np

    from fsjax.ops.matching import _shape

    c = fz.Chain.from_json(SHAPE_STRIPES)
    gd, sl = fsjax.get_op("graycode_decode"), fsjax.get_op("shape_locate")
    st0, st1 = c.stages
    tpl = gd.fn(fz.build_input(fsjax.GrayStack, "scene", (16, 16), "float64"), **gd.knob_params(st0.a, st0.b))
    t = np.asarray(tpl.data)
    assert np.all(t == t[:1]) and np.ptp(t) > 0   # constant along rows: vertical stripes only
    img = fz.build_input(fsjax.Image, "scene", (16, 16), "float64", 1)   # the pool's other input
    kp = sl.knob_params(st1.a, st1.b)
    m = sl.fn(img, tpl, **kp)
    assert not bool(np.asarray(m.valid).any())   # undetermined: nothing reported
    monkeypatch.setattr(_shape, "DET_MIN", -1.0)   # the null: the rule off
    m0 = sl.fn(img, tpl, **kp, max_points=255)   # another static argument: traced again, without the rule
    assert bool(m0.valid[0]) and float(m0.score[0]) > 0.9   # a confident instance, row arbitrary


# exp_transform on the pool's very large image (the scene x 1e6, float32): (1 + c)^x overflows to
# +inf (NONFINITE in the cold run of the fifth full run, docs/fuzz.md). IEEE overflow of the
# exponential far outside the Image range [0, 1], as numpy.expm1 gives; now documented in its
# docstring and read by the fuzzer (fsjax.fuzz._run.DOCUMENTED_OVERFLOW: infinities only, a NaN
# still fails).
EXP_LARGE = {"input": {"dtype": "float32", "kind": "large", "size": [16, 16], "sort": "Image", "variant": 0},
             "stages": [{"op": "exp_transform", "a": 0.1, "b": None, "params": {}, "slot": 0}]}


def test_exp_transform_overflow_is_documented(monkeypatch):
    import numpy as np

    from fsjax.fuzz import _run

    c = fz.Chain.from_json(EXP_LARGE)
    spec = fsjax.get_op("exp_transform")
    x = fz.build_input(fsjax.Image, "large", (16, 16), "float32")
    kp = spec.knob_params(0.1, None)
    y = np.asarray(spec.fn(x, **kp).data)
    xs = np.asarray(x.data, np.float64)
    over = xs * np.log1p(kp["c"]) > np.log(np.finfo(np.float32).max)
    assert over.any() and np.all(np.isposinf(y[over])) and np.all(np.isfinite(y[~over]))
    assert not np.isnan(y).any()
    # with grad: the fifth full run's GRADNAN (exp_transform -> shi_tomasi -> log -> measure_pairs):
    # the pull-back through an overflowed (+inf) value is undefined, and the stage's forward is not
    # finite, so it is no "finite forward, NaN gradient" (the fuzzer's stage-by-stage grad now
    # blames a stage only when its input and output are finite)
    assert fz.Runner([spec], vmap=False).run(c).status == "ok"
    assert fz.Runner([spec], vmap=False).run(c, whole=True).status == "ok"   # and compiled whole (replay)
    monkeypatch.setattr(_run, "DOCUMENTED_OVERFLOW", frozenset())   # the null: without the rule
    o = fz.Runner([spec], grad=False, vmap=False).run(c)
    assert (o.status, o.cls) == ("failed", "NONFINITE"), o


# shape_locate with a float32 image and a float64 template (the fifth run: `Image[spike f32] ->
# threshold -> region_dilate -> distance_transform -> shape_locate#1`; the distance map of a Region
# is float64 with x64 on) returned float64: JAX's promotion of mixed inputs, not a contract break.
# The fuzzer compared the output with the first input's dtype only (false CONTRACT); now with the
# inputs' dtypes promoted together.
def test_dtype_contract_promotes_mixed_inputs():
    from fsjax.fuzz._run import _Fail

    spec = fsjax.get_op("add_images")
    a32 = fz.build_input(fsjax.Image, "scene", (8, 8), "float32")
    a64 = fz.build_input(fsjax.Image, "scene", (8, 8), "float64")
    runner = fz.Runner([spec], grad=False, vmap=False)
    out = fsjax.Image(a64.data)   # a float64 output, as shape_locate gave (the rule, not add_images, is tested)
    runner._check_stage(0, spec, (a32, a64), out, {}, ())   # promoted: kept
    with pytest.raises(_Fail, match="dtype not kept"):   # two float32 inputs, a float64 output: broken
        runner._check_stage(0, spec, (a32, a32), out, {}, ())


# absolute_phase gives NaN where a code is negative (-1: undecidable), as its docstring says; the fifth run
# reported NONFINITE (`Color -> color_channel -> fft_phase -> absolute_phase#1`: codes from a phase
# image). The fuzzer reads the documented NaN (DOCUMENTED_NAN); an inf would still fail.
def test_absolute_phase_documented_nan(monkeypatch):
    import numpy as np

    from fsjax.fuzz import _run
    from fsjax.fuzz._run import _Fail

    wrapped = fsjax.Image(jnp.zeros((2, 2)))
    code = fsjax.Image(jnp.asarray([[0.0, -1.0], [1.0, -3.0]]))
    out = fsjax.ops.absolute_phase(wrapped, code, code)
    d = np.asarray(out.data)
    assert np.array_equal(np.isnan(d), np.asarray(code.data) < 0)   # NaN exactly at the negative codes
    runner = fz.Runner([fsjax.get_op("absolute_phase")], grad=False, vmap=False)
    runner._check_finite(0, "absolute_phase", out, "eager", ())
    monkeypatch.setattr(_run, "DOCUMENTED_NAN", frozenset())   # the null: without the rule
    with pytest.raises(_Fail, match="NaN in the output"):
        runner._check_finite(0, "absolute_phase", out, "eager", ())


# decorrelation_stretch three times on the pool's float32 colour scene: MISMATCH jit vs eager in the
# fifth full run (1 of 768 values, 2.05e-3 against 2e-3). Both ways were 4.5e-3 off float64: the
# scene has rank 2, and the null axis's rounding noise got the max_gain floor's gain (x100 over the
# largest axis) at every stretch. A hard cut-off (gain 0 below the rounding level) fixed that but made
# the op discontinuous (reverted). Fixed in ops/image/_color.py: each axis's gain is multiplied by
# a smooth factor w(lam / r) that goes to 0 at the dtype's rounding level (r = eps^(2/3) tr C).
DECORR3 = {"input": {"dtype": "float32", "kind": "scene", "size": [16, 16], "sort": "Color", "variant": 0},
           "stages": [{"op": "decorrelation_stretch", "a": None, "b": None, "params": {}, "slot": 0}] * 3}


def test_decorrelation_stretch_float32_rank2_repeated():
    """The minimised chain replayed every way (eager, per-stage jit(vmap), grad, the chain compiled
    whole) is clean; float32 stays with float64 through three stretches (the bound in the docstring),
    and the op stays continuous and differentiable at the rank-deficient input."""
    import jax
    import numpy as np

    c = fz.Chain.from_json(DECORR3)
    f = fsjax.ops.decorrelation_stretch
    x32, x64 = (fz.build_input(fsjax.Color, "scene", (16, 16), dt) for dt in ("float32", "float64"))
    w = np.linalg.eigvalsh(np.cov(np.asarray(x64.data).reshape(-1, 3).T))
    assert w[0] < 1e-12 * w[-1]   # rank 2: the pool's colour scene has a null colour axis
    y32, y64 = f(f(f(x32))), f(f(f(x64)))
    err = float(np.max(np.abs(np.asarray(y32.data, np.float64) - np.asarray(y64.data))))
    assert err < 2e-6, err   # was 4.5e-3 (measured 4.7e-7)
    o = fz.Runner([fsjax.get_op("decorrelation_stretch")]).run(c, whole=True)
    assert o.status == "ok", o
    # continuity and the derivative along the null colour axis, float64: moving the image off rank 2
    # by t changes the output smoothly (the hard cut-off jumped by ~1e-3 of the data at t = 0+)
    v = np.linalg.eigh(np.cov(np.asarray(x64.data).reshape(-1, 3).T))[1][:, 0]   # the null axis
    z = np.random.default_rng(0).standard_normal((16, 16))[..., None] * v

    def g(t):
        return f(fsjax.Color(x64.data + t * jnp.asarray(z))).data

    jg = jax.jit(g)
    ts = np.linspace(0.0, 1e-4, 101)
    outs = np.stack([np.asarray(jg(t)) for t in ts])
    steps = np.max(np.abs(np.diff(outs, axis=0)), axis=(1, 2, 3))
    assert steps.max() < 50 * steps.mean() + 1e-12, (steps.max(), steps.mean())   # no jump
    loss = lambda t: jnp.sum(g(t) * jnp.asarray(z))   # noqa: E731
    for t0 in (0.0, 5e-5):
        ga = float(jax.grad(loss)(t0))
        fd = float((loss(t0 + 1e-7) - loss(t0 - 1e-7)) / 2e-7)
        assert np.isfinite(ga) and abs(ga - fd) <= 1e-3 * max(1.0, abs(fd)), (t0, ga, fd)


# volume_to_sdf documents "+inf everywhere when there is no foreground voxel"; branch fuzz19's full
# run (seed 0) reported it NONFINITE after a Gaussian left no voxel above the level 0.5
# (`Volume[scene 16x16 float64] -> gaussian3d@0.8 -> volume_to_sdf`). The fuzzer now reads that
# rule (fsjax.fuzz._run.DOCUMENTED_ALL_INF): one infinity over the whole output; a NaN, or an
# infinity beside finite distances, would still fail.
SDF_EMPTY = {"input": {"dtype": "float64", "kind": "scene", "size": [16, 16], "sort": "Volume", "variant": 0},
             "stages": [{"op": "gaussian3d", "a": 0.8, "b": None, "params": {}, "slot": 0},
                        {"op": "volume_to_sdf", "a": None, "b": None, "params": {}, "slot": 0}]}


def test_volume_to_sdf_without_foreground_is_documented_inf(monkeypatch):
    import numpy as np

    from fsjax.fuzz import _run

    specs = [fsjax.get_op("gaussian3d"), fsjax.get_op("volume_to_sdf")]
    c = fz.Chain.from_json(SDF_EMPTY)
    assert fz.Runner(specs, grad=False, vmap=False).run(c).status == "ok"
    v = np.asarray(fsjax.ops.volume_to_sdf(fsjax.Volume(np.zeros((4, 5, 6)))).data)
    assert np.all(np.isposinf(v))   # the documented +inf: no foreground voxel
    w = np.asarray(fsjax.ops.volume_to_sdf(fsjax.Volume(np.ones((4, 5, 6)))).data)
    assert np.all(np.isneginf(w))   # and -inf: no background voxel
    runner = fz.Runner(specs, grad=False, vmap=False)
    half = np.full((4, 5, 6), np.inf)
    half[0, 0, 0] = 1.0
    assert not runner._documented_neg_inf("volume_to_sdf", fsjax.Volume(half), {})   # inf beside a finite value
    nan = np.full((4, 5, 6), np.nan)
    assert not runner._documented_neg_inf("volume_to_sdf", fsjax.Volume(nan), {})
    mixed = np.full((4, 5, 6), np.inf)
    mixed[1] = -np.inf   # both infinities at once: neither empty-class case
    assert not runner._documented_neg_inf("volume_to_sdf", fsjax.Volume(mixed), {})
    assert runner._documented_neg_inf("volume_to_sdf", fsjax.Volume(-np.full((4, 5, 6), np.inf)), {})
    monkeypatch.setattr(_run, "DOCUMENTED_ALL_INF", frozenset())   # the null: without the rule
    o = fz.Runner(specs, grad=False, vmap=False).run(c)
    assert (o.status, o.cls) == ("failed", "NONFINITE"), o


# lm_rotation_z3d on a blurred scene volume as its template: the LM does not converge in 50 steps,
# so the record is refused (valid False) eagerly and under jit(vmap); the
# last iterate's NCC score differed by 1.5e-4 (branch fuzz19's full run, seed 0: MISMATCH). A
# refused record is now compared on its refusal and reason only (fsjax.fuzz._run._both_refused);
# a record valid one way and refused the other is still a MISMATCH.
LMZ_REFUSED = {"input": {"dtype": "float64", "kind": "scene", "size": [16, 16], "sort": "Volume", "variant": 0},
               "stages": [{"op": "gaussian3d", "a": 0.8, "b": None, "params": {}, "slot": 0},
                          {"op": "lm_rotation_z3d", "a": None, "b": None, "params": {}, "slot": 1}]}


@pytest.mark.slow
def test_lm_rotation_z3d_refused_both_ways_is_no_mismatch(monkeypatch):
    import numpy as np

    from fsjax.fuzz import _run

    specs = [fsjax.get_op("gaussian3d"), fsjax.get_op("lm_rotation_z3d")]
    c = fz.Chain.from_json(LMZ_REFUSED)
    o = fz.Runner(specs, grad=False).run(c)
    assert o.status == "ok", o
    m = fsjax.ops.lm_rotation_z3d(fz.build_input(fsjax.Volume, "scene", (16, 16), "float64", 1),
                                  fsjax.ops.gaussian3d(fz.build_input(fsjax.Volume, "scene", (16, 16), "float64", 0),
                                                       **specs[0].knob_params(0.8, None, strict=False)))
    # refused, with a reason (max_iterations under XLA's default emitters; not_found, score under
    # min_score, under the suite's older loop emitters: the non-converged path moves with rounding)
    assert not bool(m.valid) and m.message != "ok"
    assert bool(np.all(np.isnan(np.asarray(m.t))))
    # a valid record against a refused one still differs; two refusals with other reasons too
    import equinox as eqx

    ok = eqx.tree_at(lambda r: r.valid, m, jnp.asarray(True))
    assert _run._differ(ok, m, "float64") is not None
    other = eqx.tree_at(lambda r: r.reason, m, jnp.asarray(int(m.reason) + 1, jnp.asarray(m.reason).dtype))
    assert "both refused" in _run._differ(other, m, "float64")
    assert _run._differ(eqx.tree_at(lambda r: r.score, m, m.score + 0.01), m, "float64") is None
    monkeypatch.setattr(_run, "_both_refused", lambda x, y: False)   # the null: compare every field
    # (and no judging on the eager input: the solver's program agrees there, so that alone would
    # call the difference conditioning)
    monkeypatch.setattr(fz.Runner, "_same_input_agrees", lambda self, *a: False)
    o = fz.Runner(specs, grad=False).run(c)
    assert (o.status, o.cls) == ("failed", "MISMATCH"), o


# reconstruct_erosion / reconstruct_dilation computed in the mask's dtype: a float64 marker over a
# float32 mask gave float32 (CONTRACT in the ninth full run of docs/fuzz.md: the minimised chain
# below; distance_transform of a Region is float64, the pool's second input float32). Fixed in
# ops/measure2d/_segment.py: both in their promoted dtype.
REC_DTYPE = {"input": {"dtype": "float32", "kind": "scene", "size": [16, 16], "sort": "Region", "variant": 0},
             "stages": [{"op": "distance_transform", "a": None, "b": None, "params": {}, "slot": 0},
                        {"op": "reconstruct_erosion", "a": None, "b": None, "params": {}, "slot": 0}]}


def test_reconstruct_keeps_the_promoted_dtype():
    import numpy as np

    c = fz.Chain.from_json(REC_DTYPE)
    o = fz.Runner([fsjax.get_op("distance_transform"), fsjax.get_op("reconstruct_erosion")],
                  grad=False, vmap=False).run(c)
    assert o.status == "ok", o
    m64 = fz.build_input(fsjax.Image, "scene", (16, 16), "float64")
    k32 = fz.build_input(fsjax.Image, "scene", (16, 16), "float32", 1)
    for name in ("reconstruct_erosion", "reconstruct_dilation"):
        f = fsjax.get_op(name).fn
        r = f(m64, k32)
        assert r.data.dtype == jnp.float64, name
        # the same values as with both inputs float64 (the mask's float32 values, widened)
        ref = f(m64, fsjax.Image(jnp.asarray(k32.data, jnp.float64)))
        np.testing.assert_array_equal(np.asarray(r.data), np.asarray(ref.data))
        assert f(k32, k32).data.dtype == jnp.float32, name


# region_shape of one-pixel regions (regional maxima of the pool's scene, labelled): circularity
# 4 pi area / perimeter^2 is NaN for a zero perimeter, as the measure ops document; stop 37's full run
# reported it NONFINITE. The fuzzer reads the documented NaN (fsjax.fuzz._run._undefined_circularity_only):
# NaN only in the circularity column of valid rows whose perimeter is 0; any other NaN still fails.
SHAPE_ONE_PIXEL = {"input": {"dtype": "float64", "kind": "scene", "size": [16, 16], "sort": "Image", "variant": 0},
                   "stages": [{"op": op, "a": None, "b": None, "params": {}, "slot": 0}
                              for op in ("regional_maxima", "label", "region_shape")]}


def test_region_shape_one_pixel_circularity_is_documented_nan(monkeypatch):
    import equinox as eqx
    import numpy as np

    from fsjax.fuzz import _run

    specs = [fsjax.get_op(s["op"]) for s in SHAPE_ONE_PIXEL["stages"]]
    c = fz.Chain.from_json(SHAPE_ONE_PIXEL)
    assert fz.Runner(specs, grad=False, vmap=False).run(c).status == "ok"
    img = fz.build_input(fsjax.Image, "scene", (16, 16), "float64")
    props = fsjax.ops.region_shape(fsjax.ops.label(fsjax.ops.regional_maxima(img)))
    t = np.asarray(props.table)[np.asarray(props.valid)]
    ci, pi = props.names.index("circularity"), props.names.index("perimeter")
    assert np.isnan(t[:, ci]).sum() > 0 and np.all(t[np.isnan(t[:, ci]), pi] == 0)   # NaN exactly at perimeter 0
    assert _run._undefined_circularity_only(props)
    other = eqx.tree_at(lambda r: r.table, props, props.table.at[0, props.names.index("area")].set(jnp.nan))
    assert not _run._undefined_circularity_only(other)   # a NaN area is not explained
    monkeypatch.setattr(_run, "_undefined_circularity_only", lambda p: False)   # the null: without the rule
    o = fz.Runner(specs, grad=False, vmap=False).run(c)
    assert (o.status, o.cls) == ("failed", "NONFINITE"), o


# euclidean_cluster on 2,048 surface samples: 116 points have more than max_neighbors = 32 neighbours.
# Eagerly the registry grows the defaulted max_neighbors and runs again (truncated False); under jit it
# cannot, and flags truncated. Stop 37's full run reported MISMATCH (`.truncated`). The fuzzer now reads a
# traced record flagged truncated against an eager one that is not as the traced way failing closed
# (fsjax.fuzz._run._traced_overflow_eager_grew); the reverse, or other differences with equal flags, still fail.
CLUSTER_GROWN = {"input": {"dtype": "float64", "kind": "scene", "size": [16, 16], "sort": "Mesh", "variant": 0},
                 "stages": [{"op": "sample_surface", "a": None, "b": None, "params": {}, "slot": 0},
                            {"op": "euclidean_cluster", "a": None, "b": None, "params": {}, "slot": 0}]}


def test_euclidean_cluster_traced_overflow_where_eager_grew(monkeypatch):
    import jax

    from fsjax.fuzz import _run

    specs = [fsjax.get_op(s["op"]) for s in CLUSTER_GROWN["stages"]]
    c = fz.Chain.from_json(CLUSTER_GROWN)
    assert fz.Runner(specs, grad=False, vmap=False).run(c).status == "ok"
    pts = fsjax.ops.sample_surface(fz.build_input(fsjax.Mesh, "scene", (16, 16), "float64"))
    eager = fsjax.ops.euclidean_cluster(pts)
    traced = jax.jit(fsjax.ops.euclidean_cluster)(pts)
    assert not bool(eager.truncated) and bool(traced.truncated)
    assert _run._differ(traced, eager, "float64", []) is None
    assert _run._differ(eager, traced, "float64", []) is not None   # eager flagged, traced not: a mismatch
    # the null, without the rule: the same pair is the run's MISMATCH (compared directly: a second
    # replay of the chain cost ~15 s in the suite)
    monkeypatch.setattr(_run, "_traced_overflow_eager_grew", lambda x, y: False)
    assert "truncated" in _run._differ(traced, eager, "float64", [])


# lk_translation3d was never executed in stop 37's full run: the pool's second volume had spacing
# (2, 1, 1) while the running volume had another, and the op refuses a spacing mismatch (a clear
# error, so not a failure, but the op went untested). The pool's second volume now takes the running
# one's spacing (fsjax.fuzz._gen.extra_input).
def test_extra_volume_takes_the_running_spacing():
    from fsjax.fuzz._gen import extra_input

    v = fz.build_input(fsjax.Volume, "scene", (16, 16), "float64")
    assert v.spacing != (1.0, 1.0, 1.0)
    run = fsjax.Volume(v.data, spacing=(1.0, 1.0, 1.0))
    e = extra_input(fsjax.Volume, run, "float64", 1)
    assert e.spacing == run.spacing and e.data.shape == run.data.shape
    m = fsjax.ops.lk_translation3d(run, e)   # runs (the null below: the pool's own spacing is refused)
    assert m.t.shape == (3,)
    with pytest.raises(ValueError, match="lk_translation3d: argument 'template' has spacing"):
        fsjax.ops.lk_translation3d(run, fz.build_input(fsjax.Volume, "scene", (16, 16), "float64", 1))


# gauss_deriv of a constant float64 image was round-off noise of a few ulps (its antisymmetric
# taps' weighted sum cancels only to round-off, in an order that differs between the eager and
# the compiled program), and equalize_hist stretched that noise over [0, 1] differently both
# ways: MISMATCH equalize_hist [jit], all 256 values, in the eleventh full run (docs/fuzz.md).
# Fixed in the op: first-derivative taps are summed as differences of mirrored samples
# (fsjax.ops._common.correlate1d_antisymmetric), so a constant image has exactly zero derivative.
FLAT_DERIVATIVE = {"input": {"sort": "Image", "kind": "constant", "size": [16, 16], "dtype": "float64", "variant": 0},
                   "stages": [{"op": "gauss_deriv", "a": 0.3, "b": None, "params": {}, "slot": 0},
                              {"op": "equalize_hist", "a": None, "b": None, "params": {}, "slot": 0}]}


def test_derivative_of_a_constant_image_is_exactly_zero():
    """The minimised chain replays clean without the conditioning rule; the derivative is exactly
    0 eagerly and under jit; the null (the plain weighted sum with the same taps) is not."""
    import jax

    from fsjax.ops._common import correlate1d
    from fsjax.ops.image._edges import _gauss_taps

    c = fz.Chain.from_json(FLAT_DERIVATIVE)
    runner = fz.Runner([fsjax.get_op("gauss_deriv"), fsjax.get_op("equalize_hist")], grad=False)
    o = runner.run(c)
    assert o.status == "ok" and o.conditioned is None, o
    x = fz.build_input(fsjax.Image, "constant", (16, 16), "float64")
    for comp in ("x", "y", "xy", "amp"):
        e = fsjax.ops.gauss_deriv(x, sigma=1.3, component=comp).data
        j = jax.jit(lambda im, comp=comp: fsjax.ops.gauss_deriv(im, sigma=1.3, component=comp))(x).data
        assert float(jnp.max(jnp.abs(e))) == 0.0 and float(jnp.max(jnp.abs(j))) == 0.0, comp
    w = _gauss_taps(1.3, 1, 4.0, 8.0, jnp.float64)
    null = correlate1d(jnp.full((16, 16), 0.7371), w, axis=-1)
    assert float(jnp.max(jnp.abs(null))) > 0.0   # the plain sum leaves round-off


# Image[scene 16x16 float32] -> butterworth_lowpass -> gauss_deriv -> fft_phase: 86 of 256
# phases differed by up to 0.092 rad between the staged (jit(vmap)) way and the eager one in the
# eleventh run. The two fft_phase programs agree on the same input: the stage inputs differ by
# float32 round-off of the two upstream filters (~2e-5 of the image's range, within the
# tolerance), and the phase of a coefficient at 1e-5..1e-3 of the largest magnitude turns that
# into 0.01-0.9 rad. That is the conditioning of the phase, not a traced way computing otherwise:
# the runner judges a differing stage on the eager input (Runner._same_input_agrees) and records
# it as conditioned. (The run's own chain no longer differs since gauss_deriv's taps are summed
# in mirrored pairs, above; these knob values still do.)
PHASE_AFTER_LOWPASS = {"input": {"sort": "Image", "kind": "scene", "size": [16, 16], "dtype": "float32", "variant": 0},
                       "stages": [{"op": "butterworth_lowpass", "a": 0.2, "b": None, "params": {}, "slot": 0},
                                  {"op": "gauss_deriv", "a": 0.2, "b": None, "params": {}, "slot": 0},
                                  {"op": "fft_phase", "a": None, "b": None, "params": {}, "slot": 0}]}


def test_ill_conditioned_phase_is_judged_on_the_eager_input(monkeypatch):
    """The chain is recorded as conditioned at fft_phase (not failed); the null, the runner
    without the same-input judgement, calls it a MISMATCH at fft_phase."""
    c = fz.Chain.from_json(PHASE_AFTER_LOWPASS)
    specs = [fsjax.get_op(s.op) for s in c.stages]
    runner = fz.Runner(specs, grad=False)
    o = runner.run(c)
    assert o.status == "ok", o
    assert o.conditioned is not None and o.conditioned[:2] == ("fft_phase", 2), o
    assert runner.stats["conditioned"] == 1
    monkeypatch.setattr(fz.Runner, "_same_input_agrees", lambda self, *a: False)
    o = fz.Runner(specs, grad=False).run(c)
    assert (o.status, o.cls, o.op, o.stage) == ("failed", "MISMATCH", "fft_phase", 2), o


# curvature after remove_ground on the float32 point scene: 5 points survive, fewer than the 6 a
# quadric fit needs, and curvature returned NaN rows that its `valid` (the cloud's mask) called
# valid (NONFINITE curvature in a profile run of stop 34, never fixed until stop 38). Fixed in the
# op: a row whose fit is ill-posed is invalid (valid = cloud mask & a posed fit) and holds NaN.
CURV_FEW = {"input": {"sort": "Points", "kind": "scene", "size": [16, 16], "dtype": "float32", "variant": 0},
            "stages": [{"op": "remove_ground", "a": 0.5, "b": 0.5, "params": {}, "slot": 0},
                       {"op": "curvature", "a": None, "b": None, "params": {}, "slot": 0}]}


def test_curvature_flags_rows_it_cannot_fit():
    import numpy as np

    c = fz.Chain.from_json(CURV_FEW)
    runner = fz.Runner([fsjax.get_op("remove_ground"), fsjax.get_op("curvature")], grad=False)
    o = runner.run(c)
    assert o.status == "ok", o
    pts = fz.build_input(fsjax.Points, "scene", (16, 16), "float32")
    kept = fsjax.get_op("remove_ground").fn(pts, **fsjax.get_op("remove_ground").knob_params(0.5, 0.5, strict=True))
    cv = fsjax.ops.curvature(kept)
    v, ok = np.asarray(cv.values), np.asarray(cv.valid)
    assert 0 < int(np.asarray(kept.valid).sum()) < 6 and not ok.any() and np.isnan(v).all()
    # the null: the same values under the cloud's own mask are a NONFINITE
    old = fsjax.PointValues(cv.values, cv.names, valid=kept.valid)
    with pytest.raises(fz._run._Fail, match="NaN"):
        runner._check_finite(1, "curvature", old, "eager")


# decorrelation_stretch of a grey image carried to colour (grey_to_rgb -> rgb_to_lab -> lab_to_rgb):
# the covariance has two null eigenvalues, equal, and eigh's eigenvector derivative there is
# 0 * inf = NaN (GRADNAN in a profile run of stop 34, "not investigated" until stop 38). Fixed in
# the op: the whitening matrix is differentiated as a spectral function (divided differences of
# the gains, their limit at a repeated eigenvalue), not through the eigenvectors.
DECORR_GREY = {"input": {"sort": "Image", "kind": "large", "size": [16, 16], "dtype": "float32", "variant": 0},
               "stages": [{"op": "grey_to_rgb", "a": None, "b": None, "params": {}, "slot": 0},
                          {"op": "rgb_to_lab", "a": None, "b": None, "params": {}, "slot": 0},
                          {"op": "lab_to_rgb", "a": None, "b": None, "params": {}, "slot": 0},
                          {"op": "decorrelation_stretch", "a": None, "b": 0.9, "params": {}, "slot": 0}]}


def test_decorrelation_stretch_gradient_at_repeated_eigenvalues(monkeypatch):
    import jax
    import numpy as np

    c = fz.Chain.from_json(DECORR_GREY)
    o = fz.Runner([fsjax.get_op(s.op) for s in c.stages]).run(c)
    assert o.status == "ok", o
    rng = np.random.default_rng(5)
    grey = jnp.asarray(np.repeat(rng.uniform(0.2, 0.8, (12, 12, 1)), 3, axis=2))   # rank 1: two null axes
    z, wgt = (jnp.asarray(rng.standard_normal(grey.shape)) for _ in range(2))
    loss = jax.jit(lambda t: jnp.sum(fsjax.ops.decorrelation_stretch(fsjax.Color(grey + t * z)).data * wgt))
    ga = float(jax.grad(loss)(0.0))
    fd = float((loss(1e-8) - loss(-1e-8)) / 2e-8)
    assert np.isfinite(ga) and abs(ga) > 0.1 and abs(ga - fd) <= 1e-5 * abs(fd), (ga, fd)
    # an isotropic covariance (three equal eigenvalues): finite and equal to the finite difference
    a = rng.standard_normal((144, 3))
    q = np.linalg.qr(a - a.mean(0))[0]
    iso = jnp.asarray((q * 12.0 * 0.1 + 0.5).reshape(12, 12, 3))
    loss2 = jax.jit(lambda t: jnp.sum(fsjax.ops.decorrelation_stretch(fsjax.Color(iso + t * z), target_sigma=0.2).data * wgt))
    g2, fd2 = float(jax.grad(loss2)(0.0)), float((loss2(1e-6) - loss2(-1e-6)) / 2e-6)
    assert abs(g2) > 0.1 and abs(g2 - fd2) <= 1e-6 * abs(fd2), (g2, fd2)

    # the null: the same whitening differentiated through eigh's eigenvectors (the op before the
    # fix): the chain's gradient is NaN again
    from fsjax.ops.image import _color

    def through_eigh(cm, aux):
        lam, vec = jnp.linalg.eigh(cm)
        return (vec * _color._stretch_gains(lam, aux)[None, :]) @ vec.T

    monkeypatch.setattr(_color, "_whitening", through_eigh)
    o = fz.Runner([fsjax.get_op(s.op) for s in c.stages]).run(c)
    assert (o.status, o.cls, o.op) == ("failed", "GRADNAN", "decorrelation_stretch"), o
