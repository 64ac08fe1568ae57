"""Contours: subpixel_edges, iso_contour, contour features; the exact inspection scenes."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage as ndi
import skimage
from scipy.spatial import cKDTree
from skimage.measure import find_contours

import fsjax
from fsjax.synth._inspection import blurred_disc, step_edge, tilted_edge


def _img(x):
    return fsjax.Image(jnp.asarray(x))


def _polylines(c):
    p, v = np.asarray(c.points), np.asarray(c.valid)
    out, cur = [], []
    for i in range(len(v)):
        if v[i]:
            cur.append(p[i])
        elif cur:
            out.append(np.array(cur))
            cur = []
    if cur:
        out.append(np.array(cur))
    return out


def _canon(a):
    """A polyline as a hashable sequence, independent of orientation and (for loops) start."""
    a = np.round(a, 9)
    if len(a) > 1 and np.array_equal(a[0], a[-1]):
        a = a[:-1]
        seqs = [tuple(map(tuple, np.roll(b, -s, axis=0))) for b in (a, a[::-1]) for s in range(len(b))]
        return ("loop", min(seqs))
    return ("path", min(tuple(map(tuple, a)), tuple(map(tuple, a[::-1]))))


# ---------------------------------------------------------------------------
# the scenes themselves
# ---------------------------------------------------------------------------


def test_scene_rendering_is_exact():
    """The closed-form/quadrature renderer vs brute-force supersampling (which converges to it)."""
    x, t = blurred_disc(centre=(15.3, 16.7), radius=9.25, shape=(32, 32), blur=0.6)
    errs = []
    for s in (8, 16):
        yy, xx = (np.mgrid[0:32 * s, 0:32 * s] + 0.5) / s - 0.5
        ind = ((yy - 15.3) ** 2 + (xx - 16.7) ** 2 <= 9.25**2).astype(float)
        ref = ndi.gaussian_filter(ind, 0.6 * s, mode="constant", truncate=6).reshape(32, s, 32, s).mean(axis=(1, 3))
        errs.append(float(np.abs((x - 0.2) / 0.6 - ref).max()))
    print(f"blurred_disc vs supersampling x8, x16: max |diff| {errs[0]:.4f}, {errs[1]:.4f} (converging)")
    assert errs[1] < errs[0] / 2 and errs[1] < 0.006
    # a tilted edge at 0 degrees is the closed-form vertical step
    a, _ = tilted_edge((4.0, 23.37), 0.0, shape=(9, 48))
    b, _ = step_edge(23.37, shape=(9, 48))
    assert np.abs(a - b).max() < 1e-12


# ---------------------------------------------------------------------------
# subpixel_edges
# ---------------------------------------------------------------------------


def test_subpixel_straight_edges():
    offsets = 23.0 + np.linspace(0.0, 0.95, 8)
    imgs = np.stack([step_edge(e, shape=(9, 48), blur=0.7)[0] for e in offsets])
    f = jax.jit(jax.vmap(lambda x: fsjax.ops.subpixel_edges(fsjax.Image(x), sigma=1.5)))
    c = f(jnp.asarray(imgs))
    errs = []
    for i, e in enumerate(offsets):
        cols = np.asarray(c.points[i][c.valid[i]][:, 1])
        assert len(cols) == 7  # rows 1..7 (the frame is never an edge)
        errs.append(cols.mean() - e)
    errs = np.abs(errs)
    print(f"subpixel_edges, vertical edge at 8 sub-pixel offsets: max |error| {errs.max():.4f} px")
    assert errs.max() <= 0.02
    # a tilted edge (20 degrees): distance of the points to the true line
    x, t = tilted_edge((20.3, 24.6), 20.0, shape=(40, 48), blur=0.7)
    c = fsjax.ops.subpixel_edges(_img(x), sigma=1.5)
    p = np.asarray(c.points[c.valid])
    inner = (p[:, 0] > 6) & (p[:, 0] < 33) & (p[:, 1] > 6) & (p[:, 1] < 41)
    d = (p[inner] - np.array(t["point"])) @ np.array(t["normal"])
    print(f"subpixel_edges, 20 deg edge: mean |distance| {np.abs(d).mean():.4f} px, max {np.abs(d).max():.4f} px "
          f"({inner.sum()} points)")
    assert np.abs(d).mean() <= 0.02 and abs(d.mean()) <= 0.005


def test_subpixel_disc_vs_null():
    x, t = blurred_disc(centre=(40.37, 40.81), radius=30.25, shape=(82, 82), blur=0.6)
    cy, cx = t["centre"]

    def dist(p):
        return np.hypot(p[:, 0] - cy, p[:, 1] - cx) - t["radius"]

    c = fsjax.ops.subpixel_edges(_img(x), sigma=1.0, capacity=512)
    p = np.asarray(c.points[c.valid])
    d = dist(p)
    d_pix = dist(np.round(p))  # null: the same edge pixels without the sub-pixel step
    c2 = fsjax.ops.subpixel_edges(_img(x), sigma=1.0, capacity=512, direction="gradient")
    d2 = dist(np.asarray(c2.points[c2.valid]))
    bias = (0.6**2 + 1.0 + 1 / 12) / (2 * t["radius"])
    print(f"subpixel_edges on a disc (R 30.25, {len(d)} points): mean |dist| {np.abs(d).mean():.4f} px "
          f"(mean {d.mean():+.4f}; curvature bias ~ -{bias:.4f}); direction='gradient' {np.abs(d2).mean():.4f} px; "
          f"null (edge pixel centres) {np.abs(d_pix).mean():.4f} px")
    assert not bool(c.truncated) and len(d) > 150
    assert np.abs(d).mean() <= 0.05
    assert np.abs(d).mean() < np.abs(d_pix).mean() / 5
    assert np.abs(d).mean() < np.abs(d2).mean()


def test_subpixel_capacity_truncates():
    x, _ = blurred_disc(centre=(15.3, 16.7), radius=9.25, shape=(32, 32), blur=0.6)
    full = fsjax.ops.subpixel_edges(_img(x), capacity=256)
    n = int(full.valid.sum())
    part = fsjax.ops.subpixel_edges(_img(x), capacity=n - 5)
    assert not bool(full.truncated) and bool(part.truncated)
    assert bool(jnp.all(part.valid))
    assert np.allclose(np.asarray(part.points), np.asarray(full.points[: n - 5]))
    # nothing above threshold: no points, not truncated
    flat = fsjax.ops.subpixel_edges(_img(np.full((16, 16), 0.5)))
    assert int(flat.valid.sum()) == 0 and not bool(flat.truncated)


# ---------------------------------------------------------------------------
# iso_contour
# ---------------------------------------------------------------------------


def _compare_skimage(x, level, fc="low"):
    c = fsjax.ops.iso_contour(_img(x), level=level, capacity=8192, fully_connected=fc)
    sk = find_contours(x, level, fully_connected=fc)
    P, S = np.asarray(c.points[c.valid]), np.concatenate(sk)
    d_sk = float(cKDTree(P).query(S)[0].max())
    d_fs = float(cKDTree(S).query(P)[0].max())
    pl = _polylines(c)
    same = sorted(map(_canon, sk)) == sorted(map(_canon, pl))
    length_fs = float(fsjax.ops.contour_length(c).value)
    length_sk = sum(float(np.sum(np.hypot(*np.diff(a, axis=0).T))) for a in sk)
    return c, d_sk, d_fs, len(pl), len(sk), same, length_fs, length_sk, len(P), len(S)


@pytest.mark.parametrize("fc", ["low", "high"])
def test_iso_contour_matches_skimage(fc):
    x = skimage.data.coins()[100:228, 100:228] / 255.0
    c, d_sk, d_fs, n_fs, n_sk, same, l_fs, l_sk, v_fs, v_sk = _compare_skimage(x, 0.5, fc)
    print(f"iso_contour vs find_contours (coins 128x128, level 0.5, {fc}): vertices {v_fs} / {v_sk}, "
          f"max dist sk->fs {d_sk:.1e}, fs->sk {d_fs:.1e}; polylines {n_fs} / {n_sk}, identical sequences {same}; "
          f"total length {l_fs:.6f} / {l_sk:.6f}")
    assert not bool(c.truncated)
    assert d_sk <= 1e-9 and d_fs <= 1e-9 and v_fs == v_sk
    assert same and n_fs == n_sk
    assert abs(l_fs - l_sk) < 1e-9 * l_sk
    # random data (no ties), a different size
    r = np.random.default_rng(3).random((23, 31))
    _, d_sk, d_fs, n_fs, n_sk, same, *_ = _compare_skimage(r, 0.5, fc)
    assert d_sk <= 1e-9 and d_fs <= 1e-9 and same and n_fs == n_sk


def test_iso_contour_ties_with_level():
    """Values exactly at the level: scikit-image merges coincident vertices and drops zero-length
    segments; fsjax keeps every grid-edge vertex. Every skimage vertex is an fsjax vertex, and every
    extra fsjax vertex sits on a grid node whose value equals the level."""
    x = np.round(np.random.default_rng(0).random((20, 24)) * 4) / 4
    for fc in ("low", "high"):
        c = fsjax.ops.iso_contour(_img(x), level=0.5, capacity=4096, fully_connected=fc)
        P = np.asarray(c.points[c.valid])
        S = np.concatenate(find_contours(x, 0.5, fully_connected=fc))
        assert cKDTree(P).query(S)[0].max() <= 1e-9
        far = cKDTree(S).query(P)[0] > 1e-9
        extra = P[far]
        on_node = np.all(extra == np.round(extra), axis=1)
        assert on_node.all()
        assert np.all(x[extra[:, 0].astype(int), extra[:, 1].astype(int)] == 0.5)
        print(f"ties ({fc}): {len(P)} fsjax vertices, {len(S)} skimage, {far.sum()} only in fsjax (on level nodes)")


def test_iso_contour_area_orientation_and_features():
    R = 12.3
    x, t = blurred_disc(centre=(24.6, 25.2), radius=R, shape=(50, 50), blur=0.8, lo=0.0, hi=1.0)
    c = fsjax.ops.iso_contour(_img(x), level=0.5, capacity=512)
    polys = _polylines(c)
    assert len(polys) == 1 and np.array_equal(polys[0][0], polys[0][-1])
    area = float(fsjax.ops.contour_area(c).value)
    dark = float(fsjax.ops.contour_area(fsjax.ops.iso_contour(_img(1.0 - x), level=0.5, capacity=512)).value)
    circ = float(fsjax.ops.contour_circularity(c).value)
    length = float(fsjax.ops.contour_length(c).value)
    h = float(fsjax.ops.contour_bbox(c, which="height").value)
    rmin = float(fsjax.ops.contour_bbox(c, which="row_min").value)
    # skimage's polygon area of the same contour (shoelace in numpy) and its perimeter
    sk = find_contours(x, 0.5)[0]
    sk_area = 0.5 * np.sum(sk[:-1, 0] * sk[1:, 1] - sk[1:, 0] * sk[:-1, 1])
    print(f"iso disc R={R}: area {area:.4f} (pi R^2 {math.pi * R * R:.4f}; skimage polygon {abs(sk_area):.4f}), "
          f"dark twin {dark:.4f}, length {length:.4f} (2 pi R {2 * math.pi * R:.4f}), circularity {circ:.5f}, "
          f"bbox height {h:.4f}, row_min {rmin:.4f}")
    assert area > 0 and abs(area + dark) < 1e-9
    assert abs(area - abs(sk_area)) < 1e-9
    assert abs(area - math.pi * R * R) / (math.pi * R * R) < 0.01
    assert abs(length - 2 * math.pi * R) / (2 * math.pi * R) < 0.01
    assert 0.98 < circ <= 1.0
    assert abs(h - 2 * R) < 0.1 and abs(rmin - (24.6 - R)) < 0.05


def test_iso_contour_truncates_and_separates():
    x = np.zeros((12, 20))
    x[2:5, 2:5] = 1.0
    x[6:10, 10:17] = 1.0
    c = fsjax.ops.iso_contour(_img(x), level=0.5, capacity=64)
    polys = _polylines(c)
    assert len(polys) == 2 and not bool(c.truncated)
    n_needed = int(c.valid.sum()) + 1  # one separating gap
    small = fsjax.ops.iso_contour(_img(x), level=0.5, capacity=n_needed - 1)
    assert bool(small.truncated)
    exact = fsjax.ops.iso_contour(_img(x), level=0.5, capacity=n_needed)
    assert not bool(exact.truncated)
    areas = [0.5 * np.sum(p[:-1, 0] * p[1:, 1] - p[1:, 0] * p[:-1, 1]) for p in polys]
    assert np.allclose(sorted(areas), [9 - 0.5, 28 - 0.5])
    assert abs(float(fsjax.ops.contour_area(c).value) - (8.5 + 27.5)) < 1e-12


def test_features_refuse_unordered_points():
    x, _ = blurred_disc(centre=(15.3, 16.7), radius=9.25, shape=(32, 32), blur=0.6)
    c = fsjax.ops.subpixel_edges(_img(x))
    assert bool(jnp.isnan(fsjax.ops.contour_length(c).value))
    assert bool(jnp.isnan(fsjax.ops.contour_area(c).value))
    assert bool(jnp.isnan(fsjax.ops.contour_circularity(c).value))
    # the bounding box works on point sets: the disc spans 2R up to the curvature bias
    h = float(fsjax.ops.contour_bbox(c, which="height").value)
    assert abs(h - 2 * 9.25) < 0.2
    empty = fsjax.Contour(jnp.zeros((4, 2)), valid=jnp.zeros(4, bool))
    assert float(fsjax.ops.contour_length(empty).value) == 0.0
    assert bool(jnp.isnan(fsjax.ops.contour_bbox(empty).value))
    assert bool(jnp.isnan(fsjax.ops.contour_circularity(empty).value))


def test_feature_gradients_fd():
    t = np.linspace(0, 2 * np.pi, 50, endpoint=False)
    pts = jnp.asarray(np.stack([10 + 6 * np.sin(t), 12 + 4 * np.cos(t)], -1))
    d = jnp.asarray(np.random.default_rng(1).standard_normal(pts.shape))
    for op in ("contour_length", "contour_area", "contour_circularity"):
        def f(s, op=op):
            return getattr(fsjax.ops, op)(fsjax.Contour(pts + s * d, closed=True)).value

        g = float(jax.grad(f)(0.0))
        fd = float((f(1e-6) - f(-1e-6)) / 2e-6)
        assert abs(g) > 1e-6 and abs(g - fd) <= 1e-5 * max(1.0, abs(fd)), (op, g, fd)


def test_bad_parameters_raise():
    img = _img(np.zeros((10, 10)))
    with pytest.raises(ValueError, match="subpixel_edges.*sigma"):
        fsjax.ops.subpixel_edges(img, sigma=0.0)
    with pytest.raises(TypeError, match="subpixel_edges.*capacity"):
        fsjax.ops.subpixel_edges(img, capacity=10.5)
    with pytest.raises(ValueError, match="subpixel_edges.*direction"):
        fsjax.ops.subpixel_edges(img, direction="diagonal")
    with pytest.raises(ValueError, match="subpixel_edges.*threshold"):
        fsjax.ops.subpixel_edges(img, threshold=-1.0)
    with pytest.raises(ValueError, match="iso_contour.*fully_connected"):
        fsjax.ops.iso_contour(img, fully_connected="both")
    with pytest.raises(ValueError, match="iso_contour.*capacity"):
        fsjax.ops.iso_contour(img, capacity=0)
    with pytest.raises(ValueError, match="iso_contour.*level"):
        fsjax.ops.iso_contour(img, level=float("nan"))
    c = fsjax.Contour(jnp.zeros((3, 2)))
    with pytest.raises(ValueError, match="contour_bbox.*which"):
        fsjax.ops.contour_bbox(c, which="area")
    with pytest.raises(ValueError, match="contour_length.*max_gap"):
        fsjax.ops.contour_length(c, max_gap=0.0)
    with pytest.raises(ValueError, match="iso_contour.*img"):
        fsjax.ops.iso_contour(fsjax.Image(jnp.zeros((1, 5))))


def test_numbers_from_truncated_inputs_are_nan():
    """Issue 20 sweep (capacity defaults): a length, area or fit of a Contour whose capacity
    overflowed used to be the plausible number of the points that fitted; now NaN / not
    converged, directly, through apply and in a pipeline. An untruncated input is unchanged."""
    x = np.zeros((12, 20))
    x[2:5, 2:5] = 1.0
    x[6:10, 10:17] = 1.0
    full = fsjax.ops.iso_contour(_img(x), level=0.5, capacity=64)
    part = fsjax.ops.iso_contour(_img(x), level=0.5, capacity=8)
    assert bool(part.truncated) and not bool(full.truncated)
    assert math.isfinite(float(fsjax.ops.contour_length(full).value))
    assert math.isnan(float(fsjax.ops.contour_length(part).value))
    assert math.isnan(float(fsjax.apply(part, "contour_area").value))
    f = fsjax.ops.fit_circle(part)
    assert not bool(f.converged) and bool(jnp.all(jnp.isnan(f.params)))
    p = fsjax.pipeline([("iso_contour", {"level": 0.5, "capacity": 8}), "contour_length"])
    assert math.isnan(float(p(_img(x)).value))
    lab = fsjax.ops.label(fsjax.Region(jnp.asarray(x > 0.5)), capacity=1)
    assert bool(lab.truncated) and math.isnan(float(fsjax.ops.mean_area(lab).value))


def test_traced_nan_max_gap_fails_closed():
    """Issue 20 sweep, second pass (tools/sweep_traced_params.py): a traced ``max_gap`` of NaN
    compared false against every gap and gave the plain length / area / circularity, though
    the eager call refuses it; now NaN. In range the traced call equals the eager one."""
    x = np.zeros((12, 20))
    x[2:5, 2:5] = 1.0
    c = fsjax.ops.iso_contour(_img(x), level=0.5, capacity=64)
    f = jax.jit(lambda g: fsjax.ops.contour_length(c, max_gap=g).value)
    assert math.isnan(float(f(jnp.nan)))
    assert float(f(3.0)) == pytest.approx(float(fsjax.ops.contour_length(c, max_gap=3.0).value))
