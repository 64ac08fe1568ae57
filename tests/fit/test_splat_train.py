"""Splat training: metrics vs references, densification under the cap, a short run beats its init."""

import doctest

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fsjax
from fsjax import Mesh
from fsjax.fit import splat_train as T
from fsjax.synth._pool import icosphere


def test_module_examples():
    res = doctest.testmod(T, extraglobs={"fsjax": fsjax, "jnp": jnp, "np": np, "jax": jax})
    assert res.attempted >= 2 and res.failed == 0


def test_ssim_matches_skimage():
    from skimage.metrics import structural_similarity

    rng = np.random.default_rng(0)
    a = rng.uniform(size=(40, 36, 3))
    b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1)
    ref = structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                channel_axis=-1, data_range=1.0)
    ours = float(T.ssim_color(jnp.asarray(a), jnp.asarray(b)))
    print(f"ssim_color vs skimage: {ours:.12f} vs {ref:.12f} (|diff| {abs(ours - ref):.1e})")
    assert abs(ours - ref) < 1e-12
    p = float(T._psnr(jnp.asarray(a), jnp.asarray(b)))  # evaluate_splats: fsjax.ops.psnr on colour
    assert abs(p - 10 * np.log10(1 / np.mean((a - b) ** 2))) < 1e-9


def test_coverage_holes_per_third():
    alpha = np.ones((9, 4))
    mask = np.ones((9, 4), bool)
    alpha[7:, :2] = 0.1  # 4 holes in the bottom third (12 object pixels)
    h = T.coverage_holes(alpha, mask)
    assert h["bottom"] == pytest.approx(4 / 12) and h["top"] == 0.0 and h["all"] == pytest.approx(4 / 36)
    assert np.isnan(T.coverage_holes(alpha, np.zeros_like(mask))["all"])


def test_densify_respects_cap_and_resets_moments():
    n, cap = 6, 10
    rng = np.random.default_rng(0)
    y = {"means": jnp.asarray(rng.normal(size=(cap, 3))), "log_scales": jnp.full((cap, 3), -1.0),
         "quats": jnp.tile(jnp.asarray([[1.0, 0, 0, 0]]), (cap, 1)), "opacity_logits": jnp.zeros(cap),
         "colors": jnp.zeros((cap, 1, 3)), "uv_offset": jnp.zeros((cap, 2))}
    tx = T._grouped_adam({k: 0.1 for k in y} | {"uv_offset": 0.0}, decay={})
    state = tx.init(y)
    state = T._GroupedAdamState(state.count, {k: v + 1 for k, v in state.mu.items()}, state.nu)
    valid = np.arange(cap) < n
    grad = np.array([5, 4, 3, 2, 1, 0, 0, 0, 0, 0], float)

    import equinox as eqx

    class St(eqx.Module):
        opt_state: object

    y2, st2, v2 = T._densify_prune(y, St(state), valid, grad, 0.5, 0.005, 0.1, np.random.default_rng(1))
    assert v2.sum() == cap  # 5 candidates, only 4 free slots: the cap holds
    assert np.all(np.asarray(st2.opt_state.mu["means"])[6:] == 0)  # new slots: moments reset
    assert np.all(np.asarray(st2.opt_state.mu["means"])[4:6] == 1)  # untouched
    # large splats (scale e^-1 > 0.1) are split: the parent moved, scale divided by 1.6
    assert np.allclose(np.asarray(y2["log_scales"])[0], -1.0 - np.log(1.6))
    assert not np.allclose(np.asarray(y2["means"])[0], np.asarray(y["means"])[0])


@pytest.mark.slow
def test_short_training_beats_init_and_is_deterministic():
    v, f = icosphere(2, 1.0)
    mesh = Mesh(jnp.asarray(v), jnp.asarray(f, jnp.int32))
    data = T.mesh_views(mesh, n_views=8, width=32, height=32, holdout_every=4, capacity=512, n_points=2000)
    kw = dict(n_init=300, max_splats=600, iterations=40, densify_every=10, densify_from=10, progress=False,
              tile_size=16, capacity=256)
    r1 = T.train_splats(jax.random.key(3), data, **kw)
    r2 = T.train_splats(jax.random.key(3), data, **kw)
    assert np.array_equal(np.asarray(r1.gaussians.means), np.asarray(r2.gaussians.means))
    # the second call reuses the compiled step (it was a closure over the call's arrays and
    # compiled again on every call)
    assert r1.compile_seconds > 0 and r2.compile_seconds == 0 and r2.compile_cpu_seconds == 0
    g0 = T.init_from_mesh(jax.random.split(jax.random.key(3), 3)[0], data, 300, 600)
    e0 = T.evaluate_splats(g0, data)
    e1 = T.evaluate_splats(r1.gaussians, data)
    print(f"splat training (icosphere, 32x32, 40 steps): held-out PSNR {e0['psnr']:.2f} -> {e1['psnr']:.2f} dB, "
          f"SSIM {e0['ssim']:.3f} -> {e1['ssim']:.3f}, holes {e1['holes']['all']:.3f}, splats {r1.n_splats}")
    assert e1["psnr"] > e0["psnr"] + 1.0
    assert int(r1.gaussians.valid.sum()) <= 600 and r1.converged
