"""Binary morphology on Region: conformance with scipy.ndimage on thresholded
photographs and synthetic masks, fill_holes ground truths, nulls, bad input."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage as ndi
from skimage import data, filters
from skimage import morphology as skm

import fsjax
from fsjax.ops import (
    boundary,
    fill_holes,
    region_and,
    region_close,
    region_difference,
    region_dilate,
    region_erode,
    region_not,
    region_open,
    region_or,
    region_xor,
)


def _otsu(img):
    return img > filters.threshold_otsu(img)


COINS = _otsu(data.coins()[::2, ::2])  # 152 x 192, coins with holes
CAMERA = _otsu(data.camera()[::4, ::4])  # 128 x 128, touches the image border
MASKS = {"coins": COINS, "camera": CAMERA}


def footprint(r: int, shape: str) -> np.ndarray:
    if shape == "disk":
        return skm.disk(r).astype(bool)
    return np.ones((2 * r + 1, 2 * r + 1), bool)


def run(op, m, **kw):
    return np.asarray(op(fsjax.Region(jnp.asarray(m)), **kw).data)


# ---------------------------------------------------------------------------
# Erosion / dilation / opening / closing vs scipy.ndimage
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(MASKS))
@pytest.mark.parametrize("shape", ["disk", "square"])
def test_erode_dilate_vs_scipy(name, shape):
    m = MASKS[name]
    total = 0
    for r in (1, 3):
        fp = footprint(r, shape)
        refs = {
            "erode ignore (border_value=1)": (run(region_erode, m, radius=r, shape=shape),
                                              ndi.binary_erosion(m, fp, border_value=1)),
            "erode background (border_value=0)": (run(region_erode, m, radius=r, shape=shape, border="background"),
                                                  ndi.binary_erosion(m, fp, border_value=0)),
            "dilate (border_value=0)": (run(region_dilate, m, radius=r, shape=shape),
                                        ndi.binary_dilation(m, fp)),
            "dilate background": (run(region_dilate, m, radius=r, shape=shape, border="background"),
                                  ndi.binary_dilation(m, fp)),
        }
        for label, (ours, ref) in refs.items():
            n = int(np.sum(ours != ref))
            print(f"{name} {shape} r={r} {label}: {n} differing pixels")
            total += n
    assert total == 0


@pytest.mark.parametrize("name", list(MASKS))
def test_open_close_vs_scipy(name):
    m = MASKS[name]
    fp = footprint(2, "disk")
    refs = {
        "open ignore vs dilate(erode(bv=1))": (
            run(region_open, m, radius=2), ndi.binary_dilation(ndi.binary_erosion(m, fp, border_value=1), fp)),
        "close ignore vs erode(dilate, bv=1)": (
            run(region_close, m, radius=2), ndi.binary_erosion(ndi.binary_dilation(m, fp), fp, border_value=1)),
        "open background vs binary_opening": (
            run(region_open, m, radius=2, border="background"), ndi.binary_opening(m, fp)),
        "close background vs binary_closing": (
            run(region_close, m, radius=2, border="background"), ndi.binary_closing(m, fp)),
    }
    total = 0
    for label, (ours, ref) in refs.items():
        n = int(np.sum(ours != ref))
        print(f"{name}: {label}: {n} differing pixels")
        total += n
    assert total == 0
    # the two border conventions really differ on a mask touching the border
    if name == "camera":
        assert np.any(run(region_erode, m, radius=2) != run(region_erode, m, radius=2, border="background"))


def test_laws():
    m = COINS
    o, c = run(region_open, m, radius=2), run(region_close, m, radius=2)
    assert np.all(o <= m) and np.all(m <= c)  # anti-extensive / extensive ("ignore")
    assert np.array_equal(run(region_open, o, radius=2), o)
    assert np.array_equal(run(region_close, c, radius=2), c)
    # duality under "ignore": erode(m) = ~dilate(~m)
    assert np.array_equal(run(region_erode, m, radius=3), ~run(region_dilate, ~m, radius=3))


@pytest.mark.parametrize("op", [region_erode, region_open])
def test_traced_radius_equals_concrete(op):
    m = jnp.asarray(COINS[:64, :64])
    radii = jnp.array([0.0, 1.0, 1.5, 4.0, 8.0])
    for shape in ("disk", "square"):
        batch = jax.jit(jax.vmap(lambda r, s=shape: op(fsjax.Region(m), radius=r, shape=s).data))(radii)
        for i, r in enumerate(np.asarray(radii)):
            ref = np.asarray(op(fsjax.Region(m), radius=float(r), shape=shape).data)
            assert np.array_equal(np.asarray(batch[i]), ref), (shape, r)


def test_traced_radius_beyond_support_raises():
    m = jnp.asarray(COINS[:32, :32])
    # a bool mask has no NaN, so an out-of-support traced radius raises at run time
    f = eqx.filter_jit(lambda r: region_dilate(fsjax.Region(m), radius=r, max_radius=3).data)
    assert np.array_equal(np.asarray(f(jnp.asarray(3.0))), ndi.binary_dilation(np.asarray(m), skm.disk(3).astype(bool)))
    with pytest.raises(eqx.EquinoxRuntimeError, match="region_dilate.*max_radius"):
        jax.block_until_ready(f(jnp.asarray(4.0)))
    with pytest.raises(Exception, match="region_dilate.*max_radius"):  # plain jax.jit wraps it
        jax.block_until_ready(jax.jit(lambda r: region_dilate(fsjax.Region(m), radius=r, max_radius=3).data)(-1.0))


# ---------------------------------------------------------------------------
# fill_holes
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(MASKS))
def test_fill_holes_vs_scipy_real(name):
    m = MASKS[name]
    for conn, structure in ((4, None), (8, np.ones((3, 3), bool))):
        ref = ndi.binary_fill_holes(m, structure=structure)
        ours = run(fill_holes, m, connectivity=conn)
        n = int(np.sum(ours != ref))
        print(f"fill_holes {name} (connectivity {conn}) vs scipy.binary_fill_holes: {n} differing pixels; "
              f"{int(ref.sum() - m.sum())} hole pixels filled")
        assert n == 0
    if name == "coins":
        assert ndi.binary_fill_holes(m).sum() > m.sum()  # the case is not trivial


def rings_scene(rng, n=6, size=(96, 128)):
    h, w = size
    rr, cc = np.mgrid[0:h, 0:w]
    m = np.zeros(size, bool)
    truth = np.zeros(size, bool)
    for _ in range(n):
        cy, cx = rng.uniform(-5, h + 5), rng.uniform(-5, w + 5)
        ro = rng.uniform(5, 18)
        ri = ro - rng.uniform(1.0, 4.0)
        d2 = (rr - cy) ** 2 + (cc - cx) ** 2
        m |= (d2 <= ro**2) & (d2 > ri**2)
        truth |= d2 <= ro**2
    return m, truth


def test_fill_holes_synthetic_rings():
    rng = np.random.default_rng(7)
    masks = [rings_scene(rng)[0] for _ in range(6)]
    batch = jnp.asarray(np.stack(masks))
    filled = np.asarray(jax.jit(jax.vmap(lambda x: fill_holes(fsjax.Region(x)).data))(batch))
    for conn, structure in ((4, None), (8, np.ones((3, 3), bool))):
        bad = 0
        for i, m in enumerate(masks):
            ref = ndi.binary_fill_holes(m, structure=structure)
            ours = filled[i] if conn == 4 else run(fill_holes, m, connectivity=8)
            bad += int(np.sum(ours != ref))
        print(f"fill_holes on 6 random ring scenes (connectivity {conn}): {bad} pixels differ from scipy")
        assert bad == 0


def test_fill_holes_ground_truths():
    rr, cc = np.mgrid[0:40, 0:40]
    d2 = (rr - 20) ** 2 + (cc - 20) ** 2
    disk = d2 <= 14**2
    # a thick ring fills to the full disk
    assert np.array_equal(run(fill_holes, disk & (d2 > 8**2)), disk)
    # a ring cut open by the image border is not closed: nothing to fill
    shifted = np.roll(disk & (d2 > 8**2), 30, axis=1)
    shifted[:, :10] = False
    assert np.array_equal(run(fill_holes, shifted), shifted)
    # a 1-pixel 8-connected circle (inner boundary with connectivity 4) has diagonal
    # gaps: the inside is a hole for a 4-connected background, not for an 8-connected one
    curve = run(boundary, disk, connectivity=4)
    assert np.array_equal(run(fill_holes, curve, connectivity=4), disk)
    assert np.array_equal(run(fill_holes, curve, connectivity=8), curve)
    # nested: a ring inside the hole of another ring; everything inside is filled
    nested = (disk & (d2 > 10**2)) | ((d2 <= 6**2) & (d2 > 3**2))
    assert np.array_equal(run(fill_holes, nested), disk)
    # empty and full masks
    assert not run(fill_holes, np.zeros((8, 9), bool)).any()
    assert run(fill_holes, np.ones((8, 9), bool)).all()


def zigzag_maze(n=41):
    """Concentric square walls, each with one gap, the gaps alternating corners.

    The background inside is connected to the border only through a path that
    winds around every ring (many turns)."""
    wall = np.zeros((n, n), bool)
    for k in range(0, n // 2, 2):
        wall[k, k:n - k] = wall[n - 1 - k, k:n - k] = True
        wall[k:n - k, k] = wall[k:n - k, n - 1 - k] = True
        if k:
            if (k // 2) % 2:
                wall[k, k + 1] = False  # gap near the top-left corner
            else:
                wall[n - 1 - k, n - 2 - k] = False  # gap near the bottom-right corner
    return wall


def test_fill_holes_long_winding_path():
    wall = zigzag_maze()
    # outer wall closed: the whole maze is one hole
    assert np.array_equal(run(fill_holes, wall), ndi.binary_fill_holes(wall))
    assert run(fill_holes, wall).all()
    # open the outer wall: the winding corridor reaches the border, nothing is a hole
    opened = wall.copy()
    opened[0, 20] = False
    ours = run(fill_holes, opened)
    print(f"winding maze: {int(np.sum(ours != ndi.binary_fill_holes(opened)))} pixels differ from scipy")
    assert np.array_equal(ours, ndi.binary_fill_holes(opened))
    assert np.array_equal(ours, opened)


# ---------------------------------------------------------------------------
# boundary
# ---------------------------------------------------------------------------


def test_boundary_vs_scipy_and_ground_truth():
    for name, m in MASKS.items():
        for conn, st in ((4, ndi.generate_binary_structure(2, 1)), (8, np.ones((3, 3), bool))):
            for border, bv in (("ignore", 1), ("background", 0)):
                ref = m & ~ndi.binary_erosion(m, st, border_value=bv)
                n = int(np.sum(run(boundary, m, connectivity=conn, border=border) != ref))
                print(f"boundary {name} conn={conn} border={border}: {n} differing pixels")
                assert n == 0
    rect = np.zeros((12, 14), bool)
    rect[3:9, 2:12] = True  # 6 x 10
    for conn in (4, 8):
        assert run(boundary, rect, connectivity=conn).sum() == 2 * 6 + 2 * 10 - 4
    # touching the top edge: "ignore" does not count the edge, "background" does
    top = np.zeros((12, 14), bool)
    top[0:6, 2:12] = True
    assert run(boundary, top).sum() == 2 * 6 + 10 - 2
    assert run(boundary, top, border="background").sum() == 2 * 6 + 2 * 10 - 4
    # 8-connectivity boundary of a disk is a superset of the 4-connectivity one
    rr, cc = np.mgrid[0:30, 0:30]
    disk = (rr - 15) ** 2 + (cc - 15) ** 2 <= 100
    b4, b8 = run(boundary, disk, connectivity=4), run(boundary, disk, connectivity=8)
    assert np.all(b4 <= b8) and b8.sum() > b4.sum()


# ---------------------------------------------------------------------------
# Set ops
# ---------------------------------------------------------------------------


def test_set_ops():
    a = COINS[:128, :128]
    b = CAMERA
    ra, rb = fsjax.Region(jnp.asarray(a)), fsjax.Region(jnp.asarray(b))
    assert np.array_equal(np.asarray(region_and(ra, rb).data), a & b)
    assert np.array_equal(np.asarray(region_or(ra, rb).data), a | b)
    assert np.array_equal(np.asarray(region_xor(ra, rb).data), a ^ b)
    assert np.array_equal(np.asarray(region_difference(ra, rb).data), a & ~b)
    assert np.array_equal(np.asarray(region_not(ra).data), ~a)
    # inclusion-exclusion
    assert (a | b).sum() == a.sum() + b.sum() - (a & b).sum()
    with pytest.raises(ValueError, match="region_xor.*same shape"):
        region_xor(ra, fsjax.Region(jnp.zeros((4, 4), bool)))


# ---------------------------------------------------------------------------
# Nulls: salt / pepper on a clean mask
# ---------------------------------------------------------------------------


def clean_mask():
    m = np.zeros((96, 96), bool)
    m[8:30, 10:40] = True
    m[50:85, 15:35] = True
    m[40:70, 55:90] = True
    return m


def test_open_beats_null_on_salt():
    rng = np.random.default_rng(3)
    clean = clean_mask()
    noisy = clean | (rng.random(clean.shape) < 0.05)
    err_null = np.mean(noisy != clean)
    err_open = np.mean(run(region_open, noisy, radius=1, shape="square") != clean)
    err_close = np.mean(run(region_close, noisy, radius=1, shape="square") != clean)
    print(f"salt 5%: pixel error rate vs clean mask: noisy (null) {err_null:.4f}, "
          f"3x3 opening {err_open:.4f}, 3x3 closing (wrong tool) {err_close:.4f}")
    assert err_open < 0.1 * err_null
    assert err_close > err_null


def test_close_beats_null_on_pepper():
    rng = np.random.default_rng(4)
    clean = clean_mask()
    noisy = clean & ~(rng.random(clean.shape) < 0.05)
    err_null = np.mean(noisy != clean)
    err_close = np.mean(run(region_close, noisy, radius=1, shape="square") != clean)
    print(f"pepper 5%: pixel error rate vs clean mask: noisy (null) {err_null:.4f}, 3x3 closing {err_close:.4f}")
    assert err_close < 0.1 * err_null


# ---------------------------------------------------------------------------
# Bad input
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("op", [region_erode, region_dilate, region_open, region_close])
def test_bad_parameters(op):
    reg = fsjax.Region(jnp.asarray(COINS[:16, :16]))
    name = op.__name__
    with pytest.raises(ValueError, match=rf"{name}.*'radius'"):
        op(reg, radius=-2)
    with pytest.raises(ValueError, match=rf"{name}.*'shape'"):
        op(reg, shape="diamond")
    with pytest.raises(ValueError, match=rf"{name}.*'border'"):
        op(reg, border="wrap")
    with pytest.raises(TypeError, match=rf"{name}.*'max_radius'"):
        op(reg, max_radius=None)
    with pytest.raises(TypeError, match=rf"{name}.*Region"):
        op(fsjax.Image(jnp.zeros((4, 4))))


def test_bad_parameters_fill_boundary():
    reg = fsjax.Region(jnp.asarray(COINS[:16, :16]))
    with pytest.raises(ValueError, match="fill_holes.*'connectivity'"):
        fill_holes(reg, connectivity=6)
    with pytest.raises(ValueError, match="boundary.*'connectivity'"):
        boundary(reg, connectivity=2)
    with pytest.raises(ValueError, match="boundary.*'border'"):
        boundary(reg, border="outside")


def test_huge_radius_costs_no_more_than_the_image_and_is_exact():
    """Issue 20 sweep (cost growing with one argument; tools/sweep_traced_params.py): a concrete
    radius built a (2R + 1)-segment element whatever the image (radius=1e4 on 24 x 32 ran
    > 40 s). An element wider than the image's diagonal covers every pixel from every pixel
    under the constant border, so it is cut there: the traced program for radius 300 is the
    one for the diagonal (before: 2,405 equations vs 85), and the masks are equal."""
    m = jnp.zeros((6, 8), bool).at[2, 3].set(True).at[5, 0].set(True)
    reg = fsjax.Region(m)
    diag = 10  # ceil(hypot(6, 8))
    for op, shape in ((region_dilate, "disk"), (region_erode, "square")):
        n_big = len(jax.make_jaxpr(lambda d, op=op, shape=shape: op(fsjax.Region(d), radius=300, shape=shape).data)(m).eqns)
        n_cut = len(jax.make_jaxpr(lambda d, op=op, shape=shape: op(fsjax.Region(d), radius=diag, shape=shape).data)(m).eqns)
        assert n_big == n_cut
    big = region_dilate(reg, radius=300)
    assert bool(jnp.all(big.data))  # every pixel is within the diagonal of a set pixel
    assert bool(jnp.array_equal(region_dilate(reg, radius=300, border="background").data, big.data))
    assert not bool(jnp.any(region_erode(reg, radius=300, border="background").data))
