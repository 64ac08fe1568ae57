"""Neighbour search (knn, radius_search) against scipy.spatial.cKDTree: exact sets and distances."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import cKDTree

from fsjax import Mesh
from fsjax.data import bunny, mesh_arrays
from fsjax.ops import knn, radius_search, sample_surface
from fsjax.synth._pool import icosphere

RTOL = 8 * np.finfo(np.float64).eps


def _d2(ref, q, idx):
    """Squared distances in the same summation order as fsjax (x, y, z)."""
    p = ref[np.clip(idx, 0, None)]
    d = p - q[:, None, :]
    out = (d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]) + d[..., 2] * d[..., 2]
    return np.where(idx >= 0, out, np.inf)


def _check_knn(ref, q, k, idx, d2, valid=None):
    """Exactness vs cKDTree. Returns the number of query rows compared."""
    idx, d2 = np.asarray(idx), np.asarray(d2)
    sel = np.arange(len(ref)) if valid is None else np.flatnonzero(valid)
    tree = cKDTree(ref[sel])
    kk = min(k, len(sel))
    dt, it = tree.query(q, kk)
    it = sel[np.asarray(it).reshape(len(q), kk)]
    assert idx.shape == (len(q), k) and idx.dtype == np.int32
    # our distances are the true distances of the returned indices (to rounding: XLA may fuse
    # multiply-adds), ascending
    np.testing.assert_allclose(d2, _d2(ref, q, idx), rtol=RTOL, atol=0)
    assert np.all(np.diff(d2[:, :kk], axis=1) >= 0)
    # missing neighbours when fewer than k valid points
    assert np.all(idx[:, kk:] == -1) and np.all(np.isinf(d2[:, kk:]))
    assert np.all(idx[:, :kk] >= 0)
    # the multiset of distances equals cKDTree's (recomputed exactly from its indices)
    np.testing.assert_allclose(d2[:, :kk], np.sort(_d2(ref, q, it), axis=1), rtol=RTOL, atol=0)
    np.testing.assert_allclose(d2[:, :kk], np.asarray(dt).reshape(len(q), kk) ** 2, rtol=1e-12, atol=1e-300)
    # identical sets up to ties at the k-th distance
    kth = _d2(ref, q, idx)[:, kk - 1:kk] * (1 - RTOL)
    for j in range(len(q)):
        a = set(idx[j, :kk][_d2(ref, q[j:j + 1], idx[j:j + 1, :kk])[0] < kth[j]].tolist())
        b = set(it[j][_d2(ref, q[j:j + 1], it[j:j + 1])[0] < kth[j]].tolist())
        assert a == b
    if valid is not None:
        assert np.all(np.asarray(valid)[idx[idx >= 0]])
    return len(q)


def _check_radius(ref, q, r, cap, out, valid=None):
    idx, d2, cnt, trunc = (np.asarray(a) for a in out)
    sel = np.arange(len(ref)) if valid is None else np.flatnonzero(valid)
    lists = cKDTree(ref[sel]).query_ball_point(q, r)
    true_cnt = np.array([len(x) for x in lists])
    np.testing.assert_array_equal(cnt, true_cnt)
    np.testing.assert_array_equal(trunc, true_cnt > cap)
    np.testing.assert_allclose(d2, _d2(ref, q, idx), rtol=RTOL, atol=0)
    for j in range(len(q)):
        mine = idx[j][idx[j] >= 0]
        assert len(mine) == min(cap, true_cnt[j])
        truth = sel[np.asarray(lists[j], dtype=int)]
        if true_cnt[j] <= cap:
            assert set(mine.tolist()) == set(truth.tolist())
        else:  # the nearest `cap` of the true set
            td = np.sort(_d2(ref, q[j:j + 1], truth[None])[0])
            np.testing.assert_allclose(d2[j, : len(mine)], td[:cap], rtol=RTOL, atol=0)
            assert set(mine.tolist()) <= set(truth.tolist())
        assert np.all(np.diff(d2[j, : len(mine)]) >= 0)
    return int(true_cnt.max())


def _clouds():
    rng = np.random.default_rng(7)
    uni = rng.random((3000, 3))
    # ties and duplicates: a coarse integer lattice, every point twice
    lat = np.stack(np.meshgrid(np.arange(10.0), np.arange(10.0), np.arange(15.0), indexing="ij"),
                   -1).reshape(-1, 3)
    dup = np.concatenate([lat, lat])[rng.permutation(2 * len(lat))]
    # clustered: 10 tight Gaussian blobs in a big box plus sparse background
    centres = rng.random((10, 3)) * 20
    clus = np.concatenate([centres[rng.integers(0, 10, 2800)] + 0.05 * rng.normal(size=(2800, 3)),
                           rng.random((200, 3)) * 20])
    # planar: z = 0 exactly (degenerate extent along z)
    plane = np.concatenate([rng.random((3000, 2)), np.zeros((3000, 1))], axis=1)
    # bunny vertices (real scan)
    v, _ = mesh_arrays("bunny")
    bun = v[rng.choice(len(v), 3000, replace=False)]
    sampled = np.asarray(sample_surface(bunny(), n=3000, seed=3).xyz)
    return {"uniform": uni, "lattice_dup": dup, "clustered": clus, "planar": plane, "bunny": bun,
            "bunny_sampled": sampled}


NAMES = ["uniform", "lattice_dup", "clustered", "planar", "bunny", "bunny_sampled"]


@pytest.mark.parametrize("name", NAMES)
def test_knn_exact_vs_ckdtree(name):
    ref = _clouds()[name]
    rng = np.random.default_rng(1)
    lo, hi = ref.min(0), ref.max(0)
    # queries: half on reference points (self-neighbours, ties), half random in the box
    q = np.concatenate([ref[rng.choice(len(ref), 300)], lo + (hi - lo) * rng.random((300, 3))])
    if name == "lattice_dup":
        q[:50] = np.round(q[:50]) + 0.5  # equidistant to 8 lattice points x2 duplicates
    rows = 0
    for k in (1, 8, 32):
        for method in ("grid", "brute"):
            idx, d2 = knn(ref, q, k, method=method)
            rows += _check_knn(ref, q, k, idx, d2)
    print(f"knn {name}: {len(ref)} refs, {rows} query rows identical to cKDTree (k = 1, 8, 32; grid and brute)")


@pytest.mark.parametrize("name", NAMES)
def test_radius_exact_vs_ckdtree(name):
    ref = _clouds()[name]
    rng = np.random.default_rng(2)
    q = np.concatenate([ref[rng.choice(len(ref), 200)], ref.min(0) + np.ptp(ref, 0) * rng.random((200, 3))])
    scale = float(np.median(cKDTree(ref).query(ref[:200], 9)[0][:, -1]))
    for r in (0.5 * scale, 2.0 * scale, 1.0 if name == "lattice_dup" else 3 * scale):
        for method in ("grid", "brute"):
            mx = _check_radius(ref, q, r, 16, radius_search(ref, q, r, 16, method=method))
    print(f"radius_search {name}: counts and sets identical to cKDTree (max count {mx}, capacity 16)")


def test_knn_valid_mask_and_too_few_points():
    rng = np.random.default_rng(3)
    ref = rng.random((3000, 3))  # the shapes of the tests above: compiled programs are reused
    valid = rng.random(3000) < 0.5
    ref_bad = ref.copy()
    ref_bad[~valid] = np.nan  # invalid slots may hold garbage
    q = rng.random((600, 3))
    for method in ("grid", "brute"):
        idx, d2 = knn(ref_bad, q, 32, ref_valid=jnp.asarray(valid), method=method)
        _check_knn(ref, q, 32, idx, d2, valid=valid)
    # fewer valid points than k
    few = np.zeros(3000, bool)
    few[[3, 50, 77]] = True
    for method in ("grid", "brute"):
        idx, d2 = knn(ref, q, 8, ref_valid=jnp.asarray(few), method=method)
        _check_knn(ref, q, 8, idx, d2, valid=few)
        idx, d2 = knn(ref, q, 8, ref_valid=jnp.zeros(3000, bool), method=method)
        assert np.all(np.asarray(idx) == -1) and np.all(np.isinf(np.asarray(d2)))


def test_knn_far_queries_and_float32():
    rng = np.random.default_rng(4)
    ref = rng.random((3000, 3))
    q = np.concatenate([rng.random((575, 3)), 50 + rng.random((20, 3)), -(1e6) * rng.random((5, 3))])
    idx, d2 = knn(ref, q, 8, method="grid")
    _check_knn(ref, q, 8, idx, d2)
    ref32, q32 = ref.astype(np.float32), q[:600].astype(np.float32)
    idx, d2 = knn(ref32, q32, 8, method="grid")
    assert np.asarray(d2).dtype == np.float32
    dt, it = cKDTree(ref32.astype(np.float64)).query(q32.astype(np.float64), 8)
    # float32: same sets except where two distances agree to float32 rounding
    same = np.mean([set(a) == set(b) for a, b in zip(np.asarray(idx), it)])
    err = np.max(np.abs(np.sqrt(np.asarray(d2, np.float64)) - dt) / dt)
    print(f"knn float32 vs cKDTree(float64): identical sets {same:.4f}, max |d - d_ref| / d_ref = {err:.1e}")
    assert same >= 0.99 and err < 1e-5


@pytest.mark.parametrize("method", ["grid", "brute"])
def test_knn_float64_distances_that_tie_in_float32(method):
    """float64 selects on float32-rounded keys, then repairs: rows whose k-th and (k+1)-th keys
    tie in float32 must still get the exact float64 neighbours. Reference points at distances
    1 + j 1e-10 from the query (all equal in float32), stored with the farther half first, each
    half ascending: the first candidates are already in order, so only the tie test can tell
    that they are the wrong ones."""
    k = 6
    s = 1e-10 * np.concatenate([np.arange(20, 40), np.arange(20)])
    line = np.stack([1.0 + s, np.zeros(40), np.zeros(40)], 1)
    filler = 5.0 + np.random.default_rng(11).random((3000, 3))  # far away
    ref = np.concatenate([filler[:1500], line, filler[1500:]])
    q = np.zeros((4, 3))
    idx, d2 = knn(ref, q, k, method=method)
    assert np.array_equal(np.asarray(idx)[0], 1520 + np.arange(k)), np.asarray(idx)[0]
    assert np.allclose(np.asarray(d2)[0], (1.0 + 1e-10 * np.arange(k)) ** 2, rtol=0, atol=1e-15)


@pytest.mark.parametrize("method", ["grid", "brute"])
def test_radius_capacity_cut_on_float64_distances_that_tie_in_float32(method):
    """The radius search's capacity cut, on the same line of points tied in float32: the kept
    ``capacity`` must be the exact float64 nearest (the grid path selects on float32 keys and
    rescans the rows whose cut is tied)."""
    cap = 6
    s = 1e-10 * np.concatenate([np.arange(20, 40), np.arange(20)])
    line = np.stack([1.0 + s, np.zeros(40), np.zeros(40)], 1)
    filler = 5.0 + np.random.default_rng(11).random((3000, 3))
    ref = np.concatenate([filler[:1500], line, filler[1500:]])
    idx, d2, count, trunc = radius_search(ref, np.zeros((4, 3)), 1.5, cap, method=method)
    assert int(count[0]) == 40 and bool(trunc[0])
    assert np.array_equal(np.asarray(idx)[0], 1520 + np.arange(cap)), np.asarray(idx)[0]


@pytest.mark.slow
def test_jit_vmap():
    rng = np.random.default_rng(5)
    refs = jnp.asarray(rng.random((2, 3000, 3)))
    qs = jnp.asarray(rng.random((2, 200, 3)))
    f = jax.jit(jax.vmap(lambda r, q: knn(r, q, 8, method="grid")))
    idx, d2 = f(refs, qs)
    for b in range(2):
        _check_knn(np.asarray(refs[b]), np.asarray(qs[b]), 8, idx[b], d2[b])
    g = jax.jit(lambda r, q, rad: radius_search(r, q, rad, 8, method="grid"))
    out = g(refs[0], qs[0], 0.08)  # traced radius
    _check_radius(np.asarray(refs[0]), np.asarray(qs[0]), 0.08, 8, out)


def test_radius_truncation_flag():
    ref = np.random.default_rng(6).random((3000, 3))
    q = ref[:50]
    out = radius_search(ref, q, 0.3, 4, method="grid")
    mx = _check_radius(ref, q, 0.3, 4, out)
    assert bool(np.all(np.asarray(out[3])))  # > 4 neighbours everywhere at r = 0.3
    print(f"radius_search overflow: all 50 queries truncated at capacity 4 (max true count {mx})")


def test_bad_input():
    ref = np.zeros((10, 3))
    with pytest.raises(ValueError, match="knn: argument 'k'"):
        knn(ref, ref, 0)
    with pytest.raises(ValueError, match="knn: argument 'k'"):
        knn(ref, ref, 65)
    with pytest.raises(TypeError, match="knn: argument 'k'"):
        knn(ref, ref, 2.0)
    with pytest.raises(ValueError, match="knn: argument 'query_xyz'"):
        knn(ref, np.zeros((4, 2)), 2)
    with pytest.raises(ValueError, match="knn: argument 'ref_xyz'.*NaN"):
        knn(np.full((4, 3), np.nan), ref, 2)
    with pytest.raises(ValueError, match="knn: argument 'method'"):
        knn(ref, ref, 2, method="kdtree")
    with pytest.raises(ValueError, match="radius_search: argument 'radius'"):
        radius_search(ref, ref, -1.0, 4)
    with pytest.raises(ValueError, match="radius_search: argument 'capacity'"):
        radius_search(ref, ref, 1.0, 0)
    # empty clouds
    idx, d2 = knn(np.zeros((0, 3)), ref, 3)
    assert idx.shape == (10, 3) and np.all(np.asarray(idx) == -1)


# ---------------------------------------------------------------------------
# sample_surface
# ---------------------------------------------------------------------------


def _areas(v, f):
    return 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)


def test_sample_surface_area_split_3_to_1():
    # two disjoint triangles with areas 3 and 1 (in different planes)
    v = np.array([[0.0, 0, 0], [3, 0, 0], [0, 2, 0], [5, 0, 1], [7, 0, 1], [5, 0, 2]])
    f = np.array([[0, 1, 2], [3, 4, 5]])
    np.testing.assert_allclose(_areas(v, f), [3.0, 1.0])
    n = 40000
    p = sample_surface(Mesh(v, f), n=n, seed=11)
    x = np.asarray(p.xyz)
    on_big = np.abs(x[:, 2]) < 1e-12
    on_small = np.abs(x[:, 1]) < 1e-12
    assert np.all(on_big ^ on_small)  # every point exactly on one of the two planes
    # inside the triangles (barycentric test)
    assert np.all((x[on_big, 0] >= 0) & (x[on_big, 1] >= 0) & (x[on_big, 0] / 3 + x[on_big, 1] / 2 <= 1 + 1e-12))
    assert np.all((x[on_small, 0] >= 5) & (x[on_small, 2] >= 1)
                  & ((x[on_small, 0] - 5) / 2 + (x[on_small, 2] - 1) <= 1 + 1e-12))
    frac = on_big.mean()
    sd = np.sqrt(0.75 * 0.25 / n)
    print(f"sample_surface 3:1 triangles: fraction on the big one {frac:.4f} (truth 0.75, 4 sd = {4 * sd:.4f})")
    assert abs(frac - 0.75) < 4 * sd
    nr = np.asarray(p.normals)
    np.testing.assert_allclose(nr[on_big], np.broadcast_to([0, 0, 1.0], nr[on_big].shape), atol=1e-15)
    np.testing.assert_allclose(nr[on_small], np.broadcast_to([0, -1.0, 0], nr[on_small].shape), atol=1e-15)


def _chi2(counts, expected):
    return float(np.sum((counts - expected) ** 2 / expected))


def test_sample_surface_uniform_per_area_on_bunny():
    v, f = mesh_arrays("bunny")
    area = _areas(v, f)
    n = 60000
    x = np.asarray(sample_surface(bunny(), n=n, seed=5).xyz)
    # 40 bins of equal area: faces sorted by centroid height (y), cut by cumulative area
    nb = 40
    order = np.argsort(v[f].mean(axis=1)[:, 1])
    cum = np.cumsum(area[order]) / area.sum()
    bin_of_face = np.empty(len(f), int)
    bin_of_face[order] = np.minimum((cum * nb - 1e-12).astype(int), nb - 1)
    expected = np.bincount(bin_of_face, weights=area, minlength=nb) / area.sum() * n
    # each sample's face, approximated by the nearest face centroid (the bands are wide)
    _, face = cKDTree(v[f].mean(axis=1)).query(x)
    counts = np.bincount(bin_of_face[face], minlength=nb)
    chi2 = _chi2(counts, expected)
    # null: a face chosen uniformly (ignoring area), then a uniform point in it
    rng = np.random.default_rng(0)
    fu = rng.integers(0, len(f), n)
    counts0 = np.bincount(bin_of_face[fu], minlength=nb)
    chi2_0 = _chi2(counts0, expected)
    print(f"sample_surface bunny: chi2 per-area uniformity over {nb} equal-area bands = {chi2:.1f} "
          f"(df {nb - 1}, 0.1% critical 73.4); null (faces uniform, not area-weighted) = {chi2_0:.0f}")
    assert chi2 < 73.4 < chi2_0


def test_sample_surface_within_triangle_and_sphere():
    # within one triangle: the 4 midpoint sub-triangles get equal shares
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    n = 20000
    x = np.asarray(sample_surface(Mesh(v, np.array([[0, 1, 2]])), n=n, seed=2).xyz)
    sub = np.where(x[:, 0] > 0.5, 0, np.where(x[:, 1] > 0.5, 1, np.where(x[:, 0] + x[:, 1] < 0.5, 2, 3)))
    chi2 = _chi2(np.bincount(sub, minlength=4), n / 4)
    print(f"sample_surface one triangle: chi2 over 4 midpoint sub-triangles = {chi2:.2f} (df 3, 0.1% crit 16.3)")
    assert chi2 < 16.3
    # icosphere: points on the faces, normals outward and unit
    vi, fi = icosphere(2, radius=2.0)
    p = sample_surface(Mesh(vi, fi), n=4000, key=jax.random.PRNGKey(9))
    xs, ns = np.asarray(p.xyz), np.asarray(p.normals)
    assert np.all(np.sum(xs * ns, axis=1) > 0)
    np.testing.assert_allclose(np.linalg.norm(ns, axis=1), 1.0, atol=1e-14)
    assert np.all(np.linalg.norm(xs, axis=1) <= 2.0 + 1e-12) and np.all(np.linalg.norm(xs, axis=1) > 1.8)


def test_sample_surface_determinism_and_bad_input():
    m = Mesh(*icosphere(1))
    a = np.asarray(sample_surface(m, n=100, seed=3).xyz)
    b = np.asarray(jax.jit(lambda mm: sample_surface(mm, n=100, seed=3))(m).xyz)
    c = np.asarray(sample_surface(m, n=100, seed=4).xyz)
    d = np.asarray(sample_surface(m, n=100, seed=4, key=jax.random.PRNGKey(3)).xyz)
    np.testing.assert_allclose(a, b, rtol=1e-14, atol=1e-15)  # jit may fuse multiply-adds
    np.testing.assert_array_equal(a, np.asarray(sample_surface(m, n=100, seed=3).xyz))
    np.testing.assert_array_equal(a, d)  # the key overrides the seed
    assert not np.allclose(a, c)
    # invalid faces are never sampled
    fv = np.ones(80, bool)
    fv[40:] = False
    p = sample_surface(Mesh(*icosphere(1), face_valid=fv), n=2000, seed=0)
    v, f = icosphere(1)
    _, near = cKDTree(v[f].mean(axis=1)).query(np.asarray(p.xyz))
    assert np.all(near < 40)
    with pytest.raises(ValueError, match="sample_surface: argument 'n'"):
        sample_surface(m, n=0)
    with pytest.raises(TypeError, match="sample_surface: argument 'n'"):
        sample_surface(m, n=10.5)
    flat = Mesh(np.zeros((3, 3)), np.array([[0, 1, 2]]))
    with pytest.raises(ValueError, match="sample_surface: argument 'mesh' has no valid face"):
        sample_surface(flat, n=10)
    out = jax.jit(lambda mm: sample_surface(mm, n=10))(flat)  # under jit: fails closed
    assert not np.any(np.asarray(out.valid)) and np.all(np.isnan(np.asarray(out.xyz)))


# ---------------------------------------------------------------------------
# point_spacing
# ---------------------------------------------------------------------------


def test_point_spacing_vs_ckdtree():
    from fsjax import Points
    from fsjax.ops import point_spacing

    x = _clouds()["bunny_sampled"][:2000]
    valid = np.ones(len(x), bool)
    valid[::5] = False
    xv = x[valid]
    for k in (1, 8):
        d, _ = cKDTree(xv).query(xv, k + 1)
        truth = d[:, 1:].mean()
        got = float(point_spacing(Points(x, valid=valid), k=k).value)
        rel = abs(got - truth) / truth
        print(f"point_spacing k={k} on 1600 bunny points: {got:.6e} vs cKDTree {truth:.6e} (rel {rel:.1e})")
        assert rel < 1e-12
    # duplicates count at distance 0; fewer than k + 1 valid points -> NaN
    dup = Points(np.array([[0.0, 0, 0], [0, 0, 0], [1, 0, 0]]))
    assert float(point_spacing(dup).value) == pytest.approx(1 / 3)
    assert np.isnan(float(point_spacing(dup, k=3).value))
    with pytest.raises(ValueError, match="point_spacing: argument 'k'"):
        point_spacing(dup, k=0)


def test_index_built_once_reused_exact_with_coarse_levels():
    # issue 12: one index per cloud, built once and queried many times (ICP's target); the coarse
    # levels answer queries far from the cloud (a 30 deg rotation, points 10 cm off) exactly
    from fsjax.data import surface_points
    from fsjax.fit.rigid import rotation_from_axis_angle
    from fsjax.ops import build_index, query_knn, query_radius

    ref = surface_points("bunny", 3000, 0)
    valid = np.arange(3000) % 7 != 0
    rot = np.asarray(rotation_from_axis_angle(jnp.array([0.3, 1.0, -0.4]), 30.0))
    q1 = surface_points("bunny", 1000, 1) @ rot.T
    q1[:50] += 0.1  # far from every reference point
    q2 = surface_points("bunny", 1000, 2)  # near the cloud: second use of the same index, same compiled query
    index = jax.jit(lambda r, v: build_index(r, v, k=4, coarse=True))(jnp.asarray(ref), jnp.asarray(valid))
    query = jax.jit(lambda ix, q, a: query_knn(ix, q, 8, approx=a))  # one compile: approx is traced
    for q in (q1, q2):
        idx, d2 = query(index, jnp.asarray(q), False)
        _check_knn(ref, q, 8, idx, d2, valid=valid)
    # the approximate mode (ICP's early iterations): real valid points at their true distances,
    # ascending, never nearer than the exact answer; exact for queries near the cloud; and really
    # approximate far from it (the null: some rows differ from the exact ones)
    q12 = np.concatenate([q1, q2])  # far (30 deg) and near queries
    ex_idx, ex_d2 = (np.asarray(a) for a in query(index, jnp.asarray(q12), False))
    ap_idx, ap_d2 = (np.asarray(a) for a in query(index, jnp.asarray(q12), True))
    assert np.all(ap_idx >= 0) and np.all(valid[ap_idx])
    true_d2 = np.sum((q12[:, None, :] - ref[ap_idx]) ** 2, -1)
    np.testing.assert_allclose(ap_d2, true_d2, rtol=1e-12, atol=1e-18)
    assert np.all(np.diff(ap_d2, axis=1) >= 0) and np.all(ap_d2 >= ex_d2 * (1 - 1e-12))
    near = ex_d2[:, -1] < 0.99 * float(index.h) ** 2  # the k-th neighbour within one cell: certified at once
    assert near.sum() > 100 and np.array_equal(ap_d2[near], ex_d2[near])
    differ = np.any(ap_d2 != ex_d2, axis=1)
    print(f"approximate mode: {differ[:1000].mean():.3f} of the far rows differ from the exact ones "
          f"(k-th distance ratio up to {np.sqrt(ap_d2[:, -1] / ex_d2[:, -1]).max():.2f})")
    assert differ.any()
    # radius search on an index built with its radius as the cell side, equal to radius_search
    r = 0.01
    rix = build_index(jnp.asarray(ref), jnp.asarray(valid), cell=r)
    out = query_radius(rix, jnp.asarray(q2), r, 32)
    _check_radius(ref, q2, r, 32, out, valid=valid)
    with pytest.raises(ValueError, match="query_radius: argument 'radius'"):
        query_radius(rix, jnp.asarray(q2), 2 * float(rix.h), 32)


def test_query_knn_max_dist_gate():
    """``max_dist``: the neighbours within the gate are the exact ones, the rest missing; far queries
    (here a whole second cloud 1 unit away) are settled without the brute-force scan."""
    from fsjax.ops.points._search import build_index, query_knn

    rng = np.random.default_rng(3)
    ref = rng.uniform(0, 1, (3000, 3)) * np.array([1.0, 1.0, 0.02])  # a thin slab
    qry = np.r_[rng.uniform(0, 1, (500, 3)) * np.array([1.0, 1.0, 0.02]),
                rng.uniform(0, 1, (500, 3)) + np.array([0.0, 0.0, 1.0])]
    idx, d2 = knn(ref, qry, 4)
    g = build_index(jnp.asarray(ref), k=4, coarse=True)
    for gate in (0.02, 0.05, 1.2):
        gi, gd = query_knn(g, jnp.asarray(qry), 4, max_dist=gate)
        inside = np.asarray(d2) <= gate**2
        assert np.array_equal(np.asarray(gi)[inside], np.asarray(idx)[inside])
        assert np.all(np.asarray(gi)[~inside] == -1) and np.all(np.isinf(np.asarray(gd)[~inside]))
    assert inside[:500].mean() > 0.9 and not inside[500:].all()  # both kinds of query occur


def test_index_chain_every_pass_exact_on_a_lattice_float64():
    """The fallback chain (one looped body over its passes: fine 125-cell block, 4x / 16x levels,
    whole-array scan) is exact for queries that each pass answers: a float64 lattice (distances
    that tie, also in float32) and queries 0, 3, 12, 50 and 400 cells from it."""
    from fsjax.ops.points._search import build_index, query_knn

    g = np.stack(np.meshgrid(*[np.arange(12) * 0.1] * 3, indexing="ij"), -1).reshape(-1, 3)
    rng = np.random.default_rng(5)
    ix = jax.jit(lambda r: build_index(r, k=8, coarse=True))(jnp.asarray(g))
    h = float(ix.h)
    offs = (0.0, 3 * h, 12 * h, 50 * h, 400 * h)
    q = np.concatenate([g[rng.choice(len(g), 24)] + np.array([1.1, 0.0, 0.0]) * (d > 0) + np.array([d, 0.0, 0.0])
                        for d in offs])
    q[:12] = g[:12]  # exact lattice points: distances tie
    idx, d2 = jax.jit(lambda ix, q: query_knn(ix, q, 8))(ix, jnp.asarray(q))
    assert _check_knn(g, q, 8, idx, d2) == len(q)
    # the null of "every pass is reached": the far groups' nearest point lies beyond the blocks before
    near = np.sqrt(np.asarray(d2)[:, 0]).reshape(len(offs), -1).min(axis=1) / h
    assert near[1] > 2 and near[2] > 10 and near[3] > 45 and near[4] > 390


def test_knn_cell_size_for_k1_is_the_nearest_other_point():
    """k = 1: the cell side is 1.5 x the median distance of 16 strided points to their nearest OTHER
    point (the first neighbour of a reference point is itself, at 0: it gave no estimate and a grid
    of one cell, 7 s for 20,000 x 20,000 points)."""
    from fsjax.data import surface_points
    from fsjax.ops.points._search import _knn_cell_size

    ref = surface_points("bunny", 2000, 0).astype(np.float32)
    pick = np.linspace(0, len(ref) - 1, 16).round().astype(int)
    d, _ = cKDTree(ref).query(ref[pick], 2)
    h = float(_knn_cell_size(jnp.asarray(ref), jnp.ones(len(ref), bool), 1))
    np.testing.assert_allclose(h, 1.5 * np.median(d[:, 1]), rtol=1e-5)
    assert h > 0


def test_one_program_for_several_k_and_query_counts():
    """ICP's one search program: the number of neighbours (``k_used`` <= the static width) and of
    query rows (``n_q``) are traced, so the target's own k-NN and the k = 1 correspondences share
    one compile; each call is exact vs cKDTree for its own k, the columns past ``k_used`` and the
    rows past ``n_q`` are missing. The fallback passes in one looped body (ICP's ``one_group``),
    far queries (30 deg, points 10 cm off) included, in the exact mode."""
    from fsjax.data import surface_points
    from fsjax.fit.rigid import rotation_from_axis_angle
    from fsjax.ops import build_index
    from fsjax.ops.points._search import _query_grid_knn

    ref = surface_points("bunny", 3000, 0)
    rot = np.asarray(rotation_from_axis_angle(jnp.array([0.3, 1.0, -0.4]), 30.0))
    q = surface_points("bunny", 3000, 1) @ rot.T
    q[:40] += 0.1
    ix = jax.jit(lambda r: build_index(r, k=10, coarse=True))(jnp.asarray(ref))
    calls = []

    def f(ix, q, k_used, n_q):
        calls.append(1)  # traced once per compile
        return _query_grid_knn(ix, q, 10, jnp.bool_(False), jnp.asarray(np.inf), k_used, n_q, one_group=True)

    fj = jax.jit(f)
    for k_used, n_q, qq in ((10, 3000, ref), (1, 2200, q), (4, 3000, q)):
        idx, d2 = (np.asarray(a) for a in fj(ix, jnp.asarray(qq), k_used, n_q))
        assert _check_knn(ref, qq[:n_q], k_used, idx[:n_q, :k_used], d2[:n_q, :k_used]) == n_q
        assert np.all(idx[:, k_used:] == -1) and np.all(np.isinf(d2[:, k_used:]))
        assert np.all(idx[n_q:] == -1) and np.all(np.isinf(d2[n_q:]))
    assert len(calls) == 1  # one program for the three


def test_warm_started_query_equals_the_plain_one():
    """``warm`` (ICP's last correspondences): the previous neighbour's distance bounds the search.
    Same answers as without it, bit for bit, in the exact and the approximate mode, whatever the
    previous neighbours are (good ones 0.2 deg earlier, random ones, missing, invalid points), and
    for k_used > 1 (where it is ignored); the null: the warm pass really answers most near rows."""
    from fsjax.data import surface_points
    from fsjax.fit.rigid import rotation_from_axis_angle
    from fsjax.ops import build_index
    from fsjax.ops.points._search import _WARM_SLOTS, _batched, _query_grid_knn, _warm_pass

    ref = surface_points("bunny", 3000, 0)
    valid = np.arange(3000) % 11 != 0
    rot = np.asarray(rotation_from_axis_angle(jnp.array([0.3, 1.0, -0.4]), 30.0))
    small = np.asarray(rotation_from_axis_angle(jnp.array([1.0, -0.2, 0.5]), 0.2))
    near = surface_points("bunny", 2000, 1)
    q = np.concatenate([near, near[:1000] @ rot.T])  # near and far (30 deg) queries
    q[-20:] += 0.1
    ix = jax.jit(lambda r, v: build_index(r, v, k=10, coarse=True))(jnp.asarray(ref), jnp.asarray(valid))
    n = len(q)

    @jax.jit
    def f(ix, q, approx, k_used, warm):
        return _query_grid_knn(ix, q, 10, approx, jnp.asarray(np.inf), k_used, n, one_group=True, warm=warm)

    @jax.jit
    def plain(ix, q, approx, k_used):
        return _query_grid_knn(ix, q, 10, approx, jnp.asarray(np.inf), k_used, n, one_group=True)

    prev = np.asarray(plain(ix, jnp.asarray(q @ small.T), False, 1)[0][:, 0])
    rng = np.random.default_rng(0)
    warms = {"previous": prev, "random": rng.integers(0, 3000, n), "missing": np.full(n, -1),
             "invalid": np.full(n, 11)}
    for approx in (False, True):
        for k_used in (1, 4):
            want = [np.asarray(a) for a in plain(ix, jnp.asarray(q), approx, k_used)]
            for name, w in warms.items():
                got = [np.asarray(a) for a in f(ix, jnp.asarray(q), approx, k_used, jnp.asarray(w, jnp.int32))]
                assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1]), (approx, k_used, name)
    idx, d2 = (np.asarray(a) for a in plain(ix, jnp.asarray(q), False, 1))
    assert _check_knn(ref, q, 1, idx[:, :1], d2[:, :1], valid=valid) == n
    answered = jax.jit(lambda ix, q, w: _batched(lambda a, b: _warm_pass(ix, a, b, 10, _WARM_SLOTS), (q, w), 1000)[2])
    got = np.asarray(answered(ix, jnp.asarray(q), jnp.asarray(prev, jnp.int32)))
    assert got[:2000].mean() > 0.8 and got[-20:].sum() == 0
    assert not np.asarray(answered(ix, jnp.asarray(q), jnp.full(n, 11, jnp.int32))).any()


@pytest.mark.parametrize("n, few_cells", [(5000, False), (40000, True), (40000, False), (140000, True)])
def test_grid_sort_and_cell_starts_equal_a_stable_argsort(n, few_cells):
    """The index build's key sort (one sort of packed (key, index) words where they fit in 32 bits --
    always up to 32,768 points, above when the grid has few cells -- else an argsort) is the stable
    order, invalid points (key int32 max) last, and its cell-start table is the prefix sum of the
    cell counts."""
    from fsjax.ops.points import _search as S

    rng = np.random.default_rng(3)
    t = S._table_size(n)
    ncells = 1000 if few_cells else t - 1
    key = rng.integers(0, min(ncells, n // 8), n).astype(np.int32)  # ~8 points per key: many ties
    key[rng.random(n) < 0.1] = np.iinfo(np.int32).max
    order, skey = jax.jit(lambda k: S._sort_by_key(k, t, jnp.int32(ncells)))(jnp.asarray(key))
    ref = np.argsort(key, kind="stable")
    np.testing.assert_array_equal(np.asarray(order), ref)
    np.testing.assert_array_equal(np.asarray(skey), key[ref])
    counts = np.bincount(key[key < t], minlength=t).astype(np.int32)
    np.testing.assert_array_equal(np.asarray(S._prefix_sum(jnp.asarray(counts))), np.cumsum(counts))
