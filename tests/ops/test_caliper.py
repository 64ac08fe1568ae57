"""Calipers: measure_projection, measure_pos, measure_pairs.

Ground truths come from the exact scenes of ``fsjax.synth._inspection``
(continuous Gaussian blur, then exact pixel-area integration).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage as ndi
import skimage

import fsjax
from fsjax.synth._inspection import bar_code, edge_sweep, shaft, step_edge


def _img(x):
    return fsjax.Image(jnp.asarray(x))


def test_projection_matches_map_coordinates():
    x = skimage.data.camera()[100:228, 200:328] / 255.0
    row, col, ang, length, width = 60.3, 70.8, 27.0, 80, 5
    p = fsjax.ops.measure_projection(_img(x), row=row, col=col, angle_deg=ang, length=length, width=width)
    a = np.radians(ang)
    u = np.array([-np.sin(a), np.cos(a)])
    v = np.array([np.cos(a), np.sin(a)])
    p0 = np.array([row, col]) - length / 2 * u
    k = np.arange(length + 1)[:, None, None]
    j = (np.arange(width) - (width - 1) / 2)[None, :, None]
    pts = p0 + k * u + j * v
    ref = ndi.map_coordinates(x, [pts[..., 0], pts[..., 1]], order=1, mode="nearest").mean(axis=1)
    d = float(np.max(np.abs(np.asarray(p.data) - ref)))
    print(f"measure_projection vs scipy map_coordinates(order=1): max |diff| = {d:.1e}")
    assert d < 1e-12


def test_edge_sweep_subpixel_vs_null():
    """(a) An edge moved across one pixel in 0.05 px steps."""
    imgs, edges = edge_sweep(start=23.0, step=0.05, n=21, shape=(9, 48), blur=0.7)
    f = jax.jit(jax.vmap(lambda x: fsjax.ops.measure_pos(fsjax.Image(x), row=4, col=24.0, length=40, sigma=2.0)))
    e = f(jnp.asarray(imgs))
    assert bool(jnp.all(e.valid.sum(axis=1) == 1))
    err = np.asarray(e.col[:, 0]) - edges
    rms = float(np.sqrt(np.mean(err**2)))
    # null: the pixel of maximum |central difference| along the same row
    prof = imgs[:, 4, :]
    null = np.argmax(np.abs(np.gradient(prof, axis=1)), axis=1).astype(float)
    rms_null = float(np.sqrt(np.mean((null - edges) ** 2)))
    print(f"measure_pos edge sweep (21 positions, blur 0.7, sigma 2): RMS {rms:.4f} px, max {np.abs(err).max():.4f} px; "
          f"null (pixel of max gradient): RMS {rms_null:.3f} px")
    assert rms <= 0.012
    assert rms_null > 0.2 and rms < rms_null / 10


def test_shaft_diameters():
    """(b) A back-lit 3-step shaft with fractional diameters."""
    x, t = shaft()
    f = jax.jit(jax.vmap(lambda c: fsjax.ops.measure_pairs(_img(x), row=t["axis_row"], col=c, angle_deg=-90.0,
                                                          length=50, width=5, sigma=2.5, transition="negative")))
    e = f(jnp.asarray(t["centre_cols"]))
    assert bool(jnp.all(e.valid.sum(axis=1) == 2))
    w = np.asarray(e.width[:, 0])
    err = w - t["diameters"]
    top = np.asarray(e.row[:, 0]) - t["top"]
    bottom = np.asarray(e.row[:, 1]) - t["bottom"]
    print(f"shaft diameters {t['diameters']} measured {np.round(w, 4)}: max |error| {np.abs(err).max():.4f} px "
          f"(edges: top {np.abs(top).max():.4f}, bottom {np.abs(bottom).max():.4f} px)")
    assert np.abs(err).max() <= 0.02
    assert np.allclose(np.asarray(e.width[:, 1]), w)


@pytest.mark.parametrize("ranges,limit", [((2.0, 6.0), 0.5), ((1.6, 5.2), 0.5)])
def test_bar_code_edges(ranges, limit):
    """(c) 45 bars read along one scan line: every edge within +-0.5 px."""
    x, t = bar_code(45, bar_range=ranges, gap_range=ranges)
    e = fsjax.ops.measure_pairs(_img(x), row=t["row"], length=x.shape[1] - 1, width=5, sigma=0.5,
                                transition="negative", capacity=128)
    pos = np.asarray(e.col[e.valid])
    assert pos.shape == (90,) and not bool(e.truncated)
    err = np.abs(pos - t["edges"])
    wid = np.asarray(e.width[e.valid][::2])
    werr = np.abs(wid - (t["bars"][:, 1] - t["bars"][:, 0]))
    print(f"bar code, 45 bars of {ranges[0]}-{ranges[1]} px: max edge error {err.max():.3f} px, "
          f"median {np.median(err):.3f} px; max bar-width error {werr.max():.3f} px")
    assert err.max() <= limit


def test_gradient_wrt_image_fd():
    x, truth = step_edge(23.37, shape=(9, 48), blur=0.7)
    d = np.random.default_rng(0).standard_normal(x.shape)

    def first_pos(t):
        img = fsjax.Image(jnp.asarray(x) + t * jnp.asarray(d))
        return fsjax.ops.measure_pos(img, row=4, col=24.0, length=40, width=3, sigma=1.5).pos[0]

    g = float(jax.grad(first_pos)(0.0))
    h = 1e-5
    fd = float((first_pos(h) - first_pos(-h)) / (2 * h))
    print(f"d pos / d image (random direction): AD {g:.8f}, FD {fd:.8f}")
    assert abs(g) > 1e-6
    assert abs(g - fd) <= 1e-5 * max(1.0, abs(fd))
    # moving the edge itself: the image derivative of the scene w.r.t. the edge column, pushed through
    # the caliper, should move the position by ~1 px per px (exactly 1 up to the sub-pixel bias slope)
    x2, _ = step_edge(23.37 + 1e-4, shape=(9, 48), blur=0.7)
    dx = (x2 - x) / 1e-4
    moved = float(jax.jvp(lambda t: fsjax.ops.measure_pos(fsjax.Image(jnp.asarray(x) + t * jnp.asarray(dx)),
                                                          row=4, col=24.0, length=40, width=3, sigma=1.5).pos[0],
                          (0.0,), (1.0,))[1])
    print(f"d pos / d edge shift via the image: {moved:.4f} (ideal 1)")
    assert abs(moved - 1.0) < 0.1


def test_polarity_and_pairing_semantics():
    # profile along a row: dark 0.1 / bright 0.9 / brighter 1.0 / dark -> edges +, +, -
    prof = np.full(60, 0.1)
    prof[15:] = 0.6
    prof[25:] = 0.95
    prof[40:] = 0.1
    x = np.tile(prof, (5, 1))
    kw = dict(row=2, col=29.5, length=59, sigma=1.0, threshold=0.05)
    img = _img(x)
    pos_all = fsjax.ops.measure_pos(img, **kw)
    pos_p = fsjax.ops.measure_pos(img, polarity="positive", **kw)
    pos_n = fsjax.ops.measure_pos(img, polarity="negative", **kw)
    assert int(pos_all.valid.sum()) == 3
    assert int(pos_p.valid.sum()) == 2 and int(pos_n.valid.sum()) == 1
    assert np.allclose(np.asarray(pos_all.col[:3]), [14.5, 24.5, 39.5], atol=0.05)
    # positive pairs: the inner (adjacent) edges 24.5 -> 39.5
    pp = fsjax.ops.measure_pairs(img, transition="positive", **kw)
    assert int(pp.valid.sum()) == 2
    assert np.allclose(np.asarray(pp.col[:2]), [24.5, 39.5], atol=0.05)
    assert abs(float(pp.width[0]) - 15.0) < 0.05
    # no negative-first pair exists
    pn = fsjax.ops.measure_pairs(img, transition="negative", **kw)
    assert int(pn.valid.sum()) == 0
    # "all": alternating -,+,- (a bright bar then a dark bar) pairs greedily from the left
    prof2 = np.full(60, 0.9)
    prof2[10:20] = 0.1
    prof2[30:40] = 0.1
    x2 = np.tile(prof2, (5, 1))
    pa = fsjax.ops.measure_pairs(_img(x2), transition="all", **kw)
    got = np.asarray(pa.col[pa.valid])
    assert np.allclose(got, [9.5, 19.5, 29.5, 39.5], atol=0.05), got


def test_truncated_at_overflow():
    x, t = bar_code(45)
    e = fsjax.ops.measure_pos(_img(x), row=t["row"], length=x.shape[1] - 1, sigma=0.5, capacity=10)
    assert bool(e.truncated) and int(e.valid.sum()) == 10
    assert np.allclose(np.asarray(e.col), t["edges"][:10], atol=0.5)
    p = fsjax.ops.measure_pairs(_img(x), row=t["row"], length=x.shape[1] - 1, sigma=0.5, capacity=9,
                                transition="negative")
    assert bool(p.truncated) and int(p.valid.sum()) == 8 and not bool(p.valid[8])
    e_full = fsjax.ops.measure_pos(_img(x), row=t["row"], length=x.shape[1] - 1, sigma=0.5, capacity=90)
    assert not bool(e_full.truncated) and int(e_full.valid.sum()) == 90


def test_rotated_caliper_on_disc_edge():
    """A caliper at 30 degrees through a bright disc finds its two edges on the circle."""
    from fsjax.synth._inspection import blurred_disc

    x, t = blurred_disc(centre=(31.6, 32.2), radius=18.4, shape=(64, 64), blur=0.6)
    e = fsjax.ops.measure_pos(_img(x), row=31.6, col=32.2, angle_deg=30.0, length=50, sigma=1.5)
    assert int(e.valid.sum()) == 2
    r = np.hypot(np.asarray(e.row[:2]) - 31.6, np.asarray(e.col[:2]) - 32.2)
    bias = (0.6**2 + 1.5**2 + 1 / 12) / (2 * 18.4)  # curvature bias of a blurred circle, towards its centre
    print(f"rotated caliper on a disc: edge radii {np.round(r, 4)} (true 18.4; curvature bias bound {bias:.3f})")
    assert np.all(np.abs(r - 18.4) < bias + 0.01)
    assert np.allclose(np.asarray(e.pos[:2]), [25 - 18.4, 25 + 18.4], atol=bias + 0.01)


def test_bad_parameters_raise():
    img = _img(np.zeros((20, 30)))
    with pytest.raises(ValueError, match="measure_pos.*polarity"):
        fsjax.ops.measure_pos(img, polarity="up")
    with pytest.raises(ValueError, match="measure_pairs.*transition"):
        fsjax.ops.measure_pairs(img, transition="both")
    with pytest.raises(TypeError, match="measure_pos.*capacity"):
        fsjax.ops.measure_pos(img, capacity=3.5)
    with pytest.raises(ValueError, match="measure_pairs.*capacity"):
        fsjax.ops.measure_pairs(img, capacity=1)
    with pytest.raises(ValueError, match="measure_projection.*width"):
        fsjax.ops.measure_projection(img, width=0)
    with pytest.raises(ValueError, match="measure_pos.*sigma"):
        fsjax.ops.measure_pos(img, sigma=-1.0)
    with pytest.raises(ValueError, match="measure_pos.*threshold"):
        fsjax.ops.measure_pos(img, threshold=-0.1)
    with pytest.raises(ValueError, match="measure_pos.*length"):
        fsjax.ops.measure_pos(img, length=1.0)
    with pytest.raises(ValueError, match="measure_projection.*mode"):
        fsjax.ops.measure_projection(img, mode="edge")
    with pytest.raises(TypeError, match="measure_pos.*length"):
        jax.jit(lambda a: fsjax.ops.measure_pos(img, angle_deg=a))(0.0)
