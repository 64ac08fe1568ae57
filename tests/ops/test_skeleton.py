"""Thinning: exact conformance with scikit-image's Guo-Hall ``thin``, agreement with its
Zhang-Suen ``skeletonize``, topology ground truths beside the published Zhang-Suen null,
endpoints and junctions of T and + shapes."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage as ndi
import skimage.data
from skimage.measure import euler_number
from skimage.morphology import skeletonize, thin

from fsjax import Image, Region
from fsjax.ops import skeleton, skeleton_endpoints, skeleton_junctions

N = 128


def _sk(mask, **kw):
    return np.asarray(skeleton(Region(np.asarray(mask, bool)), **kw).data)


def _n_components(mask):
    return ndi.label(mask, np.ones((3, 3)))[1]


@pytest.fixture(scope="module")
def scenes():
    rng = np.random.default_rng(0)
    return {
        "coins > 100": skimage.data.coins()[60:60 + N, 60:60 + N] > 100,
        "horse": ~skimage.data.horse()[::2, ::2][:N, :N],
        "opened noise": ndi.binary_opening(rng.random((N, N)) > 0.45),
    }


def test_guo_hall_equals_skimage_thin(scenes):
    diffs = {k: int((_sk(m) != thin(m)).sum()) for k, m in scenes.items()}
    print(f"skeleton(method='guo_hall') vs skimage.morphology.thin ({N}x{N}): differing pixels {diffs}")
    assert all(v == 0 for v in diffs.values())


def test_zhang_vs_skimage_skeletonize(scenes):
    worst_all, worst_iou = 1.0, 1.0
    for name, m in scenes.items():
        z, s = _sk(m, method="zhang"), skeletonize(m)
        agree = (z == s).mean()
        iou = (z & s).sum() / (z | s).sum()
        worst_all, worst_iou = min(worst_all, agree), min(worst_iou, iou)
        print(f"zhang vs skimage.morphology.skeletonize ({name}): {100 * agree:.2f}% of pixels equal, "
              f"skeleton IoU {iou:.3f} ({s.sum()} skimage skeleton px)")
    # skimage's look-up table modifies the published rules (it keeps 2x2 squares)
    assert worst_all >= 0.98 and worst_iou >= 0.75


@pytest.mark.parametrize("method", ["guo_hall", "zhang"])
def test_bar_thins_to_centre_line_of_right_length(method):
    w, length = 5, 31
    m = np.zeros((16, 40), bool)
    m[4:4 + w, 3:3 + length] = True
    sk = _sk(m, method=method)
    rows = sorted(set(np.nonzero(sk)[0].tolist()))
    n = int(sk.sum())
    print(f"{w}x{length} bar, {method}: one row {rows}, {n} px (medial segment: {length - w + 1} px)")
    assert rows == [4 + w // 2]  # one pixel wide, on the centre row
    if method == "guo_hall":
        assert n == length - w + 1
    else:
        assert abs(n - (length - w + 1)) <= 1


def test_ring_stays_one_closed_loop():
    rr, cc = np.mgrid[0:N, 0:N] - 63.5
    d2 = rr ** 2 + cc ** 2
    ring = (d2 <= 40 ** 2) & (d2 > 31 ** 2)
    sk = _sk(ring)
    ends = np.asarray(skeleton_endpoints(Region(sk)).data)
    junc = np.asarray(skeleton_junctions(Region(sk)).data)
    print(f"ring (radii 31-40): skeleton {sk.sum()} px, components {_n_components(sk)}, "
          f"Euler number {euler_number(sk, connectivity=2)} (ring: {euler_number(ring, connectivity=2)}), "
          f"{ends.sum()} end points, {junc.sum()} junctions")
    assert _n_components(sk) == 1 and euler_number(sk, connectivity=2) == 0
    assert ends.sum() == 0 and junc.sum() == 0


def test_topology_preserved_beside_published_zhang_suen_null(scenes):
    """Guo-Hall keeps every 8-connected component and hole; the published Zhang-Suen rules
    (the null) erase 2x2 squares, so small blobs vanish."""
    m = scenes["coins > 100"].copy()
    for r0, c0 in [(3, 3), (3, 120), (120, 3), (60, 120)]:  # isolated 2x2 squares
        m[r0 - 2:r0 + 4, c0 - 2:c0 + 4] = False
        m[r0:r0 + 2, c0:c0 + 2] = True
    rows = []
    for name, x in [("input", m), ("guo_hall", _sk(m)), ("zhang (null)", _sk(m, method="zhang"))]:
        rows.append((name, _n_components(x), euler_number(x, connectivity=2)))
    print("components / Euler number (8-connectivity): "
          + ", ".join(f"{n}: {c} / {e}" for n, c, e in rows))
    assert rows[1][1:] == rows[0][1:]
    assert rows[2][1] < rows[0][1]
    for name, x in scenes.items():
        sk = _sk(x)
        assert _n_components(sk) == _n_components(x), name
        assert euler_number(sk, connectivity=2) == euler_number(x, connectivity=2), name


def test_skeleton_is_subset_and_idempotent(scenes):
    for name, m in scenes.items():
        sk = _sk(m)
        assert not (sk & ~m).any(), name
        assert np.array_equal(_sk(sk), sk), name  # nothing left to delete: converged


def _thick_t():
    t = np.zeros((40, 40), bool)
    t[5:11, 4:36] = True
    t[5:35, 17:23] = True
    return t


def _thick_plus():
    t = np.zeros((40, 40), bool)
    t[17:24, 3:37] = True
    t[3:37, 17:24] = True
    return t


@pytest.mark.parametrize("method", ["guo_hall", "zhang"])
def test_endpoints_and_junctions_of_t_and_plus(method):
    got = {}
    for name, shape in (("T", _thick_t()), ("+", _thick_plus())):
        sk = skeleton(Region(shape), method=method)
        got[name] = (int(skeleton_endpoints(sk).data.sum()), int(skeleton_junctions(sk).data.sum()))
    print(f"{method}: (end points, junctions) of thinned thick shapes {got}")
    assert got == {"T": (3, 1), "+": (4, 1)}


def test_vmap_equals_separate_calls(scenes):
    a, b = scenes["coins > 100"], scenes["horse"]
    out = jax.jit(jax.vmap(lambda m: skeleton(Region(m)).data))(jnp.stack([a, b]))
    assert np.array_equal(np.asarray(out[0]), _sk(a)) and np.array_equal(np.asarray(out[1]), _sk(b))


def test_bad_input_raises():
    with pytest.raises(ValueError, match="skeleton: argument 'method'"):
        skeleton(Region(np.ones((4, 4), bool)), method="lee")
    with pytest.raises(TypeError, match="skeleton_endpoints"):
        skeleton_endpoints(Image(np.zeros((4, 4))))
