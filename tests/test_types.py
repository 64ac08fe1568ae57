"""Sort construction and validation."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fsjax


def test_image_refuses_integers_and_records_conversion():
    with pytest.raises(TypeError, match="integer images must be converted with Image.from_uint"):
        fsjax.Image(np.zeros((4, 4), np.uint8))
    img = fsjax.Image.from_uint(np.array([[0, 255], [51, 102]], np.uint8))
    assert img.conversion == "uint8 / 255"
    np.testing.assert_allclose(img.data, [[0, 1], [0.2, 0.4]])
    img12 = fsjax.Image.from_uint(np.array([[4095, 0]], np.uint16), bit_depth=12)
    assert img12.conversion == "uint16 / 4095" and float(img12.data[0, 0]) == 1.0
    with pytest.raises(ValueError, match="exceed bit_depth=12"):
        fsjax.Image.from_uint(np.array([[5000]], np.uint16), bit_depth=12)


def test_shape_messages():
    with pytest.raises(ValueError, match=r"Color\(data=...\): expected shape \(..., 3\), got \(4, 4, 4\)"):
        fsjax.Color(jnp.zeros((4, 4, 4)))
    with pytest.raises(TypeError, match="expected a bool array, got float"):
        fsjax.Region(jnp.zeros((3, 3)))
    with pytest.raises(TypeError, match="a boolean mask is a Region"):
        fsjax.Image(jnp.zeros((3, 3), bool))
    with pytest.raises(ValueError, match="does not match xyz"):
        fsjax.Points(jnp.zeros((5, 3)), valid=jnp.ones(4, bool))
    with pytest.raises(ValueError, match="indices must be in"):
        fsjax.Mesh(jnp.zeros((3, 3)), jnp.array([[0, 1, 3]]))
    with pytest.raises(ValueError, match="zero-length quaternion"):
        fsjax.Gaussians(jnp.zeros((1, 3)), jnp.zeros((1, 3)), jnp.zeros((1, 4)), jnp.zeros(1), jnp.zeros((1, 3)))
    with pytest.raises(ValueError, match="spacing"):
        fsjax.Volume(jnp.zeros((2, 2, 2)), spacing=(1.0, 0.0, 1.0))


def test_sorts_are_pytrees_and_vmap():
    imgs = fsjax.Image(jnp.ones((3, 4, 5)))
    assert imgs.batch_shape == (3,)
    out = jax.vmap(lambda im: fsjax.Image(im.data * 2))(imgs)
    assert isinstance(out, fsjax.Image) and out.data.shape == (3, 4, 5)
    cam = fsjax.Camera.from_intrinsics(500.0, 500.0, 320.0, 240.0, width=640, height=480)
    d = fsjax.Depth(jnp.ones((480, 640)), cam)
    assert d.camera.width == 640 and cam.R.shape == (3, 3)
    lab = fsjax.Labels(jnp.array([[0, 1], [2, 2]]))
    assert int(lab.count) == 2


def test_empty_raster_refused_and_array_protocol():
    """Issue 20 item 6: a 0x0 Image used to be accepted (ops then failed with raw NumPy messages);
    np.asarray(sort) used to give a 0-d object array."""
    for make in (lambda: fsjax.Image(np.zeros((0, 0))), lambda: fsjax.Image(np.zeros((4, 0))),
                 lambda: fsjax.Region(np.zeros((0, 3), bool)), lambda: fsjax.Color(np.zeros((0, 2, 3))),
                 lambda: fsjax.Volume(np.zeros((2, 0, 2)))):
        with pytest.raises(ValueError, match="empty"):
            make()
    img = fsjax.Image(jnp.arange(6.0).reshape(2, 3))
    a = np.asarray(img)
    assert a.shape == (2, 3) and a.dtype == np.asarray(img.data).dtype and a[1, 2] == 5.0
    assert np.asarray(img, dtype=np.float32).dtype == np.float32
    assert np.asarray(fsjax.Points(jnp.zeros((4, 3)))).shape == (4, 3)
    assert float(np.asarray(fsjax.Feature(2.5))) == 2.5
    with pytest.raises(TypeError, match="Mesh has no single array; use one of its fields"):
        np.asarray(fsjax.Mesh(jnp.zeros((3, 3)), jnp.array([[0, 1, 2]])))
