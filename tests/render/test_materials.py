"""Tests of material appearance (fsjax.render.materials): thin films, gratings, anisotropic lobes, colour."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

from fsjax.render import materials as M
from fsjax.render.shading import ggx_brdf


def test_thin_film_zero_quarter_half_wave():
    lam = 550.0
    # zero thickness: the bare glass interface, whatever the film index
    for nf in (1.2, 1.38, 2.0):
        R0 = float(M.thin_film_reflectance(1.0, nf, 1.5, thickness_nm=0.0, wavelength_nm=lam))
        assert abs(R0 - 0.04) < 1e-15
    print(f"thin film, zero thickness on n=1.5: R = {R0:.6f} (bare Fresnel 0.040000)")
    # quarter-wave free-standing soap film (n = 1.33 in air)
    Rq = float(M.thin_film_reflectance(1.0, 1.33, 1.0, thickness_nm=lam / (4 * 1.33), wavelength_nm=lam))
    r01 = -0.33 / 2.33
    closed = (2 * r01 / (1 + r01**2)) ** 2
    print(f"quarter-wave soap film n=1.33 in air: R = {Rq:.6f} (closed form {closed:.6f}, target 0.077113)")
    assert round(Rq, 6) == 0.077113 and abs(Rq - closed) < 1e-15
    # quarter-wave MgF2 on glass: the classic anti-reflection closed form ((n0 ns - nf^2) / (n0 ns + nf^2))^2
    Rar = float(M.thin_film_reflectance(1.0, 1.38, 1.5, thickness_nm=lam / (4 * 1.38), wavelength_nm=lam))
    assert abs(Rar - ((1.5 - 1.38**2) / (1.5 + 1.38**2)) ** 2) < 1e-15 and Rar < 0.04
    # half-wave films are absentee at any angle and polarisation: the bare interface again
    for ang in (0.0, 30.0, 60.0):
        for pol in ("s", "p", "unpolarized"):
            ns = 1.5
            nf = 2.1
            c1 = math.sqrt(1 - (math.sin(math.radians(ang)) / nf) ** 2)
            d = lam / (2 * nf * c1)  # half-wave optical thickness along the refracted direction
            Rh = float(M.thin_film_reflectance(1.0, nf, ns, thickness_nm=d, wavelength_nm=lam, angle_deg=ang,
                                               polarization=pol))
            Rb = float(M.fresnel_dielectric(1.0, ns, angle_deg=ang, polarization=pol))
            assert abs(Rh - Rb) < 1e-14
    # energy: an absorbing-free film reflects at most 1, and total internal reflection gives 1
    R = M.thin_film_reflectance(1.0, 1.33, 1.0, thickness_nm=jnp.linspace(0, 2000, 201), wavelength_nm=lam,
                                angle_deg=40.0)
    assert bool(jnp.all((R >= 0) & (R <= 1)))
    assert abs(float(M.fresnel_dielectric(1.5, 1.0, angle_deg=60.0)) - 1.0) < 1e-12
    # Brewster: p reflectance vanishes at atan(n2/n1)
    assert float(M.fresnel_dielectric(1.0, 1.5, angle_deg=math.degrees(math.atan(1.5)), polarization="p")) < 1e-30


def test_grating_cd_both_orders():
    pitch = 1.6
    for lam in (450.0, 550.0, 650.0):
        p = float(M.grating_angles(lam, pitch, order=1))
        m = float(M.grating_angles(lam, pitch, order=-1))
        truth = math.degrees(math.asin(lam / 1600.0))
        assert abs(p - truth) < 1e-12 and abs(m + truth) < 1e-12
    print(f"CD 1.6 um, normal incidence: m=+-1 at +-{float(M.grating_angles(550.0, pitch)):.4f} deg (550 nm); "
          f"red diffracts more than blue: {float(M.grating_angles(650.0, pitch)):.2f} > "
          f"{float(M.grating_angles(450.0, pitch)):.2f} deg")
    # oblique incidence: both orders satisfy the grating equation; evanescent orders are NaN
    th_i = 30.0
    for mo in (1, -1, -2):
        t = float(M.grating_angles(600.0, pitch, incidence_deg=th_i, order=mo))
        assert abs(1600.0 * (math.sin(math.radians(t)) - math.sin(math.radians(th_i))) - mo * 600.0) < 1e-9
    assert math.isnan(float(M.grating_angles(600.0, pitch, incidence_deg=th_i, order=2)))
    assert math.isnan(float(M.grating_angles(550.0, pitch, order=3)))
    with pytest.raises(ValueError, match="grating_angles.*pitch_um"):
        M.grating_angles(550.0, 0.0)


def test_anisotropic_lobe_follows_roughness_ratio():
    for ax, ay in ((0.1, 0.4), (0.3, 0.15), (0.2, 0.2)):
        wx, wy = M.ggx_lobe_widths(ax, ay)
        assert abs(wx / wy - ax / ay) < 1e-9
        assert abs(wx - ax * math.sqrt(math.sqrt(2) - 1)) < 1e-9
    # the reflected lobe (BRDF over outgoing directions, light at the normal) elongates the same way
    z = jnp.asarray([0.0, 0.0, 1.0])

    def half_angle(axis, ax, ay):
        def f(th):
            v = jnp.asarray([math.sin(th) * axis[0], math.sin(th) * axis[1], math.cos(th)])
            return float(ggx_brdf(z, z, v, alpha_x=ax, alpha_y=ay, f0=1.0))

        half, lo, hi = 0.5 * f(0.0), 0.0, 1.5
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if f(mid) > half else (lo, mid)
        return lo

    ax, ay = 0.05, 0.2
    r = half_angle((1, 0), ax, ay) / half_angle((0, 1), ax, ay)
    print(f"anisotropic GGX (alpha 0.05 x 0.2): reflected-lobe width ratio {r:.4f} vs roughness ratio {ax / ay:.4f}; "
          f"slope-space ratio exact")
    assert abs(r - ax / ay) < 0.02


def test_cie_and_srgb():
    # tabulated CIE 1931 2-degree values (CIE 015:2004) at a few wavelengths
    tab = {450.0: (0.3362, 0.0380, 1.7721), 500.0: (0.0049, 0.3230, 0.2720), 555.0: (0.5121, 1.0000, 0.0057),
           600.0: (1.0622, 0.6310, 0.0008)}
    err = max(float(jnp.max(jnp.abs(M.cie1931_xyz(jnp.asarray(k)) - jnp.asarray(v)))) for k, v in tab.items())
    print(f"CIE 1931 fit (Wyman-Sloan-Shirley 2013) vs table: max abs err {err:.4f}")
    assert err < 0.015
    wl = jnp.arange(380.0, 781.0, 5.0)
    one = M.spectrum_to_linear_srgb(wl, jnp.ones(wl.shape))
    half = M.spectrum_to_linear_srgb(wl, jnp.full(wl.shape, 0.5))
    print(f"flat reflectance 1 -> {np.round(np.asarray(one), 12)}, 0.5 -> {np.round(np.asarray(half), 12)}")
    assert float(jnp.max(jnp.abs(one - 1.0))) < 1e-14 and float(jnp.max(jnp.abs(half - 0.5))) < 1e-14
    # narrow bands land in the right channel
    for centre, ch in ((610.0, 0), (540.0, 1), (450.0, 2)):
        spec = jnp.exp(-0.5 * ((wl - centre) / 10.0) ** 2)
        rgb = M.spectrum_to_linear_srgb(wl, spec)
        assert int(jnp.argmax(rgb)) == ch
    # a soap film's colour changes with thickness (interference) but stays bounded
    films = jnp.stack([M.thin_film_reflectance(1.0, 1.33, 1.0, thickness_nm=t, wavelength_nm=wl)
                       for t in (100.0, 300.0, 500.0)])
    rgb = M.spectrum_to_linear_srgb(wl, films)
    assert rgb.shape == (3, 3) and float(jnp.max(jnp.std(rgb, axis=0))) > 0.01
    with pytest.raises(ValueError, match="spectrum_to_xyz.*increasing"):
        M.spectrum_to_xyz(wl[::-1], jnp.ones(wl.shape))
    with pytest.raises(ValueError, match="thin_film_reflectance.*thickness_nm"):
        M.thin_film_reflectance(1.0, 1.3, 1.5, thickness_nm=-1.0, wavelength_nm=500.0)
