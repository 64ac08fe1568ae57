"""3-D grey and binary morphology (ball and cube, spacing-aware) and fill_holes3d:
exact conformance with scipy.ndimage, the element vs skimage.morphology.ball, float32,
vmap, bad input. One volume shape throughout."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage as ndi
from skimage.morphology import ball

from fsjax import Volume
from fsjax.ops import closing3d, dilation3d, erosion3d, fill_holes3d, opening3d, tophat3d
from fsjax.ops.volume._morphology3d import element

SHAPE = (12, 14, 16)
SP = (2.0, 1.0, 0.5)
OURS = {"erosion": erosion3d, "dilation": dilation3d, "opening": opening3d, "closing": closing3d,
        "tophat": tophat3d}
GREY = {"erosion": ndi.grey_erosion, "dilation": ndi.grey_dilation, "opening": ndi.grey_opening,
        "closing": ndi.grey_closing, "tophat": ndi.white_tophat}
BINARY = {"erosion": ndi.binary_erosion, "dilation": ndi.binary_dilation, "opening": ndi.binary_opening,
          "closing": ndi.binary_closing}


@pytest.fixture(scope="module")
def data():
    rng = np.random.default_rng(11)
    x = rng.random(SHAPE)
    m = ndi.gaussian_filter(rng.random(SHAPE), 1.0) > 0.5
    return x, m


def test_element_is_skimage_ball_at_unit_spacing():
    for r in (1, 2, 3):
        assert np.array_equal(element(float(r), "ball", (1.0, 1.0, 1.0)), ball(r).astype(bool))
    e = element(2.0, "ball", SP)  # half-widths 1, 2, 4 voxels
    assert e.shape == (3, 5, 9) and e[1, 2, 8] and e[0, 2, 4] and not e[0, 1, 4]
    assert element(2.0, "cube", SP).shape == (3, 5, 9)


@pytest.mark.parametrize("shape", ["ball", "cube"])
@pytest.mark.parametrize("kind", list(OURS))
def test_grey_matches_scipy(data, kind, shape):
    x, _ = data
    fp = element(2.0, shape, SP)
    for mode in ("reflect", "constant"):
        got = OURS[kind](Volume(jnp.asarray(x), spacing=SP), radius=2.0, shape=shape, mode=mode)
        ref = GREY[kind](x, footprint=fp, mode=mode)
        assert float(np.abs(np.asarray(got.data) - ref).max()) <= (1e-15 if kind == "tophat" else 0.0)


@pytest.mark.parametrize("shape", ["ball", "cube"])
def test_binary_is_grey_with_constant_border(data, shape):
    _, m = data
    fp = element(2.0, shape, SP)
    v = Volume(jnp.asarray(m, jnp.float32), spacing=SP)
    for kind, ref_fn in BINARY.items():
        got = OURS[kind](v, radius=2.0, shape=shape, mode="constant")
        assert got.data.dtype == jnp.float32
        assert np.array_equal(np.asarray(got.data) > 0.5, ref_fn(m, structure=fp)), kind


def test_fill_holes_matches_scipy_and_vmaps():
    rng = np.random.default_rng(2)
    masks = np.stack([rng.random(SHAPE) < 0.7, rng.random(SHAPE) < 0.6])
    structs = {6: ndi.generate_binary_structure(3, 1), 18: ndi.generate_binary_structure(3, 2),
               26: np.ones((3, 3, 3), bool)}
    for conn, st in structs.items():
        got = fill_holes3d(Volume(jnp.asarray(masks[0], jnp.float64)), connectivity=conn)
        assert np.array_equal(np.asarray(got.data) > 0.5, ndi.binary_fill_holes(masks[0], st)), conn
    b = jax.jit(jax.vmap(lambda d: fill_holes3d(Volume(d)).data))(jnp.asarray(masks, jnp.float32))
    for i in range(2):
        assert np.array_equal(np.asarray(b[i]) > 0.5, ndi.binary_fill_holes(masks[i]))


def test_vmap_and_float32(data):
    x, _ = data
    xs = jnp.asarray(np.stack([x, x[::-1].copy()]), jnp.float32)
    out = jax.jit(jax.vmap(lambda d: opening3d(Volume(d, spacing=SP), radius=2.0).data))(xs)
    ref = ndi.grey_opening(np.asarray(xs[1]), footprint=element(2.0, "ball", SP))
    assert out.dtype == jnp.float32 and np.array_equal(np.asarray(out[1]), ref)


def test_bad_input_names_op_and_argument():
    v = Volume(jnp.zeros((4, 5, 6)))
    with pytest.raises(ValueError, match="erosion3d: argument 'radius'"):
        erosion3d(v, radius=0.0)
    with pytest.raises(ValueError, match="dilation3d: argument 'shape'"):
        dilation3d(v, shape="disk")
    with pytest.raises(ValueError, match="opening3d: argument 'mode'"):
        opening3d(v, mode="bogus")
    with pytest.raises(ValueError, match="closing3d: argument 'radius'.*bound"):
        closing3d(v, radius=50.0)
    with pytest.raises(TypeError, match="tophat3d: argument 'radius'"):
        jax.jit(lambda r: tophat3d(v, radius=r).data)(1.0)
    with pytest.raises(ValueError, match="fill_holes3d: argument 'connectivity'"):
        fill_holes3d(v, connectivity=4)
