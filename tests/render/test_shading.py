"""Tests of the reflectance models (fsjax.render.shading)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fsjax.render import shading as S

Z = jnp.asarray([0.0, 0.0, 1.0])


def _dir(theta, phi):
    return jnp.stack([jnp.sin(theta) * jnp.cos(phi), jnp.sin(theta) * jnp.sin(phi), jnp.cos(theta)], -1)


def _hemisphere(nt=400, nphi=400):
    """Midpoint quadrature nodes (directions, weights dw) over the upper hemisphere."""
    th = (np.arange(nt) + 0.5) * (np.pi / 2) / nt
    ph = (np.arange(nphi) + 0.5) * 2 * np.pi / nphi
    T, P = np.meshgrid(th, ph, indexing="ij")
    w = np.sin(T) * (np.pi / 2 / nt) * (2 * np.pi / nphi)
    return _dir(jnp.asarray(T), jnp.asarray(P)), jnp.asarray(w)


def test_zero_light_direction_refused():
    for fn in (lambda l: S.lambert(Z, l), lambda l: S.hapke(Z, l, Z), lambda l: S.ggx_brdf(Z, l, Z),
               lambda l: S.blinn_phong(Z, l, Z), lambda l: S.lommel_seeliger(Z, l, Z)):
        with pytest.raises(ValueError, match=r"\(l=\.\.\.\): zero-length"):
            fn(jnp.zeros(3))
    # under jit: NaN, not a default direction
    out = jax.jit(lambda l: S.lambert(Z, l))(jnp.zeros(3))
    assert bool(jnp.isnan(out))


def test_lambert_albedo_and_cosine():
    w, dw = _hemisphere(200, 64)
    l = _dir(jnp.asarray(0.7), jnp.asarray(0.3))
    # Lambert r = f_r cos i; f_r integrated against cos e over the hemisphere = albedo
    f = S.lambert(Z, l, albedo=0.6) / jnp.cos(0.7)
    hem = float(jnp.sum(f * w[..., 2] * dw))
    print(f"Lambert directional-hemispherical reflectance: {hem:.6f} (albedo 0.6)")
    assert abs(hem - 0.6) < 1e-4
    assert float(S.lambert(Z, jnp.asarray([0.0, 1.0, -0.1]))) == 0.0


def test_ggx_ndf_normalised_iso_and_aniso():
    w, dw = _hemisphere()
    for ax, ay in ((0.3, None), (0.2, 0.6)):
        D = S.ggx_ndf(Z, w, alpha_x=ax, alpha_y=ay)
        tot = float(jnp.sum(D * w[..., 2] * dw))
        print(f"GGX NDF int D cos = {tot:.5f} (alpha {ax}, {ay})")
        assert abs(tot - 1.0) < 2e-3
    # anisotropic with ax = ay equals isotropic; walter's closed form
    h = _dir(jnp.asarray(0.4), jnp.asarray(1.1))
    c = jnp.cos(0.4)
    walter = 0.09 / (math.pi * (c * c * (0.09 - 1) + 1) ** 2)
    assert abs(float(S.ggx_ndf(Z, h, alpha_x=0.3, alpha_y=0.3)) - walter) < 1e-12


def test_ggx_smith_masking_projected_area():
    """int G1(o) <o, m> D(m) dm = cos(theta_o) (Heitz 2014): checks Lambda against D."""
    w, dw = _hemisphere(600, 600)
    for ax, ay in ((0.3, 0.3), (0.15, 0.5)):
        o = _dir(jnp.asarray(1.0), jnp.asarray(0.6))
        lam = S.ggx_smith_lambda(Z, o, alpha_x=ax, alpha_y=ay)
        D = S.ggx_ndf(Z, w, alpha_x=ax, alpha_y=ay)
        proj = jnp.maximum(jnp.sum(w * o, -1), 0.0)
        lhs = float(jnp.sum(proj * D * dw)) / (1.0 + float(lam))
        print(f"Smith G1 projected-area identity: {lhs:.5f} vs cos(theta_o) {math.cos(1.0):.5f} (alpha {ax}, {ay})")
        assert abs(lhs - math.cos(1.0)) < 2e-3


def test_ggx_brdf_reciprocal_and_energy_bounded():
    rng = np.random.default_rng(0)
    l = S.unit(jnp.asarray(rng.normal(size=(50, 3)) * [1, 1, 0.3] + [0, 0, 0.8]))
    v = S.unit(jnp.asarray(rng.normal(size=(50, 3)) * [1, 1, 0.3] + [0, 0, 0.8]))
    a = S.ggx_brdf(Z, l, v, alpha_x=0.2, alpha_y=0.5)
    b = S.ggx_brdf(Z, v, l, alpha_x=0.2, alpha_y=0.5)
    np.testing.assert_allclose(a, b, rtol=1e-12)
    w, dw = _hemisphere(300, 300)
    alb = float(jnp.sum(S.ggx_brdf(Z, w, _dir(jnp.asarray(0.5), jnp.asarray(0.0)), alpha_x=0.3, f0=1.0)
                        * w[..., 2] * dw))
    print(f"GGX albedo (F=1, alpha 0.3, 28.6 deg): {alb:.4f} (must be <= 1: single scattering loses energy)")
    assert 0.85 < alb <= 1.0


def test_blinn_phong_peak_at_half_vector():
    l = _dir(jnp.asarray(0.5), jnp.asarray(0.0))
    v_mirror = _dir(jnp.asarray(0.5), jnp.asarray(math.pi))
    v_off = _dir(jnp.asarray(0.7), jnp.asarray(math.pi))
    s = 20.0
    peak = float(S.blinn_phong(Z, l, v_mirror, shininess=s))
    assert abs(peak - (s + 8) / (8 * math.pi)) < 1e-12
    assert float(S.blinn_phong(Z, l, v_off, shininess=s)) < peak


def test_hapke_limits():
    rng = np.random.default_rng(2)
    l = S.unit(jnp.asarray(rng.normal(size=(40, 3)) * [1, 1, 0.2] + [0, 0, 0.9]))
    v = S.unit(jnp.asarray(rng.normal(size=(40, 3)) * [1, 1, 0.2] + [0, 0, 0.9]))
    mu0, mu = l[:, 2], v[:, 2]
    w = 0.6
    ls = S.lommel_seeliger(Z, l, v, albedo=w)
    # isotropic, no surge, smooth: r = LS * H(mu0) H(mu)
    r = S.hapke(Z, l, v, w=w, b0=0.0, xi=0.0, theta_bar_deg=0.0)
    np.testing.assert_allclose(r, ls * S.hapke_h(mu0, w) * S.hapke_h(mu, w), rtol=1e-12)
    # the opposition surge adds LS * P(0) * b0 at zero phase
    r1 = S.hapke(Z, l[:1], l[:1], w=w, b0=0.8, h=0.05)
    r0 = S.hapke(Z, l[:1], l[:1], w=w, b0=0.0, h=0.05)
    np.testing.assert_allclose(r1 - r0, S.lommel_seeliger(Z, l[:1], l[:1], albedo=w) * 0.8, rtol=1e-12)
    # and decays with phase angle: half amplitude at tan(g/2) = h
    g = 2 * math.atan(0.05)
    lg = _dir(jnp.asarray(g / 2), jnp.asarray(0.0))
    vg = _dir(jnp.asarray(g / 2), jnp.asarray(math.pi))
    d = S.hapke(Z, lg, vg, w=w, b0=0.8, h=0.05) - S.hapke(Z, lg, vg, w=w, b0=0.0, h=0.05)
    np.testing.assert_allclose(d, S.lommel_seeliger(Z, lg, vg, albedo=w) * 0.4, rtol=1e-12)
    # Chandrasekhar H via Hapke 1981: conservative H(1) = 3
    assert float(S.hapke_h(1.0, 1.0)) == 3.0


def test_hapke_roughness():
    ci, ce, psi = jnp.asarray(0.8), jnp.asarray(0.5), jnp.asarray(1.0)
    m0, m, s = S.hapke_roughness(ci, ce, psi, 0.0)
    assert (float(m0), float(m), float(s)) == (0.8, 0.5, 1.0)
    tb = math.radians(25.0)
    # normal incidence and emergence: no visible shadow, S = 1
    assert abs(float(S.hapke_roughness(1.0, 1.0, 0.0, tb)[2]) - 1.0) < 1e-12
    # the two branches (i <= e, i >= e) meet continuously at i = e
    c = math.cos(0.9)
    a = S.hapke_roughness(c, c - 1e-9, 0.7, tb)
    b = S.hapke_roughness(c - 1e-9, c, 0.7, tb)
    for x, y in zip(a, b):
        assert abs(float(x) - float(y)) < 1e-6
    # small theta_bar is continuous with theta_bar = 0
    np.testing.assert_allclose(S.hapke_roughness(ci, ce, psi, 1e-4), (0.8, 0.5, 1.0), atol=1e-3)
    # roughness darkens a surface seen at large phase (shadows), S in (0, 1]
    l = _dir(jnp.asarray(1.2), jnp.asarray(0.0))
    v = _dir(jnp.asarray(1.0), jnp.asarray(math.pi))
    smooth = float(S.hapke(Z, l, v, w=0.5, theta_bar_deg=0.0))
    rough = float(S.hapke(Z, l, v, w=0.5, theta_bar_deg=25.0))
    sr = float(S.hapke_roughness(jnp.cos(1.2), jnp.cos(1.0), math.pi, tb)[2])
    print(f"Hapke at g = 126 deg: smooth {smooth:.5f}, theta_bar 25 deg {rough:.5f}, S = {sr:.4f}")
    assert rough < smooth and 0 < sr < 1
    # gradients are finite at theta_bar = 0 and normal incidence
    gr = jax.grad(lambda t: S.hapke(Z, Z, _dir(jnp.asarray(0.3), jnp.asarray(0.0)), theta_bar_deg=t))(0.0)
    assert bool(jnp.isfinite(gr))
