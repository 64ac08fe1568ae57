"""fsjax.fit.global_reg: FPFH, correspondence RANSAC, global registration (issue 4, item 2)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fsjax.data import surface_points
from fsjax.fit import fpfh, ransac_registration, rotation_error_deg, rotation_from_axis_angle
from fsjax.tour.registration import measure_global

COARSE_MAX = 1.0  # issue 4 item 2: FPFH + RANSAC (with the point-pair refit) within 1 deg


def test_fpfh_rotation_invariant_and_distinctive():
    x = jnp.asarray(surface_points("bunny", 400, 0))
    r = rotation_from_axis_angle(jnp.array([1.0, 2.0, 3.0]), 70.0)
    f1, ok1, tr1 = fpfh(x, radius=0.03)
    f2, ok2, _ = fpfh(x @ r.T + 0.1, radius=0.03)
    d_rot = float(jnp.abs(f1 - f2).max())
    sums = np.asarray(f1).reshape(400, 3, 11).sum(-1)
    print(f"FPFH (400 bunny points, r = 30 mm): max |change| under rotation + translation {d_rot:.1e}; "
          f"{int(ok1.sum())}/400 valid, {int(tr1.sum())} truncated at capacity 48")
    assert d_rot < 1e-9 and bool(ok1.all()) and bool(ok2.all())
    assert np.allclose(sums, 1.0)  # three normalised histograms
    with pytest.raises(ValueError, match="fpfh: argument 'radius'"):
        fpfh(x, radius=0.0)


def test_ransac_outliers_and_failure():
    rng = np.random.default_rng(0)
    n = 300
    src = rng.normal(size=(n, 3))
    r = np.asarray(rotation_from_axis_angle(jnp.array([0.5, -1.0, 0.2]), 60.0))
    tgt = src @ r.T + np.array([1.0, 2.0, 3.0])
    out = rng.random(n) < 0.8  # 80 % of the matches are wrong
    tgt_m = np.where(out[:, None], rng.normal(size=(n, 3)) * 2, tgt)
    res = ransac_registration(jax.random.key(1), jnp.asarray(src), jnp.asarray(tgt_m), jnp.ones(n, bool),
                              distance=0.01, n_hypotheses=4096)
    err = float(rotation_error_deg(res.R, jnp.asarray(r)))
    print(f"RANSAC, 300 matches with 80 % outliers: rotation error {err:.1e} deg, {int(res.n_inliers)} inliers "
          f"(true {int((~out).sum())}), {int(res.n_checked)}/4096 hypotheses passed the edge-length check")
    assert err < 1e-8 and int(res.n_inliers) == int((~out).sum()) and bool(res.converged)
    assert int(res.n_checked) < 4096  # the pre-check rejects inconsistent triples
    # deterministic under the key
    res2 = ransac_registration(jax.random.key(1), jnp.asarray(src), jnp.asarray(tgt_m), jnp.ones(n, bool),
                               distance=0.01, n_hypotheses=4096)
    assert np.array_equal(np.asarray(res.R), np.asarray(res2.R))
    # all matches wrong: no consistent hypothesis -> reason 6, NaN pose
    bad = ransac_registration(jax.random.key(1), jnp.asarray(src), jnp.asarray(rng.normal(size=(n, 3))),
                              jnp.ones(n, bool), distance=0.01, n_hypotheses=1024)
    few = ransac_registration(jax.random.key(1), jnp.asarray(src), jnp.asarray(tgt), jnp.arange(n) < 2,
                              distance=0.01, n_hypotheses=64)
    print(f"all matches wrong: reason {int(bad.reason)} ({bad.message}); 2 matches: reason {int(few.reason)}")
    assert int(bad.reason) == 6 and not bool(bad.converged) and bool(jnp.all(jnp.isnan(bad.R)))
    assert int(few.reason) == 2 and bool(jnp.all(jnp.isnan(few.R)))


def test_docstring_examples():
    import doctest
    import importlib

    # importlib: the attribute fsjax.fit.icp is the function icp (star import), not the module
    for mod in (importlib.import_module("fsjax.fit.icp"), importlib.import_module("fsjax.fit.global_reg")):
        res = doctest.testmod(mod)
        print(f"{mod.__name__} doctests: {res.attempted} examples, {res.failed} failed")
        assert res.attempted >= 1 and res.failed == 0


@pytest.mark.slow
def test_global_registration_60deg_70pct_overlap():
    r = measure_global()
    print(f"global registration, 60 deg, 70 % overlap ({r['n_source']} / {r['n_target']} points, FPFH + RANSAC "
          f"16384 hypotheses): {r['n_matches']} mutual matches, {r['n_inliers']} inliers; RANSAC on matches "
          f"{r['matches_only_error_deg']:.3f} deg, + point refit {r['coarse_error_deg']:.3f} deg; "
          f"after trimmed ICP ({r['n_refine']} points) {r['refined_error_deg']:.4f} deg "
          f"({r['icp_iterations']} iterations); null (no registration) {r['null_error_deg']:.0f} deg")
    assert r["coarse_converged"]
    assert r["coarse_error_deg"] <= COARSE_MAX
    assert r["refined_error_deg"] <= 0.05



@pytest.mark.slow  # ~17 s at load 4, most of it compiling the pipeline's programs (as its neighbour above)
def test_point_to_plane_refit_beats_the_point_to_point_one():
    """The refit after RANSAC (issue 12: <= 0.5 deg before ICP). Crops of 1,384 points (the tour's
    quick scene, 60 deg, 70 % overlap). The null is the old refit, closed-form Kabsch on the same
    nearest-point pairs: its fixed point lies 0.2-1.2 deg from the truth on seeds 0-9 (two
    independent samples: a pair's offset along the surface is about the spacing); seeds 2, 7, 8 are
    three where it misses 0.5 deg (0.73 / 1.16 / 0.96). Point-to-plane on the target's normals, the
    target's edge points left out (seeds 0-9: 0.07-0.36 deg), stays within it."""
    from fsjax.fit.global_reg import _crop_pair, _fpfh, _point_refit, global_registration

    r = np.asarray(rotation_from_axis_angle(jnp.array([0.2, 1.0, 0.5]), 60.0))
    shift = np.array([0.05, 0.02, -0.03])
    out = []
    for seed in (2, 7, 8):
        xs, xt = _crop_pair(1800, 1.0 / 1.3, seed)
        s, t = jnp.asarray((xs - shift) @ r), jnp.asarray(xt)
        res = global_registration(jax.random.key(seed), s, t, radius=0.025, distance=0.01, n_hypotheses=8192,
                                  refine=None)
        ransac = global_registration(jax.random.key(seed), s, t, radius=0.025, distance=0.01, n_hypotheses=8192,
                                     refine=None, refit_rounds=0).coarse
        ones_s, ones_t = jnp.ones(s.shape[0], bool), jnp.ones(t.shape[0], bool)
        old = _point_refit(ransac, s, t, _fpfh(t, radius=0.025)[3], ones_s, ones_t, jnp.asarray(0.005), 10, "point")
        e = [float(rotation_error_deg(x, jnp.asarray(r))) for x in (ransac.R, old.R, res.coarse.R)]
        out.append(e)
        print(f"seed {seed} ({s.shape[0]} / {t.shape[0]} points): RANSAC alone {e[0]:.3f} deg, point-to-point refit "
              f"{e[1]:.3f}, point-to-plane refit (global_registration) {e[2]:.3f}; translation error "
              f"{1e3 * float(np.linalg.norm(np.asarray(res.coarse.t) - shift)):.2f} mm")
        assert bool(res.coarse.converged)
    e = np.array(out)
    assert np.all(e[:, 2] <= 0.5)  # the goal
    assert np.all(e[:, 1] > 0.5) and np.all(e[:, 2] < e[:, 1])  # the null misses it on these seeds
    # float32 (the user's default): the refit works in the target's normalised frame; in metres its
    # Gauss-Newton steps were all refused as singular and the RANSAC pose came back (here 4.23 deg)
    s32, t32 = (jnp.asarray((xs - shift) @ r, jnp.float32), jnp.asarray(xt, jnp.float32))
    res32 = global_registration(jax.random.key(8), s32, t32, radius=0.025, distance=0.01, n_hypotheses=8192,
                                refine=None)
    e32 = float(rotation_error_deg(res32.coarse.R, jnp.asarray(r, jnp.float32)))
    e32_ransac = float(rotation_error_deg(res32.coarse_matches_R, jnp.asarray(r, jnp.float32)))
    print(f"seed 8 in float32: RANSAC alone {e32_ransac:.3f} deg, refit {e32:.3f} deg")
    assert res32.coarse.R.dtype == jnp.float32 and bool(res32.coarse.converged)
    assert e32 <= 0.5 and e32 < e32_ransac


def test_ransac_refuses_a_pose_that_chance_explains():
    """On surface points a wrong pose collects a few inliers by chance; the best of thousands of
    hypotheses then passes an absolute gate of 6. The chance bound (matches re-paired at random give
    the rate of accidental inliers) refuses it and keeps poses that real matches support."""
    from scipy.spatial import cKDTree

    from fsjax.data import surface_points

    x = np.asarray(surface_points("bunny", 600, 0))
    y = np.asarray(surface_points("bunny", 600, 1))  # an independent sample of the same surface
    r = np.asarray(rotation_from_axis_angle(jnp.array([0.3, 1.0, -0.4]), 60.0))
    yt = y @ r.T + 0.05
    rng = np.random.default_rng(0)
    nn = cKDTree(y).query(x)[1]
    out = {}
    for frac in (0.0, 0.1):
        good = rng.random(600) < frac
        partner = np.where(good, nn, rng.integers(0, 600, 600))
        out[frac] = ransac_registration(jax.random.key(0), jnp.asarray(x), jnp.asarray(yt[partner]),
                                        jnp.ones(600, bool), distance=0.01, n_hypotheses=8192)
    wrong, right = out[0.0], out[0.1]
    err = float(rotation_error_deg(right.R, jnp.asarray(r)))
    print(f"600 bunny matches, none right: best pose {int(wrong.n_inliers)} inliers, chance {float(wrong.chance):.2f} "
          f"-> reason {int(wrong.reason)}; 10 % right: {int(right.n_inliers)} inliers, chance "
          f"{float(right.chance):.1e}, rotation error {err:.2f} deg (null: 60 deg)")
    # the null gate: the wrong pose has as many inliers as the absolute minimum asks
    assert int(wrong.n_inliers) >= 6
    assert int(wrong.reason) == 6 and not bool(wrong.converged) and float(wrong.chance) > 0.01
    assert bool(jnp.all(jnp.isnan(wrong.R)))
    assert bool(right.converged) and float(right.chance) < 1e-10 and err < 2.0
