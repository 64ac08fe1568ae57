"""Photometric-stereo scenes with a known answer: a still life rendered under distant lights.

Ground truth for :func:`fsjax.ops.photometric_stereo` and its relatives (conventions in
that op's module: camera frame OpenCV, lights as unit directions towards the light).
The scenes are rendered with the SDF tracer of :mod:`fsjax.render.sdf`; plain functions.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..ops import photometric_stereo
from ..types import LightStack

# ---------------------------------------------------------------------------
# ground-truth scenes (plain functions, not ops)
# ---------------------------------------------------------------------------


def still_life_scene():
    """A still life on the plane z = 0 (world z up, units arbitrary, ~6 x 5 wide, ~0.9 high).

    A sunk sphere cap, a sunk flat torus, a cone and a sunk lying capsule on a plane, each with
    its own albedo (plane 0.5). Surfaces are continuous across the contacts (creases, no
    overhangs seen from above; the steepest surface is tilted about 55 deg), so depth is a
    height field for normal integration and lights above 60 deg elevation cast no shadow.
    """
    from ..render import sdf as S

    objs = [
        S.Plane([0.0, 0.0, 1.0], 0.0),
        S.Sphere([-1.5, 0.8, -0.75], 1.3),
        S.Torus([1.4, -0.8, -0.25], 0.75, 0.42),
        S.Cone([1.5, 1.2, 0.0], 0.7, 0.9),
        S.Capsule([-2.2, -1.4, -0.3], [-0.4, -1.6, -0.3], 0.5),
    ]
    return S.SDFScene(objs, albedo=[0.5, 0.8, 0.7, 0.9, 0.6])


def overhead_view(width: int = 80, height: int = 64, pixel_size: float = 0.08):
    """Telecentric view straight down onto the still life: ``(R, t, origins, directions)``.

    ``R`` is the ``world_from_camera`` rotation (camera z = world -z, image down = world -y).
    """
    from ..render import look_at
    from ..render.sdf import orthographic_rays

    R, t = look_at([0.0, 0.0, 10.0], [0.0, 0.0, 0.0], up=[0.0, 1.0, 0.0])
    o, d = orthographic_rays(R, t, width, height, pixel_size)
    return R, t, o, d


def render_light_stack(scene, lights_cam, *, width: int = 80, height: int = 64, pixel_size: float = 0.08,
                       shadows: bool = True, light_angular_diameter_deg: float = 0.01):
    """Render a Lambertian :class:`LightStack` of ``scene`` seen by :func:`overhead_view`.

    ``lights_cam (K, 3)`` are camera-frame directions towards the lights. Attached shadows
    come from ``max(n . l, 0)``; cast shadows (``shadows=True``) from the SDF soft-shadow
    visibility of a light of the given angular diameter. Returns ``(stack, truth)`` where
    ``truth`` has camera-frame ``normals``, ``albedo``, ``depth`` (from the view plane),
    ``hit`` and the ``visibility (K, H, W)``.
    """
    from ..render.sdf import shadow_visibility, trace_rays

    R, t, o, d = overhead_view(width, height, pixel_size)
    out = trace_rays(scene, o, d, axis=R[:, 2], t_max=30.0, max_steps=200, ao_samples=1)
    Lc = jnp.asarray(lights_cam)
    Lw = Lc @ R.T
    n_w = out.normal
    if shadows:
        vis = jax.vmap(lambda lw: shadow_visibility(scene, out.position, n_w, lw, t_max=12.0,
                                                    light_angular_diameter_deg=light_angular_diameter_deg,
                                                    shadow_min_step=0.01, shadow_steps=240, offset=1e-6))(Lw)
    else:
        vis = jnp.ones((Lc.shape[0],) + out.depth.shape, Lc.dtype)
    shade = jnp.maximum(jnp.einsum("hwc,kc->khw", n_w, Lw), 0.0)
    data = jnp.where(out.hit[None], out.albedo[None] * shade * vis, 0.0)
    n_c = n_w @ R
    truth = dict(normals=n_c, albedo=out.albedo, depth=out.depth, hit=out.hit, visibility=vis,
                 n_unconverged=int(out.n_unconverged))
    return LightStack(data, Lc), truth


def angular_error_deg(n_est, n_true, mask=None) -> np.ndarray:
    """Per-pixel angle between two normal fields (degrees), over ``mask`` (flattened)."""
    a = np.asarray(n_est, float)
    b = np.asarray(n_true, float)
    cos = np.sum(a * b, -1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    # atan2 of |cross| and dot keeps precision for tiny angles
    cr = np.linalg.norm(np.cross(a, b), axis=-1)
    ang = np.degrees(np.arctan2(cr, np.sum(a * b, -1)))
    del cos
    return ang if mask is None else ang[np.asarray(mask)]


def contaminate_highlights(stack: LightStack, n_lights: int, *, strength: float = 1.5,
                           highlight_normal=(0.4, -0.3, -1.0), seed: int = 0) -> LightStack:
    """Add a coherent highlight to ``n_lights`` randomly chosen lights per pixel (plain function).

    The highlight is ``strength max(h . l_k, 0)`` with a fixed unit ``h``: a contaminated
    measurement is then exactly Lambertian for ``b + strength h``, the hardest case for a
    robust estimator (the outliers agree with each other). The subset differs per pixel
    (deterministic ``seed``).
    """
    K, Hh, Ww = stack.data.shape
    h = np.asarray(highlight_normal, float)
    h /= np.linalg.norm(h)
    L = np.asarray(stack.lights)
    hl = strength * np.maximum(L @ h, 0.0)
    rng = np.random.default_rng(seed)
    order = np.argsort(rng.random((Hh, Ww, K)), axis=-1)
    mask = np.moveaxis(order < n_lights, -1, 0)
    return LightStack(stack.data + jnp.asarray(mask * hl[:, None, None]), stack.lights)


def highlight_breakdown(stack: LightStack, normals_true, *, methods=("ls", "robust", "lmeds"), seed: int = 0,
                        **kw) -> dict:
    """Median angular error (deg) of each method vs the number of highlight-contaminated lights.

    Returns ``{"fraction": (K+1,), method: (K+1,)}`` for ``0..K`` contaminated lights per pixel.
    """
    K = stack.data.shape[0]
    out: dict = {"fraction": np.arange(K + 1) / K}
    for m in methods:
        out[m] = np.zeros(K + 1)
    for k in range(K + 1):
        st = contaminate_highlights(stack, k, seed=seed, **kw)
        for m in methods:
            nm = photometric_stereo(st, method=m)
            out[m][k] = float(np.nanmedian(angular_error_deg(nm.normals, normals_true)))
    return out
