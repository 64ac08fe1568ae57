"""Reflectance models (BRDFs) for shading rendered channels.

Conventions:

* Every function works on unit vectors broadcast over leading axes ``(..., 3)``: the surface
  normal ``n``, the direction **to** the light ``l`` and the direction **to** the viewer
  ``v`` (all pointing away from the surface). Callers pass unnormalised vectors too: they are
  normalised here. A zero-length light direction ``l`` is refused (eagerly when concrete, NaN
  under ``jit``), never silently treated as some default; a zero normal or view vector (a
  background pixel of a :class:`fsjax.render.Raster`) gives 0.
* :func:`blinn_phong`, :func:`ggx_brdf`, :func:`ggx_ndf` return the BRDF ``f_r`` (1/sr).
  :func:`lambert`, :func:`lommel_seeliger` and :func:`hapke` return Hapke's *bidirectional
  reflectance* ``r = f_r cos(i)``: the reflected radiance under a collimated light of unit
  irradiance (measured perpendicular to the beam), which is what an image pixel shows.
  All are zero where the light or the viewer is below the surface (``cos <= 0``).
* Angles: ``i`` incidence, ``e`` emergence, ``g`` phase angle (between ``l`` and ``v``),
  ``psi`` the azimuth between the planes of incidence and emergence.

Models: Lambert; normalised Blinn-Phong; GGX / Trowbridge-Reitz microfacets, isotropic and
anisotropic (Burley 2012 form), with Smith height-correlated masking-shadowing (Heitz 2014)
and Schlick's Fresnel; Lommel-Seeliger; Hapke's bidirectional reflectance (single-scattering
albedo, Henyey-Greenstein phase function, H-functions in the approximation of Hapke 1981,
the shadow-hiding opposition surge of Hapke 1986, and the macroscopic roughness correction
of Hapke 1984; the same equations are collected in Hapke 2012, ch. 12).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from ..types import is_concrete

__all__ = [
    "unit",
    "lambert",
    "blinn_phong",
    "ggx_ndf",
    "ggx_smith_lambda",
    "ggx_brdf",
    "fresnel_schlick",
    "lommel_seeliger",
    "hapke_h",
    "hapke_roughness",
    "hapke",
]


def unit(v, *, name: str = "direction", fn: str = "shading") -> jnp.ndarray:
    """Normalise ``(..., 3)`` vectors; a zero-length (or non-finite) vector is refused.

    Raises ``ValueError`` naming ``fn`` and ``name`` when the input is concrete; under ``jit``
    the result is NaN for such vectors.

    Example:
        >>> [round(float(x), 12) for x in fsjax.render.unit(jnp.asarray([0.0, 3.0, 4.0]))]
        [0.0, 0.6, 0.8]
    """
    v = jnp.asarray(v)
    if not jnp.issubdtype(v.dtype, jnp.floating):
        v = v.astype(jnp.result_type(float))
    n2 = jnp.sum(v * v, axis=-1, keepdims=True)
    ok = (n2 > 0) & jnp.isfinite(n2)
    if is_concrete(ok) and not bool(np.all(np.asarray(ok))):
        raise ValueError(f"{fn}({name}=...): zero-length or non-finite vector; a direction must have length > 0")
    return jnp.where(ok, v / jnp.sqrt(jnp.where(ok, n2, 1.0)), jnp.nan)


def _cos(a, b):
    return jnp.sum(a * b, axis=-1)


def lambert(n, l, *, albedo=1.0) -> jnp.ndarray:
    """Lambertian reflected radiance ``albedo / pi * max(n . l, 0)`` under unit irradiance.

    Example:
        >>> round(float(fsjax.render.lambert(jnp.asarray([0.0, 0, 1]), jnp.asarray([0.0, 0.6, 0.8]))), 9)
        0.254647909
    """
    n = _safe_unit(n)
    l = unit(l, name="l", fn="lambert")
    return jnp.asarray(albedo) / math.pi * jnp.maximum(_cos(n, l), 0.0)


def blinn_phong(n, l, v, *, shininess=32.0, ks=1.0) -> jnp.ndarray:
    """Normalised Blinn-Phong specular BRDF ``ks (s + 8) / (8 pi) (n . h)^s`` (1/sr), h the half vector.

    The ``(s + 8) / (8 pi)`` factor (Akenine-Moller, Haines, Hoffman, Real-Time Rendering,
    3rd ed., 2008, sec. 7.6) keeps the lobe's energy roughly constant over ``s``. Zero where
    ``n . l <= 0`` or ``n . v <= 0``.

    Example:
        >>> z = jnp.asarray([0.0, 0, 1])
        >>> round(float(fsjax.render.blinn_phong(z, z, z, shininess=8.0)), 9)  # 16 / (8 pi)
        0.636619772
    """
    n = _safe_unit(n)
    l = unit(l, name="l", fn="blinn_phong")
    v = _safe_unit(v)
    h = _safe_unit(l + v)
    s = jnp.asarray(shininess)
    val = ks * (s + 8.0) / (8.0 * math.pi) * jnp.maximum(_cos(n, h), 0.0) ** s
    return jnp.where((_cos(n, l) > 0) & (_cos(n, v) > 0), val, 0.0)


def _safe_unit(v):
    n2 = jnp.sum(v * v, axis=-1, keepdims=True)
    ok = n2 > 0
    return jnp.where(ok, v / jnp.sqrt(jnp.where(ok, n2, 1.0)), 0.0)


def _frame(n, tangent):
    """Orthonormal ``(t, b, n)``: ``t`` is ``tangent`` made orthogonal to ``n``."""
    t = tangent - _cos(tangent, n)[..., None] * n
    t = _safe_unit(t)
    b = jnp.cross(n, t)
    return t, b


def ggx_ndf(n, h, *, alpha_x=0.3, alpha_y=None, tangent=(1.0, 0.0, 0.0)) -> jnp.ndarray:
    """GGX / Trowbridge-Reitz normal distribution ``D(h)`` (1/sr), isotropic or anisotropic.

    ``D = 1 / (pi ax ay ((h.t / ax)^2 + (h.b / ay)^2 + (h.n)^2)^2)`` (Burley 2012; for
    ``ax = ay = a`` it is Walter et al. 2007's ``a^2 / (pi (cos^2 (a^2 - 1) + 1)^2)``), with
    ``t`` the ``tangent`` projected on the surface and ``b = n x t``. Normalised so that
    ``int D(h) (h . n) dw_h = 1`` over the hemisphere (tested by quadrature). Zero for
    ``h . n <= 0``.

    Args:
      alpha_x, alpha_y: roughness along ``t`` and ``b`` (``alpha_y=None``: isotropic).

    Example:
        >>> z = jnp.asarray([0.0, 0, 1])
        >>> round(float(fsjax.render.ggx_ndf(z, z, alpha_x=0.5)), 9)  # 1 / (pi a^2)
        1.273239545
    """
    n = _safe_unit(n)
    h = _safe_unit(h)
    ax = jnp.asarray(alpha_x)
    ay = ax if alpha_y is None else jnp.asarray(alpha_y)
    t, b = _frame(n, jnp.asarray(tangent, dtype=n.dtype))
    ht, hb, hn = _cos(h, t), _cos(h, b), _cos(h, n)
    q = (ht / ax) ** 2 + (hb / ay) ** 2 + hn**2
    return jnp.where(hn > 0, 1.0 / (math.pi * ax * ay * q * q), 0.0)


def ggx_smith_lambda(n, w, *, alpha_x=0.3, alpha_y=None, tangent=(1.0, 0.0, 0.0)) -> jnp.ndarray:
    """Smith's ``Lambda(w)`` for GGX: ``(-1 + sqrt(1 + a_w^2 tan^2 theta)) / 2`` (Heitz 2014, sec. 5).

    ``a_w^2 = cos^2 phi ax^2 + sin^2 phi ay^2`` for the azimuth ``phi`` of ``w`` in the
    tangent frame (the anisotropic projected roughness, Heitz 2014, sec. 5.3). Written as
    ``a_w^2 tan^2 = ((w.t ax)^2 + (w.b ay)^2) / (w.n)^2`` so it is smooth at normal incidence.

    Example:
        >>> z = jnp.asarray([0.0, 0, 1])
        >>> float(fsjax.render.ggx_smith_lambda(z, z, alpha_x=0.5))
        0.0
    """
    n = _safe_unit(n)
    w = _safe_unit(w)
    ax = jnp.asarray(alpha_x)
    ay = ax if alpha_y is None else jnp.asarray(alpha_y)
    t, b = _frame(n, jnp.asarray(tangent, dtype=n.dtype))
    wn = _cos(w, n)
    ok = wn > 0
    wn_s = jnp.where(ok, wn, 1.0)
    a2t2 = ((_cos(w, t) * ax) ** 2 + (_cos(w, b) * ay) ** 2) / (wn_s * wn_s)
    return jnp.where(ok, 0.5 * (jnp.sqrt(1.0 + a2t2) - 1.0), jnp.inf)


def fresnel_schlick(cos_theta, f0) -> jnp.ndarray:
    """Schlick's approximation ``F0 + (1 - F0)(1 - cos)^5`` of the Fresnel reflectance (Schlick 1994).

    Example:
        >>> float(fsjax.render.fresnel_schlick(1.0, 0.04))
        0.04
    """
    c = jnp.clip(jnp.asarray(cos_theta), 0.0, 1.0)
    return f0 + (1.0 - f0) * (1.0 - c) ** 5


def ggx_brdf(n, l, v, *, alpha_x=0.3, alpha_y=None, tangent=(1.0, 0.0, 0.0), f0=0.04) -> jnp.ndarray:
    """Cook-Torrance microfacet BRDF with GGX: ``D(h) G2(l, v) F(v.h) / (4 |n.l| |n.v|)`` (1/sr).

    ``G2 = 1 / (1 + Lambda(l) + Lambda(v))`` is Smith's height-correlated masking-shadowing
    (Heitz 2014, sec. 6); ``F`` is Schlick's with normal-incidence reflectance ``f0`` (0.04 for
    a dielectric of n = 1.5). Zero where ``n.l <= 0`` or ``n.v <= 0``.

    Example:
        >>> z = jnp.asarray([0.0, 0, 1])
        >>> # at normal incidence: D = 1/(pi a^2), G2 = 1, F = f0 -> f0 / (4 pi a^2)
        >>> round(float(fsjax.render.ggx_brdf(z, z, z, alpha_x=0.5, f0=1.0)), 9)
        0.318309886
    """
    n = _safe_unit(n)
    l = unit(l, name="l", fn="ggx_brdf")
    v = _safe_unit(v)
    h = _safe_unit(l + v)
    kw = dict(alpha_x=alpha_x, alpha_y=alpha_y, tangent=tangent)
    nl, nv = _cos(n, l), _cos(n, v)
    ok = (nl > 0) & (nv > 0)
    D = ggx_ndf(n, jnp.where(jnp.sum(h * h, -1, keepdims=True) > 0, h, n), **kw)
    lam_l = jnp.where(ok, ggx_smith_lambda(n, jnp.where(ok[..., None], l, n), **kw), 0.0)
    lam_v = jnp.where(ok, ggx_smith_lambda(n, jnp.where(ok[..., None], v, n), **kw), 0.0)
    G = 1.0 / (1.0 + lam_l + lam_v)
    F = fresnel_schlick(_cos(v, h), f0)
    den = jnp.where(ok, 4.0 * nl * nv, 1.0)
    return jnp.where(ok, D * G * F / den, 0.0)


def lommel_seeliger(n, l, v, *, albedo=1.0) -> jnp.ndarray:
    """Lommel-Seeliger reflectance ``r = (w / 4 pi) mu0 / (mu0 + mu)``, ``mu0 = n.l``, ``mu = n.v``.

    The single-scattering law of an isotropically scattering half-space (Hapke 2012,
    ch. 9); its BRDF is ``(w / 4 pi) / (mu0 + mu)``.
    It is :func:`hapke` with isotropic phase function, no opposition surge, ``H = 1`` (the
    multiple-scattering term removed), and zero roughness (tested).

    Example:
        >>> z = jnp.asarray([0.0, 0, 1])
        >>> round(float(fsjax.render.lommel_seeliger(z, z, z, albedo=1.0)), 9)  # 1 / (8 pi)
        0.039788736
    """
    n = _safe_unit(n)
    l = unit(l, name="l", fn="lommel_seeliger")
    v = _safe_unit(v)
    mu0, mu = _cos(n, l), _cos(n, v)
    ok = (mu0 > 0) & (mu > 0)
    return jnp.where(ok, jnp.asarray(albedo) / (4 * math.pi) * mu0 / jnp.where(ok, mu0 + mu, 1.0), 0.0)


def hapke_h(x, w) -> jnp.ndarray:
    """Chandrasekhar's H-function for isotropic scatterers, Hapke's approximation ``(1 + 2x) / (1 + 2 gamma x)``.

    ``gamma = sqrt(1 - w)`` (Hapke 1981, eq. 26); within 4 % of the exact H-function
    (Hapke 2012, ch. 8). ``H(0) = 1``; for ``w = 1``, ``H(x) = 1 + 2x``.

    Example:
        >>> round(float(fsjax.render.hapke_h(0.5, 0.75)), 9)  # (1 + 1) / (1 + 0.5)
        1.333333333
    """
    x = jnp.asarray(x)
    gam = jnp.sqrt(1.0 - jnp.asarray(w))
    return (1.0 + 2.0 * x) / (1.0 + 2.0 * gam * x)


def hapke_roughness(cos_i, cos_e, psi, theta_bar) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """Hapke's macroscopic-roughness correction: effective cosines and the shadowing function.

    Returns ``(mu0_e, mu_e, S)`` of Hapke (1984) (also Hapke 2012, ch. 12):
    with ``chi = 1 / sqrt(1 + pi tan^2 tb)``, ``E1(x) = exp(-2 / (pi tan tb tan x))``,
    ``E2(x) = exp(-1 / (pi tan^2 tb tan^2 x))``, ``eta(x) = chi (cos x + sin x tan tb E2(x) /
    (2 - E1(x)))`` and ``f(psi) = exp(-2 tan(psi / 2))``, separately for ``i <= e`` and
    ``i >= e``. For ``theta_bar = 0`` it returns ``(cos i, cos e, 1)`` exactly.

    Args:
      cos_i, cos_e: cosines of incidence and emergence (> 0).
      psi: azimuth difference in radians, in ``[0, pi]``.
      theta_bar: mean slope angle in radians, in ``[0, pi/2)``.
    """
    mu0 = jnp.asarray(cos_i)
    mu = jnp.asarray(cos_e)
    psi = jnp.abs(jnp.asarray(psi))
    tb = jnp.asarray(theta_bar)
    i = jnp.arccos(jnp.clip(mu0, -1.0, 1.0))
    e = jnp.arccos(jnp.clip(mu, -1.0, 1.0))
    tt = jnp.tan(tb)
    rough = tt > 0
    tts = jnp.where(rough, tt, 1.0)
    chi = 1.0 / jnp.sqrt(1.0 + math.pi * tt * tt)

    def E1(x):
        tx = jnp.tan(x)
        ok = rough & (tx > 0)
        return jnp.where(ok, jnp.exp(-2.0 / (math.pi * tts * jnp.where(ok, tx, 1.0))), 0.0)

    def E2(x):
        tx = jnp.tan(x)
        ok = rough & (tx > 0)
        return jnp.where(ok, jnp.exp(-1.0 / (math.pi * tts * tts * jnp.where(ok, tx * tx, 1.0))), 0.0)

    def eta(x):
        return chi * (jnp.cos(x) + jnp.sin(x) * tt * E2(x) / (2.0 - E1(x)))

    s2 = jnp.sin(psi / 2.0) ** 2
    cp = jnp.cos(psi)
    fpsi = jnp.where(psi < math.pi, jnp.exp(-2.0 * jnp.tan(jnp.minimum(psi, math.pi - 1e-12) / 2.0)), 0.0)
    e1i, e1e, e2i, e2e = E1(i), E1(e), E2(i), E2(e)
    eta_i, eta_e = eta(i), eta(e)
    # i <= e
    den_a = 2.0 - e1e - (psi / math.pi) * e1i
    mu0_a = chi * (mu0 + jnp.sin(i) * tt * (cp * e2e + s2 * e2i) / den_a)
    mu_a = chi * (mu + jnp.sin(e) * tt * (e2e - s2 * e2i) / den_a)
    S_a = mu_a / eta_e * mu0 / eta_i * chi / (1.0 - fpsi + fpsi * chi * mu0 / eta_i)
    # i >= e
    den_b = 2.0 - e1i - (psi / math.pi) * e1e
    mu0_b = chi * (mu0 + jnp.sin(i) * tt * (e2i - s2 * e2e) / den_b)
    mu_b = chi * (mu + jnp.sin(e) * tt * (cp * e2i + s2 * e2e) / den_b)
    S_b = mu_b / eta_e * mu0 / eta_i * chi / (1.0 - fpsi + fpsi * chi * mu / eta_e)
    a = i <= e
    mu0e = jnp.where(a, mu0_a, mu0_b)
    mue = jnp.where(a, mu_a, mu_b)
    S = jnp.where(a, S_a, S_b)
    # theta_bar = 0 is the smooth surface exactly (not 1 - 1 ulp)
    return jnp.where(rough, mu0e, mu0), jnp.where(rough, mue, mu), jnp.where(rough, S, 1.0)


def hapke(n, l, v, *, w=0.5, b0=1.0, h=0.06, xi=0.0, theta_bar_deg=0.0) -> jnp.ndarray:
    """Hapke's bidirectional reflectance ``r = K (w / 4 pi) mu0e / (mu0e + mue) [(1 + B) P + H H - 1] S`` (1/sr).

    ``r`` is the reflected radiance per unit incident irradiance (perpendicular to the beam),
    ``r = f_r cos(i)``; it is zero where the light or the viewer is below the local surface.
    Terms:

    * ``w`` single-scattering albedo; ``P(g)`` the one-term Henyey-Greenstein phase function
      with asymmetry ``xi`` (0 isotropic, < 0 back-scattering);
    * ``H = H(mu0e, w) H(mue, w)`` with :func:`hapke_h` (Hapke 1981);
    * ``B(g) = b0 / (1 + tan(g / 2) / h)`` the shadow-hiding opposition surge of amplitude
      ``b0`` and angular width ``h`` (Hapke 1986; Hapke 2012, ch. 9);
    * ``mu0e, mue, S`` from :func:`hapke_roughness` with mean slope ``theta_bar_deg``
      (Hapke 1984). No porosity factor ``K`` (``K = 1``) and no coherent-backscatter term.

    Example:
        >>> z = jnp.asarray([0.0, 0, 1])
        >>> # isotropic, no surge, smooth: (w/4pi)(1/2)(P + H(1)^2 - 1) with H(1) = 3/(1+2 sqrt(1-w))
        >>> r = fsjax.render.hapke(z, z, z, w=0.75, b0=0.0)
        >>> round(float(r), 9) == round(0.75 / (8 * np.pi) * (1.5 ** 2), 9)
        True
    """
    n = _safe_unit(n)
    l = unit(l, name="l", fn="hapke")
    v = _safe_unit(v)
    mu0, mu = _cos(n, l), _cos(n, v)
    ok = (mu0 > 0) & (mu > 0)
    mu0s = jnp.where(ok, mu0, 0.5)
    mus = jnp.where(ok, mu, 0.5)
    cg = jnp.clip(_cos(l, v), -1.0, 1.0)
    g = jnp.arccos(cg)
    # azimuth between the projections of l and v on the tangent plane
    lp = l - mu0[..., None] * n
    vp = v - mu[..., None] * n
    lpn, vpn = jnp.sum(lp * lp, -1), jnp.sum(vp * vp, -1)
    both = (lpn > 0) & (vpn > 0)
    cpsi = jnp.where(both, _cos(lp, vp) / jnp.sqrt(jnp.where(both, lpn * vpn, 1.0)), 1.0)
    psi = jnp.arccos(jnp.clip(cpsi, -1.0, 1.0))
    tb = jnp.deg2rad(jnp.asarray(theta_bar_deg))
    mu0e, mue, S = hapke_roughness(mu0s, mus, psi, tb)
    xi = jnp.asarray(xi)
    P = (1.0 - xi * xi) / (1.0 + 2.0 * xi * cg + xi * xi) ** 1.5
    tg = jnp.tan(jnp.minimum(g, math.pi - 1e-9) / 2.0)
    B = jnp.asarray(b0) / (1.0 + tg / jnp.asarray(h))
    H = hapke_h(mu0e, w) * hapke_h(mue, w)
    r = jnp.asarray(w) / (4 * math.pi) * mu0e / (mu0e + mue) * ((1.0 + B) * P + H - 1.0) * S
    return jnp.where(ok, r, 0.0)
