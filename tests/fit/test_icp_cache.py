"""fsjax.fit.icp: the certified correspondence cache (issue 12) gives the exact search's answers."""

from __future__ import annotations

import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fsjax.data import surface_points
from fsjax.fit import icp, rotation_error_deg, rotation_from_axis_angle
from fsjax.ops import build_index, query_knn

icp_mod = importlib.import_module("fsjax.fit.icp")  # (fsjax.fit.icp the attribute is the function)


def _cache_at(g, pc, k, gate=None):
    """The cache of rows at ``pc``: sorted positions of their k nearest, and the radius (as the loop)."""
    idx, d2 = query_knn(g, pc, k, max_dist=gate)
    inv = np.zeros(g.order.shape, np.int32)
    inv[np.asarray(g.order)] = np.arange(g.order.shape[0])
    pos = np.where(idx >= 0, inv[np.maximum(idx, 0)], -1)
    rad = np.where(np.isfinite(d2[:, -1]), np.sqrt(d2[:, -1]), np.inf if gate is None else gate)
    return jnp.asarray(pos), jnp.asarray(rad, pc.dtype)


_answer = jax.jit(icp_mod._cache_answer)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_cache_answer_equals_the_exact_query(dtype):
    """Rows the cache certifies get the exact search's nearest (index and squared distance, bit for
    bit); a row moved so that its true nearest is outside its cache is refused. The null: the same
    cache without the certificate (every row taken) answers wrongly on the moved rows."""
    tgt = jnp.asarray(surface_points("bunny", 2500, 0), dtype)
    tgt = (tgt - tgt.mean(0)) / jnp.sqrt(jnp.mean(jnp.sum((tgt - tgt.mean(0)) ** 2, -1)))
    g = build_index(tgt, jnp.ones(tgt.shape[0], bool), k=10, coarse=True)
    rng = np.random.default_rng(0)
    pc = tgt[:2000] + jnp.asarray(rng.normal(size=(2000, 3)) * 0.01, dtype)
    # small motions (most rows certified) and, on the first 50 rows, a jump to another part of the cloud
    p = pc + jnp.asarray(rng.normal(size=(2000, 3)) * 0.002, dtype)
    p = p.at[:50].set(tgt[2000:2050] + 0.001)
    for gate in (1e6, 0.018):  # no gate in effect; a gate that leaves rows fewer than 4 points within it
        _check_rows(g, pc, p, gate, dtype)


def _check_rows(g, pc, p, gate, dtype):
    pos, rad = _cache_at(g, pc, 4, gate)
    idx, d2, cert = _answer(g.spts, g.order, pos, pc, rad, p, jnp.asarray(gate, dtype))
    ie, de = query_knn(g, p, 4, max_dist=gate)  # its first column: the exact nearest (one program with the cache's)
    ie, de = ie[:, 0], de[:, 0]
    cert = np.asarray(cert)
    print(f"{jnp.dtype(dtype).name} gate {gate}: {int((np.asarray(rad) == np.asarray(rad.dtype.type(gate))).sum())} radii at the gate, {cert.sum()} of 2000 rows certified, moved rows {cert[:50].sum()}")
    assert cert[50:].mean() > 0.2  # the cache answers many rows (not a check that never runs)
    assert np.array_equal(np.asarray(idx)[cert], np.asarray(ie)[cert])
    assert np.array_equal(np.asarray(d2)[cert], np.asarray(de)[cert])
    # the moved rows: their nearest is none of their cached points, and the certificate refuses them
    cached_ids = np.where(np.asarray(pos[:50]) >= 0, np.asarray(g.order)[np.maximum(np.asarray(pos[:50]), 0)], -1)
    outside = np.array([int(ie[i]) not in cached_ids[i] for i in range(50)])
    assert outside.all() and not cert[:50].any()
    assert np.any(np.asarray(idx)[:50] != np.asarray(ie)[:50])  # null: taking them anyway is wrong


def test_cache_with_fewer_target_points_than_its_width():
    """A target of 3 points and a cache 4 wide: the missing column makes the radius infinite (every
    target point is cached), so every row is certified and right."""
    tgt = jnp.asarray([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    g = build_index(tgt, jnp.ones(3, bool), k=2)
    pc = jnp.asarray([[0.1, 0.1, 0.0], [0.9, 0.1, 0.0]])
    pos, rad = _cache_at(g, pc, 4)
    p = jnp.asarray([[0.1, 0.8, 0.0], [0.4, 0.1, 0.0]])  # moved across to other nearest points
    idx, d2, cert = _answer(g.spts, g.order, pos, pc, rad, p, jnp.inf)
    assert np.isinf(np.asarray(rad)).all() and np.asarray(cert).all()
    assert np.asarray(idx).tolist() == [2, 0]


def _two_runs(monkeypatch, dtype, knob, values, fixed):
    """Point-to-point ICP on the grid path (forced at 700 points, 5 deg) with ``knob`` at each of
    ``values`` (the other knobs at ``fixed``), traced apart; and the cache turns' certified counts."""
    monkeypatch.setattr(icp_mod, "_BRUTE_LIMIT", 0)
    for k, v in fixed.items():
        monkeypatch.setattr(icp_mod, k, v)
    tgt = jnp.asarray(surface_points("bunny", 700, 0), dtype)
    r = np.asarray(rotation_from_axis_angle(jnp.array([0.3, 1.0, -0.4]), 5.0))
    src = jnp.asarray((surface_points("bunny", 700, 0) - 0.002) @ r, dtype)
    counts = []
    answer = icp_mod._cache_answer

    def counted(*args):
        out = answer(*args)
        jax.debug.callback(lambda c: counts.append(int(c)), jnp.sum(out[2]))
        return out

    monkeypatch.setattr(icp_mod, "_cache_answer", counted)
    res = []
    try:
        for v in values:
            monkeypatch.setattr(icp_mod, knob, v)
            for f in (icp_mod._icp_core.fast, icp_mod._icp_core.plain):
                f.clear_cache()
            res.append(jax.device_get(icp(src, tgt, method="point_to_point")))
    finally:
        monkeypatch.undo()
        for f in (icp_mod._icp_core.fast, icp_mod._icp_core.plain):
            f.clear_cache()
    errs = [float(rotation_error_deg(jnp.asarray(o.R), jnp.asarray(r))) for o in res]
    print(f"{jnp.dtype(dtype).name} {knob} {values}: iterations {[int(o.iterations) for o in res]}, errors "
          f"{errs} deg; certified rows per cache turn {counts}")
    return res, errs, counts


@pytest.mark.slow
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_icp_with_the_cache_equals_icp_without(monkeypatch, dtype):
    """With the cache (``_CACHE_K = 4``) and without (``0``), all points in every turn
    (``_SUBSET = 1``): the same result, leaf for leaf (tolerance: R, t within 1e-6, rms_len within
    1e-9 of the cloud's unit, the same iterations, flags and counts; measured bit-identical). The
    cache is used: the turns' certified rows are counted (a callback while running), and some turns
    search no row (all 700 certified)."""
    (off, on), errs, counts = _two_runs(monkeypatch, dtype, "_CACHE_K", (0, 4), {"_SUBSET": 1})
    assert len(counts) >= 2 and max(counts) == 700  # cache turns ran, some with every row certified
    assert bool(on.converged) and errs[1] < 0.01  # registered (the null, no ICP, is 5 deg)
    assert int(on.iterations) == int(off.iterations) and int(on.reason) == int(off.reason)
    assert int(on.n_correspondences) == int(off.n_correspondences)
    np.testing.assert_allclose(np.asarray(on.R), np.asarray(off.R), rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.asarray(on.t), np.asarray(off.t), rtol=0, atol=1e-6)
    np.testing.assert_allclose(float(on.rms_len), float(off.rms_len), rtol=0, atol=1e-9)
    assert float(on.inlier_fraction) == float(off.inlier_fraction)


@pytest.mark.slow
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_icp_on_a_subset_in_the_approximate_phase(monkeypatch, dtype):
    """Approximate turns on every 4th source point (``_SUBSET = 4``, forced below ``_SUBSET_FROM``) against all points (``1``): not
    the same trajectory, the same registration: both converge, rotation error to the truth below
    0.01 deg (the null, no ICP: 5 deg), poses within 1e-4, iterations within 4 of each other."""
    (full, part), errs, _ = _two_runs(monkeypatch, dtype, "_SUBSET", (1, 4), {"_CACHE_K": 4, "_SUBSET_FROM": 0})
    assert bool(full.converged) and bool(part.converged)
    assert max(errs) < 0.01
    np.testing.assert_allclose(np.asarray(part.R), np.asarray(full.R), rtol=0, atol=1e-4)
    assert abs(int(part.iterations) - int(full.iterations)) <= 4
    assert float(part.inlier_fraction) == float(full.inlier_fraction) == 1.0


def test_subset_with_too_few_pairs_goes_on_with_every_point(monkeypatch):
    """A source of which only 12 points lie within the distance gate of the target: the subset (every
    4th point: 3 of them at most) may give too few pairs for a step; the turn then makes no step and
    the next one searches every point, so the fit ends as without the subset (not reason 2; without
    this rule: reason 2 with 1 pair, checked on the branch before it)."""
    monkeypatch.setattr(icp_mod, "_BRUTE_LIMIT", 0)
    monkeypatch.setattr(icp_mod, "_SUBSET_FROM", 0)
    tgt = np.asarray(surface_points("bunny", 500, 0))
    rng = np.random.default_rng(3)
    near = tgt[rng.choice(500, 12, replace=False)] + 0.0005
    src = tgt[rng.choice(500, 500)] + np.array([1.0, 0.0, 0.0])  # 1 m away: beyond the gate
    src[[0, 1, 2, 3, 5, 6, 7, 9, 10, 11, 13, 14]] = near  # one of them at a row of the subset (every 4th)
    res = {}
    try:
        for k in (1, 4):
            monkeypatch.setattr(icp_mod, "_SUBSET", k)
            for f in (icp_mod._icp_core.fast, icp_mod._icp_core.plain):
                f.clear_cache()
            res[k] = jax.device_get(icp(jnp.asarray(src), jnp.asarray(tgt), method="point_to_point",
                                        max_correspondence_distance=0.01, min_inlier_fraction=0.0))
    finally:
        monkeypatch.undo()
        for f in (icp_mod._icp_core.fast, icp_mod._icp_core.plain):
            f.clear_cache()
    kept = np.arange(500) % 4 == 0
    near_rows = np.linalg.norm(src - tgt[np.argmin(((src[:, None] - tgt[None]) ** 2).sum(-1), 1)], axis=1) < 0.01
    print(f"near rows {near_rows.sum()}, in the subset {np.sum(near_rows & kept)}; reasons "
          f"{int(res[1].reason)} / {int(res[4].reason)}, pairs {int(res[1].n_correspondences)} / "
          f"{int(res[4].n_correspondences)}")
    assert np.sum(near_rows & kept) < 3 <= near_rows.sum()  # the subset alone is too few for point-to-point
    assert int(res[1].reason) == int(res[4].reason) == 0
    assert int(res[4].n_correspondences) == int(res[1].n_correspondences) == near_rows.sum()
    np.testing.assert_allclose(res[4].R, res[1].R, rtol=0, atol=1e-6)
