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
