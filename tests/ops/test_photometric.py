"""Photometric stereo on an SDF still life: accuracy vs the renderer's normals, shadows,
relighting, Frankot-Chellappa integration, and the highlight breakdown of the median."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import fsjax
from fsjax import ops as _ops
from fsjax import synth

SIZE = dict(width=64, height=48, pixel_size=0.1)
# 8 lights; steep ones leave no shadow on this still life (checked), low ones cast shadows
HIGH = fsjax.ops.light_directions([66, 70, 74, 78, 66, 70, 74, 78], [0, 45, 90, 135, 180, 225, 270, 315])
LOW = fsjax.ops.light_directions([30, 35, 40, 45, 30, 35, 40, 45], [0, 45, 90, 135, 180, 225, 270, 315])


@pytest.fixture(scope="module")
def scene():
    return synth.still_life_scene()


@pytest.fixture(scope="module")
def unshadowed(scene):
    return synth.render_light_stack(scene, HIGH, shadows=False, **SIZE)


@pytest.fixture(scope="module")
def shadowed(scene):
    return synth.render_light_stack(scene, LOW, shadows=True, **SIZE)


def test_no_shadows_all_methods_exact(unshadowed):
    stack, tr = unshadowed
    n = np.asarray(tr["normals"])
    assert bool(np.all(np.asarray(tr["hit"])))
    ndl = np.einsum("hwc,kc->khw", n, HIGH)
    assert ndl.min() > 0, "the unshadowed stack must have no attached shadow"
    for m in ("ls", "robust", "lmeds"):
        nm = fsjax.ops.photometric_stereo(stack, method=m)
        e = synth.angular_error_deg(nm.normals, n)
        da = float(np.max(np.abs(np.asarray(nm.albedo) - np.asarray(tr["albedo"]))))
        print(f"photometric stereo ({m}), 8 lights, no shadows, {n.shape[0]}x{n.shape[1]}: median angular error "
              f"{np.median(e):.2e} deg (max {e.max():.2e}); max albedo error {da:.1e}")
        assert bool(np.all(np.asarray(nm.valid)))
        assert np.median(e) <= 0.01
        assert da < 1e-9


def test_shadows_bias_least_squares_not_robust(shadowed):
    stack, tr = shadowed
    n = np.asarray(tr["normals"])
    L = np.asarray(stack.lights)
    attached = np.einsum("hwc,kc->khw", n, L) <= 0
    cast = (np.asarray(tr["visibility"]) < 0.5) & ~attached
    shadowed_px = (attached | cast).any(0)
    print(f"shadowed stack: {attached.any(0).mean():.1%} of pixels with an attached shadow, {cast.any(0).mean():.1%} "
          f"with a cast shadow")
    assert attached.any(0).mean() > 0.02 and cast.any(0).mean() > 0.05
    res = {}
    for m in ("ls", "robust"):
        nm = fsjax.ops.photometric_stereo(stack, method=m)
        e = synth.angular_error_deg(nm.normals, n)
        valid = np.asarray(nm.valid)
        res[m] = (np.median(e[shadowed_px & valid]), np.median(e[valid]), valid.mean())
        print(f"  {m}: median error on shadowed pixels {res[m][0]:.2e} deg, over all valid {res[m][1]:.2e} deg, "
              f"valid {res[m][2]:.1%}")
    assert res["ls"][0] >= 1.0  # the null is visibly biased where shadows are
    assert res["robust"][0] <= 0.1 and res["robust"][1] <= 0.1
    assert res["robust"][2] >= 0.99


def test_two_lit_lights_use_the_inequalities():
    """With exactly two lit lights the shadowed inequalities pick the solution (min-norm QP)."""
    L = fsjax.ops.light_directions([40, 40, 40, 40, 40], [0, 90, 180, 225, 300])
    n = np.array([0.7, 0.7, -0.15])
    n /= np.linalg.norm(n)
    meas = 0.6 * np.maximum(L @ n, 0)
    lit = meas > 0.02
    st = fsjax.types.LightStack(jnp.asarray(meas[:, None, None]), jnp.asarray(L))
    nm = fsjax.ops.photometric_stereo(st, shadow_threshold=0.02)
    b = np.asarray(nm.normals[0, 0]) * float(nm.albedo[0, 0])
    print(f"two lit lights ({lit.sum()} of 5): equalities residual {np.max(np.abs(L[lit] @ b - meas[lit])):.1e}, "
          f"shadowed l.b max {np.max(L[~lit] @ b):.3f} <= 0.02, valid {bool(nm.valid[0, 0])}")
    assert lit.sum() == 2 and bool(nm.valid[0, 0])
    assert np.max(np.abs(L[lit] @ b - meas[lit])) < 1e-12
    assert np.max(L[~lit] @ b) <= 0.02 + 1e-12 and b[2] <= 0
    # one lit light (or none): too little to solve, fails closed
    one = np.where(np.arange(5) == 0, meas, 0.0)
    nm1 = fsjax.ops.photometric_stereo(fsjax.types.LightStack(jnp.asarray(one[:, None, None]), jnp.asarray(L)))
    assert not bool(nm1.valid[0, 0]) and np.isnan(float(nm1.albedo[0, 0]))


def test_relight_from_recovered_normals(unshadowed, scene):
    stack, tr = unshadowed
    nm = fsjax.ops.photometric_stereo(stack)
    az, el = 20.0, 68.0
    new = fsjax.ops.light_directions(el, az)[None]
    ref, _ = synth.render_light_stack(scene, new, shadows=False, **SIZE)
    got = fsjax.ops.relight(nm, azimuth_deg=az, elevation_deg=el).data
    rmse = float(jnp.sqrt(jnp.mean((got - ref.data[0]) ** 2)))
    null = float(jnp.sqrt(jnp.mean((stack.data[0] - ref.data[0]) ** 2)))
    print(f"relighting at az {az}, el {el}: RMSE vs render {rmse:.2e}; null (nearest captured light) {null:.3f}")
    assert rmse < 1e-9 and null > 0.01


def test_frankot_chellappa_height_vs_truth(unshadowed):
    _, tr = unshadowed
    nm = fsjax.types.NormalMap(tr["normals"], tr["albedo"])
    z = np.asarray(fsjax.ops.frankot_chellappa(nm, pixel_size=SIZE["pixel_size"]).data)
    d = np.asarray(tr["depth"])
    d = d - d.mean()
    rms = float(np.sqrt(np.mean((z - d) ** 2)))
    rng = float(d.max() - d.min())
    null = float(np.sqrt(np.mean(d**2)))  # a flat surface
    print(f"Frankot-Chellappa on the true normals: depth RMS error {rms:.4f} ({rms / rng:.1%} of the "
          f"{rng:.2f} depth range); null (flat) {null:.4f}")
    assert rms < 0.1 * rng
    assert rms < null / 3


def test_highlight_breakdown_median_fails_at_half(unshadowed):
    stack, tr = unshadowed
    r = synth.highlight_breakdown(stack, np.asarray(tr["normals"]))
    rows = ", ".join(f"{f:.3f}: lmeds {a:.2g} ls {b:.2g}" for f, a, b in zip(r["fraction"], r["lmeds"], r["ls"]))
    print(f"median angular error (deg) vs fraction of highlight-contaminated lights: {rows}")
    K = len(r["fraction"]) - 1
    assert np.all(r["lmeds"][: K // 2] <= 1e-6)  # below one half: the median ignores the outliers
    assert r["lmeds"][K // 2] >= 5.0  # at one half: breakdown, as the theory says
    assert np.all(r["ls"][1:K] >= 5.0)  # least squares breaks with a single contaminated light


def test_bad_input():
    st = fsjax.synth.standard_input(fsjax.types.LightStack)
    with pytest.raises(ValueError, match="photometric_stereo.*method"):
        fsjax.ops.photometric_stereo(st, method="svd")
    with pytest.raises(ValueError, match="photometric_stereo.*shadow_threshold"):
        fsjax.ops.photometric_stereo(st, shadow_threshold=-0.1)
    with pytest.raises(ValueError, match="photometric_stereo.*3 lights"):
        fsjax.ops.photometric_stereo(fsjax.types.LightStack(st.data[:2], st.lights[:2]))
    with pytest.raises(ValueError, match="LightStack.*zero length"):
        fsjax.types.LightStack(st.data, st.lights.at[0].set(0.0))
    with pytest.raises(ValueError, match="frankot_chellappa.*pixel_size"):
        fsjax.ops.frankot_chellappa(fsjax.synth.standard_input(fsjax.types.NormalMap), pixel_size=0.0)
    with pytest.raises(TypeError, match="relight"):
        fsjax.ops.relight(st)
