"""Curvature matching in 3-D (fsjax.ops.shape_index_locate3d): the shape-index field against analytic
surfaces (ball 1, cylinder 0.5, saddle 0, a dark ball -1), the op on a ball / cube scene beside its
null, gain and offset invariance, failing closed, float32. Its grid cells run in
tests/ops/test_match3d_shape.py (voxel, points, mesh, Gaussians) and test_match3d_depth.py (depth)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fsjax
from fsjax.ops.match3d._shapeindex3d import shape_index_field
from fsjax.types import reason_code

ops = fsjax.ops


_FIELD = jax.jit(shape_index_field, static_argnums=(1, 2))


def _field(f):
    S, mag = _FIELD(jnp.asarray(f), 1.0, (1.0, 1.0, 1.0))
    return np.asarray(S), np.asarray(mag)


def test_shape_index_field_on_analytic_surfaces():
    """Smooth solids (logistic edge of width 1.5 voxels): the iso-surfaces of a ball of radius 10 are
    spheres (S = 1 up to the grid: >= 0.97, median 0.994, where the gradient is above half its peak), of a cylinder
    cylinders (0.5 to 1e-12), the iso-surfaces of z - (x^2 - y^2)/40 symmetric saddles at the origin (0);
    the ball dark on bright turns caps into cups (-1). Null: the mean curvature's sign alone says
    "convex" for both the ball and the cylinder."""
    k, i, j = (a - 15.5 for a in np.mgrid[0:32, 0:32, 0:32].astype(float))
    ball = 1 / (1 + np.exp((np.sqrt(k * k + i * i + j * j) - 10) / 1.5))
    S, mag = _field(ball)
    m = mag > 0.5 * mag.max()
    assert S[m].min() > 0.97 and np.median(S[m]) > 0.99
    S, mag = _field(1.0 - ball)
    assert S[m].max() < -0.97
    cyl = 1 / (1 + np.exp((np.sqrt(i * i + j * j) - 10) / 1.5))
    S, mag = _field(cyl)
    mc = (mag > 0.5 * mag.max()) & (np.abs(k) < 12)
    assert np.abs(S[mc] - 0.5).max() < 1e-9
    S, _ = _field(-(k - (j * j - i * i) / 40.0))
    assert np.abs(S[15:17, 15:17, 15:17]).max() < 1e-9
    # the null: both the ball and the cylinder have a positive mean curvature
    assert np.sign(np.median(_field(ball)[0][m])) == np.sign(np.median(_field(cyl)[0][mc])) == 1


def _ball_cube_scene(dtype=np.float64):
    k, i, j = np.mgrid[0:30, 0:28, 0:26]

    def ball(c, r):
        return np.clip(r + 0.5 - np.sqrt((k - c[0]) ** 2 + (i - c[1]) ** 2 + (j - c[2]) ** 2), 0, 1)

    def cube(c, r):
        return np.clip(r + 0.5 - np.maximum(np.maximum(abs(k - c[0]), abs(i - c[1])), abs(j - c[2])), 0, 1)

    scene = ball((20, 9, 10), 4.0) + cube((8, 18, 16), 3.5)
    return (fsjax.Volume(jnp.asarray(scene, dtype)), fsjax.Volume(jnp.asarray(ball((7, 7, 7), 4.0)[:15, :15, :15], dtype)),
            fsjax.Volume(jnp.asarray(cube((7, 7, 7), 3.5)[:15, :15, :15], dtype)), scene)


@pytest.mark.parametrize("dtype,tol", [(np.float64, 1e-3), (np.float32, 1e-3)])
def test_shape_index_locate3d_finds_ball_and_cube_and_beats_the_null(dtype, tol):
    """The ball's template lands on the ball ((x, y, z) = (3, 2, 13)), the cube's on the cube ((9, 11, 1));
    the null (the scene's centre of mass, placed as the template's centre) is 6.6 voxels off. A gain and
    an offset of the scene change nothing."""
    scene, tb, tc, raw = _ball_cube_scene(dtype)
    m = ops.shape_index_locate3d(scene, tb)
    assert m.t.dtype == dtype and bool(m.valid) and float(m.score) > 0.99
    assert np.abs(np.asarray(m.t) - [3, 2, 13]).max() < tol
    mc = ops.shape_index_locate3d(scene, tc)
    assert bool(mc.valid) and np.abs(np.asarray(mc.t) - [9, 11, 1]).max() < tol
    k, i, j = np.mgrid[0:30, 0:28, 0:26]
    com = np.array([(raw * a).sum() for a in (j, i, k)]) / raw.sum()
    null = np.linalg.norm(com - 7.0 - [3, 2, 13])
    assert null > 5.0
    mg = ops.shape_index_locate3d(fsjax.Volume(3.0 * scene.data + 2.0), tb)
    assert np.abs(np.asarray(mg.t) - np.asarray(m.t)).max() < 1e-3 and abs(float(mg.score) - float(m.score)) < 1e-3


def test_shape_index_locate3d_fails_closed_and_checks_arguments():
    """A contrast reversal turns the ball into a cup (refused: not found); a flat scene or a flat
    template is invalid input; bad arguments name the op."""
    scene, tb, _, _ = _ball_cube_scene()
    inv = ops.shape_index_locate3d(fsjax.Volume(1.0 - scene.data), tb)
    assert not bool(inv.valid) and int(inv.reason) == reason_code("not_found") and bool(jnp.isnan(inv.t).all())
    flat = ops.shape_index_locate3d(fsjax.Volume(jnp.ones((30, 28, 26))), tb)
    assert not bool(flat.valid) and int(flat.reason) == reason_code("invalid_input")
    ft = ops.shape_index_locate3d(scene, fsjax.Volume(jnp.zeros((15, 15, 15))))
    assert not bool(ft.valid) and int(ft.reason) == reason_code("invalid_input")
    with pytest.raises(ValueError, match="shape_index_locate3d: argument 'bins'"):
        ops.shape_index_locate3d(scene, tb, bins=2)
    with pytest.raises(ValueError, match="shape_index_locate3d: argument 'sigma'"):
        ops.shape_index_locate3d(scene, tb, sigma=0.0)
    with pytest.raises(ValueError, match="shape_index_locate3d: argument 'template'"):
        ops.shape_index_locate3d(tb, scene)
