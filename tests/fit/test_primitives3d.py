"""3-D metrology primitives: closed forms against analytic values, fits against truth,
degenerate input failing closed, and model selection by BIC/AIC over 200 trials."""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fsjax._linalg import FAST_COMPILE
from fsjax.fit import (
    angle_line_plane,
    angle_lines,
    angle_planes,
    fit_circle3d,
    fit_cylinder,
    fit_line3d,
    fit_plane,
    fit_quadric,
    fit_sphere,
    intersect_line_plane,
    intersect_planes,
    line_line_distance,
    point_line_distance,
    point_plane_distance,
    select_model,
)
from fsjax.types import reason_code

MODELS = ("plane", "sphere", "cylinder")


def _rot(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.diag(r))


def sample(kind, seed, n=150, noise=0.01):
    """Noisy patch of a unit plane square / sphere cap (60 deg) / half cylinder, random pose."""
    rng = np.random.default_rng(seed)
    if kind == "plane":
        g = rng.uniform(-1, 1, (n, 2))
        p, nr = np.c_[g, np.zeros(n)], np.tile([0.0, 0.0, 1.0], (n, 1))
    elif kind == "sphere":
        u = rng.normal(size=(12 * n, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        p = nr = u[u[:, 2] > 0.5][:n]
    else:
        th, z = rng.uniform(-np.pi / 2, np.pi / 2, n), rng.uniform(-1, 1, n)
        p, nr = np.c_[np.cos(th), np.sin(th), z], np.c_[np.cos(th), np.sin(th), 0 * z]
    p = p + noise * rng.normal(size=(n, 1)) * nr
    return p @ _rot(rng).T + rng.uniform(-2, 2, 3)


def test_distances_angles_intersections():
    plane = jnp.array([0.0, 0.0, 2.0, 4.0])  # z = 2, unnormalised normal
    assert float(point_plane_distance(jnp.array([1.0, 2.0, 5.0]), plane)) == pytest.approx(3.0, abs=1e-15)
    line = jnp.array([1.0, 1.0, 1.0, 0.0, 0.0, 3.0])
    assert float(point_line_distance(jnp.array([4.0, 5.0, -7.0]), line)) == pytest.approx(5.0, abs=1e-14)
    # skew lines: x-axis and the line {y = t, z = 2, x = 1}: common normal along z, length 2
    l1, l2 = jnp.array([0.0, 0, 0, 1, 0, 0]), jnp.array([1.0, 0, 2, 0, 1, 0])
    assert float(line_line_distance(l1, l2)) == pytest.approx(2.0, abs=1e-15)
    # parallel lines fall back to point-line distance (no division by |d1 x d2| = 0)
    assert float(line_line_distance(l1, jnp.array([5.0, 3, 4, -2, 0, 0]))) == pytest.approx(5.0, abs=1e-14)
    # issue 20 sweep (unit/dtype-dependent thresholds): lines along a diagonal whose float32
    # directions differ by one ulp (parallel to the data's precision; |d1 x d2| ~ 1e-7, above the
    # old switch 1e-12) got the skew formula, whose answer is set by rounding: 70.7 for 141.4 here
    # (with XLA's default optimisation also 0.0 for 1.414); the switch now follows the dtype's eps
    dg = (np.ones(3) / np.sqrt(3)).astype(np.float32)
    dg2 = dg.copy()
    dg2[0] = np.nextafter(dg2[0], np.float32(1))
    for p1, p2 in (([0.3, 0.1, 0.7], [0.3, 1.1, -0.3]), ([0.0, 0.0, 0.0], [100.0, 200.0, 300.0])):
        true = float(np.linalg.norm(np.cross(np.subtract(p2, p1), dg)))
        got = float(line_line_distance(jnp.asarray(np.r_[p1, dg], jnp.float32), jnp.asarray(np.r_[p2, dg2], jnp.float32)))
        assert got == pytest.approx(true, rel=1e-5), (got, true)
    th = 37.0
    d = jnp.array([np.cos(np.radians(th)), np.sin(np.radians(th)), 0.0])
    assert float(angle_lines(l1, jnp.concatenate([jnp.zeros(3), -d]))) == pytest.approx(th, abs=1e-9)
    tilt = jnp.array([0.0, np.sin(np.radians(th)), np.cos(np.radians(th)), 1.0])
    assert float(angle_planes(jnp.array([0.0, 0, 1, 0]), tilt)) == pytest.approx(th, abs=1e-9)
    assert float(angle_line_plane(jnp.concatenate([jnp.zeros(3), d]), jnp.array([1.0, 0, 0, 0]))) == \
        pytest.approx(90 - th, abs=1e-9)
    p, ok = intersect_line_plane(jnp.array([1.0, 2, 3, 1, 1, 1]), plane)
    assert bool(ok) and np.allclose(np.asarray(p), [0.0, 1.0, 2.0], atol=1e-14)
    ln, ok = intersect_planes(jnp.array([1.0, 0, 0, 2]), tilt)
    assert bool(ok)
    assert abs(float(point_plane_distance(ln[:3], tilt))) < 1e-14 and abs(float(ln[0]) - 2) < 1e-14
    assert abs(float(ln[3:] @ tilt[:3])) < 1e-14
    # parallel elements fail closed
    p, ok = intersect_line_plane(jnp.array([0.0, 0, 0, 1, 1, 0]), plane)
    assert not bool(ok) and bool(jnp.all(jnp.isnan(p)))
    ln, ok = intersect_planes(plane, jnp.array([0.0, 0, -1, 7]))
    assert not bool(ok) and bool(jnp.all(jnp.isnan(ln)))
    print("distances, angles, intersections: analytic values within 1e-9 (float64); parallel cases fail closed")


def test_fits_recover_truth():
    rng = np.random.default_rng(7)
    R, t = _rot(rng), np.array([0.3, -1.0, 2.0])
    g = rng.uniform(-1, 1, (200, 2))
    pl = np.c_[g, 0.005 * rng.normal(size=200)] @ R.T + t
    fp = fit_plane(jnp.asarray(pl))
    nerr = np.degrees(np.arccos(min(1.0, abs(float(np.asarray(fp.params[:3]) @ R[:, 2])))))
    tl = rng.uniform(-2, 2, (100, 1))
    li = t + tl * R[:, 0] + 0.005 * rng.normal(size=(100, 3))
    fl = fit_line3d(jnp.asarray(li))
    lerr = np.degrees(np.arccos(min(1.0, abs(float(np.asarray(fl.params[3:]) @ R[:, 0])))))
    u = rng.normal(size=(300, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u = u[u[:, 2] > 0.2][:120]
    fs = fit_sphere(jnp.asarray(t + 1.5 * u + 0.005 * rng.normal(size=u.shape)))
    serr = max(np.linalg.norm(np.asarray(fs.params[:3]) - t), abs(float(fs["r"]) - 1.5))
    a = np.linspace(0, 4.0, 80)
    ci = t + 0.8 * (np.cos(a)[:, None] * R[:, 0] + np.sin(a)[:, None] * R[:, 1]) + 0.005 * rng.normal(size=(80, 3))
    fc = fit_circle3d(jnp.asarray(ci))
    cerr = max(np.linalg.norm(np.asarray(fc.params[:3]) - t), abs(float(fc["r"]) - 0.8))
    cy = sample("cylinder", 3, n=200, noise=0.005)
    fy = fit_cylinder(jnp.asarray(cy))
    print(f"fits (noise 0.005): plane normal {nerr:.3f} deg rms {float(fp.rms_len):.4f}; line direction {lerr:.3f} deg; "
          f"sphere centre/radius error {serr:.4f}; 3-D circle {cerr:.4f}; cylinder radius {float(fy['r']):.4f} "
          f"(truth 1), rms {float(fy.rms_len):.4f}")
    assert nerr < 0.5 and lerr < 0.5 and serr < 0.01 and cerr < 0.01
    assert abs(float(fy["r"]) - 1) < 0.01 and float(fy.rms_len) < 0.006
    for f in (fp, fl, fs, fc, fy):
        assert bool(f.converged) and f.residuals.shape[0] > 0
    # residuals are orthogonal distances: the plane's equal point_plane_distance
    assert np.allclose(np.asarray(fp.residuals), np.asarray(point_plane_distance(jnp.asarray(pl), fp.params)))


def test_degenerate_fits_fail_closed():
    line = np.c_[np.linspace(0, 1, 20), np.linspace(0, 2, 20), np.zeros(20)]
    fp = fit_plane(jnp.asarray(line))
    assert not bool(fp.converged) and bool(jnp.all(jnp.isnan(fp.params)))
    g = np.random.default_rng(0).uniform(-1, 1, (20, 2))
    fs = fit_sphere(jnp.asarray(np.c_[g, np.zeros(20)]))
    assert not bool(fs.converged) and bool(jnp.all(jnp.isnan(fs.params)))
    few = fit_plane(jnp.asarray(line[:3] + [[0, 0, 0], [0, 0, 0], [0, 0, 1.0]]), jnp.array([True, True, False]))
    assert not bool(few.converged)
    fc = fit_circle3d(jnp.asarray(line))
    assert not bool(fc.converged)
    assert not bool(fit_quadric(jnp.asarray(line)).converged)
    nan = line.copy()
    nan[3] = np.nan  # a NaN point is excluded, not propagated
    assert int(fit_line3d(jnp.asarray(nan)).n_used) == 19 and bool(fit_line3d(jnp.asarray(nan)).converged)
    with pytest.raises(ValueError, match="select_model.*criterion"):
        select_model(jnp.asarray(line), criterion="hqc")


def test_unsupported_models_fail_closed_in_any_dtype_and_units():
    """Issue 20 sweep (detectors that accept a model the data do not support, unit/dtype-dependent
    thresholds). Before: collinear float32 points 100-200 units from the origin gave a converged
    plane and 3-D circle (the test ``ev[1] > 1e-12 ev[2]`` sat below float32's rounding), and a
    flat 2 x 2 patch with 0.01 noise gave a converged cylinder of radius 154 (float64 too).
    Now both refuse; the nulls -- a real thin plane in float32 and a real half-cylinder with the
    same noise -- are still accepted."""
    rng = np.random.default_rng(0)
    d = np.array([0.3, 0.5, 0.81]) / np.linalg.norm([0.3, 0.5, 0.81])
    line = np.array([100.0, 200.0, 50.0]) + rng.uniform(-10, 10, (100, 1)) * d
    thin = np.array([100.0, 200.0, 50.0]) + np.c_[rng.uniform(-10, 10, 100), rng.uniform(-0.5, 0.5, 100), np.zeros(100)]
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    fp, fc = fit_plane(f32(line)), fit_circle3d(f32(line))
    assert not bool(fp.converged) and not bool(fc.converged)
    assert bool(fit_plane(f32(thin)).converged)  # the null: a plane 20 x 1 units is resolved in float32
    r2 = np.random.default_rng(0)
    flat = np.c_[r2.uniform(-1, 1, (200, 2)), 0.01 * r2.normal(size=200)]
    fy = fit_cylinder(jnp.asarray(flat))
    assert not bool(fy.converged) and int(fy.reason) == reason_code("unsupported_model")
    cy = fit_cylinder(jnp.asarray(sample("cylinder", 3, n=200, noise=0.01)))
    print(f"flat patch: cylinder refused (reason {int(fy.reason)}); half cylinder, same noise: r {float(cy['r']):.4f}")
    assert bool(cy.converged) and abs(float(cy["r"]) - 1) < 0.02


def test_select_model_names_no_model_when_none_fits():
    """Issue 20 (detectors that accept a model the data do not support): a random blob and a
    torus, fitted by plane / sphere / cylinder / quadric, are explained by none (rms 0.16-0.53
    of the points' spread). Before, select_model named the least bad candidate (blob: cylinder,
    torus: sphere) with no flag; now ``valid`` False, ``choice`` -1, reason ``no_model_fits``.
    The null: a sphere cap (0.01 noise) still selects the sphere, also against its known noise,
    and is refused against a noise ten times smaller than it has."""
    rng = np.random.default_rng(0)
    u, v = rng.uniform(0, 2 * np.pi, (2, 150))
    torus = np.c_[(2 + 0.5 * np.cos(v)) * np.cos(u), (2 + 0.5 * np.cos(v)) * np.sin(u), 0.5 * np.sin(v)]
    blob = rng.normal(size=(150, 3))
    for name, pts in (("blob", blob), ("torus", torus)):
        r = select_model(jnp.asarray(pts))
        print(f"{name}: chosen {r.chosen()}, nearest {r.names[int(r.nearest)]}, rms {np.round(np.asarray(r.rms_len), 3)}")
        assert r.chosen() == "none" and int(r.choice) == -1 and not bool(r.valid)
        assert int(r.reason) == reason_code("no_model_fits") and int(r.nearest) >= 0
    cap = jnp.asarray(sample("sphere", 7))
    r = select_model(cap)
    assert r.chosen() == "sphere" and bool(r.valid) and int(r.reason) == reason_code("ok")
    known = jax.jit(lambda s: select_model(cap, noise=s))
    assert known(0.01).chosen() == "sphere"
    low = known(0.001)
    assert low.chosen() == "none" and int(low.reason) == reason_code("no_model_fits")


_CHUNK = 67  # one compiled program (batch of 67) serves both model-selection tests
_SELECT = jax.jit(jax.vmap(lambda x: select_model(x)))
_SELECT_EXE = {}


def _select(x):
    """``_SELECT`` compiled with ``fsjax._linalg.FAST_COMPILE`` (XLA:CPU's older emitters at level 2)
    instead of the suite's level 0 (tests/conftest.py).

    These two tests run this one program 12 times (804 trials), and its cost is execution (the
    cylinder's multi-start LM), not compilation. Measured per 67-trial chunk, CPU seconds:
    level 0 compile 6.8 + run 7.7; level 1 compile 8.7 + run 2.6; both tests together 90 -> 43 s.
    XLA:CPU enables no fast-math at any level, but rounding can differ in the last digits: every
    asserted rate is unchanged, one printed median moved (cylinder model on 200 sphere patches,
    rms 0.1060 -> 0.1062). FAST_COMPILE against level 1 (one 67-trial cylinder chunk, one process,
    under the suite's level 0, load ~10): compile 11.7 -> 7.3 s CPU, run 1.3-1.6 -> 1.4 s, the
    same choices.
    """
    return _select_lowered(x)[1](x)


def _select_lowered(x):
    """(lowered, compiled) ``_SELECT`` for the shape of ``x``; one lowering and one compile per shape."""
    key = (x.shape, x.dtype)
    if key not in _SELECT_EXE:
        lo = _SELECT.lower(x)
        _SELECT_EXE[key] = (lo, lo.compile(FAST_COMPILE))
    return _SELECT_EXE[key]


_CHUNKS = {}  # (model index, chunk start) -> results of that chunk, shared by the two tests below


def _chunk(i, start):
    """``vmap(select_model)`` on trials ``start .. start + _CHUNK - 1`` of model ``MODELS[i]``.

    Trial ``t`` of model ``i`` is ``sample(kind, 1000 * i + t)`` whatever the number of trials, so
    the 67-trial test is exactly the first chunk of the 200-trial one: a chunk computed for one test
    is reused by the other when both run in the same process (they were computed twice before).
    """
    key = (i, start)
    if key not in _CHUNKS:
        kind = MODELS[i]
        _CHUNKS[key] = _select(jnp.asarray(np.stack([sample(kind, 1000 * i + t)
                                                     for t in range(start, start + _CHUNK)])))
    return _CHUNKS[key]


def _select_chunked(i, n):
    """``vmap(select_model)`` over the first ``n`` trials of model ``MODELS[i]``, in chunks of
    ``_CHUNK`` (the last one filled with further trials and cut off), results concatenated."""
    parts = [_chunk(i, s) for s in range(0, n, _CHUNK)]
    return jax.tree_util.tree_map(lambda *a: jnp.concatenate(a)[:n], *parts)


def _selection_rates(trials):
    rates, evidence = {}, {}
    for i, kind in enumerate(MODELS):
        if i == 0:
            x = jnp.asarray(np.stack([sample(kind, t) for t in range(_CHUNK)]))
            # jaxlib 0.10's batched CPU LAPACK kernels can deadlock XLA:CPU's thread pool when several
            # run at once (tools/repro_xla_hang.py); select_model is written without them.
            calls = re.findall(r"custom_call @(\w+)", _select_lowered(x)[0].as_text())
            assert not [c for c in calls if "lapack" in c], f"LAPACK custom calls in vmap(select_model): {calls}"
        r = _select_chunked(i, trials)
        bic_pick = np.asarray(r.choice)
        aic_pick = np.argmin(np.asarray(r.aic), axis=1)
        rates[kind] = (float(np.mean(bic_pick == i)), float(np.mean(aic_pick == i)))
        rms = np.asarray(r.rms_len)
        evidence[kind] = [float(np.median(c[np.isfinite(c)])) if np.isfinite(c).any() else float("nan")
                          for c in rms.T]  # nan: that model's fit failed on every trial
    return rates, evidence


def _check(trials):
    rates, ev = _selection_rates(trials)
    for kind in MODELS:
        b, a = rates[kind]
        rms = ", ".join(f"{m} {v:.4f}" for m, v in zip(("plane", "sphere", "cylinder", "quadric"), ev[kind]))
        print(f"model selection on {trials} noisy {kind} patches (sigma 0.01, 150 points): BIC correct {b:.3f}, "
              f"AIC correct {a:.3f}; median rms {rms}")
    total = np.mean([rates[k][0] for k in MODELS])
    print(f"BIC correct over all {3 * trials} trials: {total:.3f}")
    assert all(rates[k][0] >= 0.95 for k in MODELS)
    # the null that over-fits: AIC picks a larger nested model on planes noticeably more often
    assert rates["plane"][1] < rates["plane"][0]


def test_model_selection_bic_picks_truth():
    _check(67)  # 201 trials in all


@pytest.mark.slow
def test_model_selection_bic_200_per_model():
    # Once skipped: it hung in XLA:CPU (a deadlock of jaxlib's batched LAPACK kernels in the intra-op
    # pool, tools/repro_xla_hang.py); select_model no longer uses LAPACK (fsjax/_linalg.py).
    _check(200)
