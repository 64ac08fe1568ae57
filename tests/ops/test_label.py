"""Connected components: ``label`` against SciPy/scikit-image array-for-array,
adversarial shapes, capacity overflow, and the component filters."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage as ndi
import skimage.data
import skimage.filters
import skimage.measure
import skimage.morphology
import skimage.segmentation

import fsjax
from fsjax.ops.measure2d._label import cumsum_count, label_array

CONNS = (4, 8)
STRUCT = {4: None, 8: np.ones((3, 3), int)}
CANVAS = (128, 128)


def _scipy(mask, conn):
    lab, n = ndi.label(mask, structure=STRUCT[conn])
    return lab, n


@functools.cache
def _labeller(conn: int, capacity: int = 100_000):
    return jax.jit(lambda m: label_array(m, conn, capacity))


@functools.cache
def _op(name: str, field: str = "data", **static):
    """A jitted ``op(Region(mask), **static)`` returning one field (compiled once per shape)."""
    fn = getattr(fsjax.ops, name)
    return jax.jit(lambda m, **kw: getattr(fn(fsjax.Region(m), **static, **kw), field))


def _run(name, mask, field="data", **static):
    return np.asarray(_op(name, field, **static)(jnp.asarray(mask)))


def _label(mask, conn, capacity=100_000):
    lab, count, trunc, rounds = _labeller(conn, capacity)(jnp.asarray(mask))
    return np.asarray(lab), int(count), bool(trunc), int(rounds)


# ---------------------------------------------------------------------------
# adversarial shapes on one canvas (one compilation per connectivity)
# ---------------------------------------------------------------------------


def _spiral(n: int) -> np.ndarray:
    """A square spiral path of width 1 with a gap of 1 between turns."""
    img = np.zeros((n, n), bool)
    r0, c0, r1, c1 = 0, 0, n - 1, n - 1
    while c0 <= c1 and r0 <= r1:
        img[r0, c0:c1 + 1] = True
        img[r0:r1 + 1, c1] = True
        if r1 - r0 < 2:
            break
        img[r1, c0:c1 + 1] = True
        if c1 - c0 < 2:
            break
        img[r0 + 2:r1 + 1, c0] = True
        img[r0 + 2, c0:c0 + 3] = True
        r0, c0, r1, c1 = r0 + 2, c0 + 2, r1 - 2, c1 - 2
    return img


def _cases() -> dict[str, np.ndarray]:
    h, w = CANVAS
    rng = np.random.default_rng(7)
    c = {}
    c["empty"] = np.zeros(CANVAS, bool)
    c["full"] = np.ones(CANVAS, bool)
    corners = np.zeros(CANVAS, bool)
    corners[0, 0] = corners[0, -1] = corners[-1, 0] = corners[-1, -1] = True
    corners[0, 31] = corners[31, 0] = corners[-1, 17] = corners[40, -1] = True
    c["border_pixels"] = corners
    c["checkerboard"] = np.indices(CANVAS).sum(0) % 2 == 0
    comb = np.zeros(CANVAS, bool)
    comb[0, :] = True
    comb[:, ::2] = True
    c["comb_down"] = comb
    c["comb_up"] = comb[::-1]
    c["comb_sideways"] = comb.T.copy()
    c["spiral"] = _spiral(h - 1).astype(bool).copy()
    c["spiral"] = np.pad(c["spiral"], ((0, 1), (0, 1)))
    snake = np.zeros(CANVAS, bool)
    snake[::2, :] = True
    for i in range(1, h, 2):
        snake[i, 0 if (i // 2) % 2 else w - 1] = True
    c["snake"] = snake
    diag = np.zeros(CANVAS, bool)
    diag[np.arange(h), np.arange(w)] = True
    diag[np.arange(h), w - 1 - np.arange(w)] = True
    c["diagonals"] = diag
    staircase = np.zeros(CANVAS, bool)
    for i in range(0, h - 1, 2):
        staircase[i, i // 2:i // 2 + 2] = True
        staircase[i + 1, i // 2 + 1] = True
    c["staircase"] = staircase
    dots = np.zeros(CANVAS, bool)
    dots[::2, ::2] = True
    c["dots"] = dots
    for p in (0.3, 0.5, 0.6):
        c[f"noise_{p}"] = rng.random(CANVAS) < p
    return c


CASES = _cases()


@pytest.mark.parametrize("conn", CONNS)
def test_label_equals_scipy_on_adversarial_shapes(conn):
    rounds = {}
    for name, mask in CASES.items():
        ref, n = _scipy(mask, conn)
        lab, count, trunc, r = _label(mask, conn)
        assert np.array_equal(lab, ref), f"{name}, connectivity {conn}: labels differ from scipy"
        assert count == n and not trunc, name
        rounds[name] = r
    print(f"connectivity {conn}: {len(CASES)} shapes identical to scipy.ndimage.label; "
          f"union-find rounds: {rounds}")
    # pointer jumping keeps long paths cheap: the 127x127 spiral is one path of ~8000 pixels
    assert rounds["spiral"] <= 12 and rounds["snake"] <= 12


def test_spiral_is_one_long_path():
    # the adversarial case really is adversarial: one component, a geodesic length in the thousands
    m = CASES["spiral"]
    ref, n = _scipy(m, 4)
    assert n == 1 and m.sum() > 7000


@pytest.mark.parametrize("shape", [(1, 13), (13, 1), (31, 33)])
@pytest.mark.parametrize("conn", CONNS)
def test_label_odd_shapes(shape, conn):
    rng = np.random.default_rng(shape[0] * 100 + shape[1])
    worst = 0
    for p in (0.4, 0.7):
        mask = rng.random(shape) < p
        ref, n = _scipy(mask, conn)
        lab, count, _, _ = _label(mask, conn)
        worst = max(worst, int(np.sum(lab != ref)))
        assert count == n
    assert worst == 0


def _coins_mask(size=128):
    img = skimage.data.coins()[:size * 2:2, :size * 2:2].astype(float) / 255.0
    return img, img > skimage.filters.threshold_otsu(img)


@pytest.mark.parametrize("conn", CONNS)
def test_label_real_images_vs_scipy_and_skimage(conn):
    _, coins = _coins_mask()
    blobs = skimage.data.binary_blobs(128, blob_size_fraction=0.06, volume_fraction=0.4, rng=3)
    camera = skimage.data.camera()[::4, ::4] > 100
    for name, mask in (("coins", coins), ("blobs", blobs), ("camera", camera)):
        ref, n = _scipy(mask, conn)
        sk = skimage.measure.label(mask, connectivity=1 if conn == 4 else 2)
        lab, count, _, rounds = _label(mask, conn)
        assert np.array_equal(lab, ref) and np.array_equal(lab, sk), name
        print(f"{name} 128x128, connectivity {conn}: {n} labels, identical to scipy.ndimage.label "
              f"and skimage.measure.label ({rounds} rounds)")


def test_label_op_and_dtype():
    _, coins = _coins_mask()
    out = jax.jit(lambda m: fsjax.ops.label(fsjax.Region(m)))(jnp.asarray(coins))
    ref, n = _scipy(coins, 8)
    assert out.data.dtype == jnp.int32
    assert np.array_equal(np.asarray(out.data), ref) and int(out.count) == n and not bool(out.truncated)
    # eager call (no outer jit) gives the same array
    small = coins[:24, :40]
    eager = fsjax.ops.label(fsjax.Region(jnp.asarray(small)), connectivity=4)
    assert np.array_equal(np.asarray(eager.data), _scipy(small, 4)[0])


def test_label_capacity_overflow():
    dots = CASES["dots"]                       # 4096 isolated pixels
    ref, n = _scipy(dots, 8)
    cap = 100
    lab, count, trunc, _ = _label(dots, 8, capacity=cap)
    assert trunc and count == cap and n == 4096
    # the first `cap` labels (raster order) are kept exactly, the rest dropped to 0
    assert np.array_equal(lab, np.where(ref <= cap, ref, 0))
    lab, count, trunc, _ = _label(dots, 8, capacity=4096)
    assert not trunc and count == 4096 and np.array_equal(lab, ref)
    out = _run("label", dots, "count", capacity=5), _run("label", dots, "truncated", capacity=5)
    assert int(out[0]) == 5 and bool(out[1])


def test_label_vmap_matches_single_calls():
    a, b = CASES["noise_0.5"], CASES["spiral"]
    f = jax.jit(jax.vmap(lambda m: fsjax.ops.label(fsjax.Region(m), capacity=4096).data))
    out = np.asarray(f(jnp.asarray(np.stack([a, b]))))
    assert np.array_equal(out[0], _scipy(a, 8)[0]) and np.array_equal(out[1], _scipy(b, 8)[0])


def test_cumsum_count_exact():
    rng = np.random.default_rng(0)
    for n in (63, 65, 300_001):
        x = rng.random(n) < 0.3
        assert np.array_equal(np.asarray(cumsum_count(jnp.asarray(x))), np.cumsum(x))


# ---------------------------------------------------------------------------
# component filters
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("conn", CONNS)
def test_count_obj_vs_scipy(conn):
    for name in ("checkerboard", "noise_0.5", "dots", "spiral", "empty"):
        got = float(_run("count_obj", CASES[name], "value", connectivity=conn))
        assert got == _scipy(CASES[name], conn)[1], name


@pytest.mark.parametrize("conn", CONNS)
def test_remove_small_vs_skimage(conn):
    _, coins = _coins_mask()
    noisy = coins ^ (np.random.default_rng(1).random(coins.shape) < 0.02)
    f = _op("remove_small", connectivity=conn)
    for min_area in (1, 5, 30, 200):
        got = np.asarray(f(jnp.asarray(noisy), min_area=jnp.asarray(float(min_area))))
        ref = skimage.morphology.remove_small_objects(noisy, max_size=min_area - 1,
                                                      connectivity=1 if conn == 4 else 2)
        assert np.array_equal(got, ref), min_area


def test_remove_small_beats_null_and_opening():
    # ground truth: three large objects; speckle noise of 1-3 pixel specks added
    truth = np.zeros(CANVAS, bool)
    rr, cc = np.mgrid[0:CANVAS[0], 0:CANVAS[1]]
    truth |= (rr - 30) ** 2 + (cc - 30) ** 2 <= 15**2
    truth[60:85, 10:40] = True
    truth |= (np.abs(rr - 70) + np.abs(cc - 70)) <= 14
    rng = np.random.default_rng(3)
    specks = np.zeros_like(truth)
    for _ in range(60):
        r, c = rng.integers(0, CANVAS[0] - 1, 2)
        specks[r:r + rng.integers(1, 3), c:c + rng.integers(1, 3)] = True
    noisy = truth | (specks & ~ndi.binary_dilation(truth, iterations=2))
    out = np.asarray(_op("remove_small")(jnp.asarray(noisy), min_area=10.0))
    opened = ndi.binary_opening(noisy, structure=np.ones((3, 3)))
    err = {"remove_small": int((out != truth).sum()), "null (input)": int((noisy != truth).sum()),
           "3x3 opening": int((opened != truth).sum())}
    print(f"speckle removal, wrong pixels vs ground truth: {err}")
    assert err["remove_small"] == 0 and err["null (input)"] > 0 and err["3x3 opening"] > 0


@pytest.mark.parametrize("conn", CONNS)
def test_clear_border_vs_skimage(conn):
    _, coins = _coins_mask()
    for mask in (coins, CASES["noise_0.3"], CASES["border_pixels"], CASES["comb_down"]):
        got = _run("clear_border", mask, connectivity=conn)
        lab = skimage.measure.label(mask, connectivity=1 if conn == 4 else 2)
        ref = skimage.segmentation.clear_border(lab) > 0
        assert np.array_equal(got, ref)


@pytest.mark.parametrize("conn", CONNS)
def test_largest_component(conn):
    _, coins = _coins_mask()
    for mask in (coins, CASES["noise_0.5"], CASES["noise_0.6"]):
        lab, n = _scipy(mask, conn)
        ref = lab == (np.argmax(np.bincount(lab.ravel())[1:]) + 1)
        got = _run("largest_component", mask, connectivity=conn)
        assert np.array_equal(got, ref)
    # ties go to the first component in raster order; empty stays empty
    tie = np.zeros(CANVAS, bool)
    tie[50:52, 1:3] = True
    tie[1:3, 50:52] = True
    got = _run("largest_component", tie, connectivity=conn)
    assert got[1, 50] and not got[50, 1]
    assert not _run("largest_component", CASES["empty"], connectivity=conn).any()


def test_labels_to_region():
    lab = jax.jit(lambda m: fsjax.ops.label(fsjax.Region(m), capacity=10))(jnp.asarray(CASES["noise_0.3"]))
    reg = fsjax.ops.labels_to_region(lab)
    assert np.array_equal(np.asarray(reg.data), np.asarray(lab.data) != 0)
    assert int(reg.data.sum()) < int(CASES["noise_0.3"].sum())      # truncated labels are gone


# ---------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------


def test_bad_parameters_name_op_and_argument():
    reg = fsjax.Region(jnp.ones((4, 4), bool))
    with pytest.raises(ValueError, match="label.*connectivity"):
        fsjax.ops.label(reg, connectivity=6)
    with pytest.raises(ValueError, match="label.*capacity"):
        fsjax.ops.label(reg, capacity=0)
    with pytest.raises(TypeError, match="label.*capacity"):
        fsjax.ops.label(reg, capacity=2.5)
    with pytest.raises(ValueError, match="remove_small.*min_area"):
        fsjax.ops.remove_small(reg, min_area=-1.0)
    with pytest.raises(ValueError, match="count_obj.*connectivity"):
        fsjax.ops.count_obj(reg, connectivity=2)
    with pytest.raises(TypeError, match="Region"):
        fsjax.ops.label(fsjax.Image(jnp.ones((4, 4))))
