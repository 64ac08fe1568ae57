"""Structured-light scenes with a known answer: a still life in millimetres, a camera-projector
rig, and the captured fringe and Gray-code frames (conventions in the module of
:func:`fsjax.ops.wrapped_phase`). Plain functions; :func:`decode_depth` runs the op chain
(wrapped phase, Gray code, absolute phase, triangulation) on a capture.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_range
from ..ops import absolute_phase, gray_frames, graycode_decode, triangulate_column, wrapped_phase
from ..types import Camera, FringeStack, GrayStack, Image, StructuredLightRig

# ---------------------------------------------------------------------------
# scenes and captures (plain functions, not ops)
# ---------------------------------------------------------------------------


def still_life_mm():
    """A still life in millimetres spanning ~100 mm in depth (z = 420 .. 520 from the camera).

    Back wall z = 520 facing the camera; a sphere, a rounded box, a cylinder lying across, a
    torus and a cone (apex towards the camera) in front of it.
    """
    from ..render import sdf as S

    rot_x = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # local z -> world y
    objs = [
        S.Plane([0.0, 0.0, -1.0], -520.0),
        S.Sphere([-45.0, -30.0, 470.0], 45.0),
        S.RoundBox([50.0, -35.0, 495.0], [35.0, 25.0, 25.0], 6.0),
        S.Cylinder([40.0, 40.0, 490.0], 18.0, 50.0, rotation=rot_x @ np.array([[0, 0, 1.0], [0, 1.0, 0], [-1.0, 0, 0]])),
        S.Torus([-50.0, 45.0, 505.0], 28.0, 10.0),
        S.Cone([0.0, 5.0, 520.0], 30.0, 100.0, rotation=np.diag([1.0, -1.0, -1.0])),
    ]
    return S.SDFScene(objs, albedo=[0.6, 0.8, 0.7, 0.75, 0.65, 0.85])


def standard_rig(width: int = 96, height: int = 72, proj_width: int = 256, proj_height: int = 192,
                 baseline_mm: float = 150.0, gl_trap: bool = False) -> StructuredLightRig:
    """Camera at the origin looking +z (FOV 40 deg) and a projector ``baseline_mm`` to its right,
    aimed at (0, 0, 470) mm (OpenCV pose from :func:`fsjax.render.look_at`, FOV 36 deg).

    ``gl_trap=True`` returns the rig whose projector pose was converted to the GL convention
    and then used as if it were OpenCV (the mistake the convention rule guards against).
    """
    from ..render.camera import gl_from_cv_pose, intrinsics_from_fov, look_at

    K = intrinsics_from_fov(width, height, fov_x_deg=40.0)
    cam = Camera(K, width=width, height=height)
    R, t = look_at([baseline_mm, 0.0, 0.0], [0.0, 0.0, 470.0], up=[0.0, -1.0, 0.0])
    if gl_trap:
        R, t = gl_from_cv_pose(R, t)
    Kp = intrinsics_from_fov(proj_width, proj_height, fov_x_deg=36.0)
    return StructuredLightRig(cam, Camera(Kp, width=proj_width, height=proj_height, R=R, t=t))


def capture_geometry(scene, rig: StructuredLightRig) -> dict:
    """Trace the camera rays, find where each hit lands in the projector and whether the projector
    sees it. Returns numpy ``depth``, ``hit``, ``u_p`` (projector column), ``lit`` (visible from
    the projector and inside its image), ``radiance`` (albedo times the projector's cosine)."""
    from ..render.camera import project
    from ..render.sdf import _soft_shadow, render_sdf

    cam, proj = rig.camera, rig.projector
    out = render_sdf(scene, cam, t_max=1500.0, max_steps=300, ao_samples=1)
    X = out.position
    uv, zp = project(proj, jnp.where(out.hit[..., None], X, 0.0))
    to_p = proj.t - X
    dist = jnp.linalg.norm(to_p, axis=-1)
    ldir = to_p / dist[..., None]

    def vis(p, n, ld, tm):
        ok = jnp.all(jnp.isfinite(p))
        p = jnp.where(ok, p, 0.0)
        n = jnp.where(ok, n, jnp.asarray([0.0, 0.0, -1.0]))
        ld = jnp.where(ok, ld, jnp.asarray([0.0, 0.0, -1.0]))
        v = _soft_shadow(scene, p + 1e-4 * n, n, ld, math.sin(math.radians(0.005)), 0.5, tm, 300, 0.5)
        return jnp.where(ok, v, 0.0)

    v = jax.vmap(vis)(X.reshape(-1, 3), out.normal.reshape(-1, 3), ldir.reshape(-1, 3),
                      jnp.where(jnp.isfinite(dist), dist, 1.0).reshape(-1)).reshape(dist.shape)
    cosang = jnp.sum(out.normal * ldir, axis=-1)
    inside = (uv[..., 0] > -0.5) & (uv[..., 0] < proj.width - 0.5) & (uv[..., 1] > -0.5) & \
             (uv[..., 1] < proj.height - 0.5)
    lit = out.hit & (v > 0.5) & inside & (cosang > 0.05)
    g = {k: np.asarray(a) for k, a in dict(depth=out.depth, hit=out.hit, u_p=uv[..., 0], lit=lit,
                                           radiance=out.albedo * jnp.maximum(cosang, 0.0)).items()}
    g["n_unconverged"] = int(out.n_unconverged)
    return g


def capture_patterns(geom: dict, *, n_shift: int = 8, period_px: float = 8.0, n_code_bits: int = 5,
                     n_full_bits: int = 8, phase_offset_periods: float = 0.0, noise: float = 0.002,
                     ambient: float = 0.05, seed: int = 0) -> dict:
    """Synthesise the captured frames from :func:`capture_geometry`.

    Intensity ``I = ambient rho + radiance pattern(u_p) + noise`` (pattern in [0, 1], 0 where the
    projector does not reach). Returns ``fringes`` (:class:`FringeStack`), ``code``
    (``n_code_bits`` Gray bits of period-wide stripes), ``code_shifted`` (one more bit,
    half-period stripes), ``code_full`` (``n_full_bits`` bits down to single projector pixels,
    the Gray-only null). ``phase_offset_periods`` shifts the fringes against the code (a
    misregistration, in periods) to pin the quarter-period breakdown.
    """
    rng = np.random.default_rng(seed)
    u = np.where(geom["lit"], geom["u_p"], 0.0) + 0.5
    rad = np.where(geom["lit"], geom["radiance"], 0.0)
    base = ambient * np.where(geom["hit"], 0.7, 0.0)

    def shot(pattern):
        return base + rad * pattern + noise * rng.standard_normal(u.shape)

    phi = 2 * np.pi * (u / period_px + phase_offset_periods) - np.pi
    fr = np.stack([shot(0.5 + 0.5 * np.cos(phi - 2 * np.pi * k / n_shift)) for k in range(n_shift)])

    def gray(width_px, n_bits):
        code = np.floor(u / width_px).astype(np.int64)
        pats = gray_frames(code, n_bits, high=1.0, low=0.0)
        return np.stack([shot(p) for p in pats])

    W_full = 2.0 ** np.ceil(np.log2(np.max(u) + 1))
    return dict(fringes=FringeStack(jnp.asarray(fr)), code=GrayStack(jnp.asarray(gray(period_px, n_code_bits))),
                code_shifted=GrayStack(jnp.asarray(gray(period_px / 2, n_code_bits + 1))),
                code_full=GrayStack(jnp.asarray(gray(W_full / 2 ** n_full_bits, n_full_bits))),
                full_stripe_px=float(W_full / 2 ** n_full_bits), period_px=period_px)


def decode_depth(frames: dict, rig: StructuredLightRig, *, min_contrast: float = 0.02) -> dict:
    """The full pipeline and its two nulls, as depth maps (numpy) plus the decoded indices.

    ``depth``: wrapped phase + complementary Gray code; ``depth_gray``: Gray code alone (column
    at the centre of the finest stripe); ``depth_phase``: phase alone (period index 0). The chain
    runs as one compiled program (op by op it compiled ~170 small ones for each capture size).
    """
    check_range("decode_depth", "min_contrast", min_contrast, 0.0, None)
    out = _decode_core(frames["fringes"], frames["code"], frames["code_shifted"], frames["code_full"], rig,
                       frames["period_px"], frames["full_stripe_px"], float(min_contrast))
    return {k: np.array(v) for k, v in out.items()}


@functools.partial(jax.jit, static_argnames=("min_contrast",))
def _decode_core(fringes, code, code_shifted, code_full, rig, P, w, min_contrast):
    phi = wrapped_phase(fringes)
    k1 = graycode_decode(code, min_contrast=min_contrast)
    k2 = graycode_decode(code_shifted, min_contrast=min_contrast)
    ab = absolute_phase(phi, k1, k2)
    col = Image(jnp.nan_to_num(ab.data * P / (2 * jnp.pi) - 0.5, nan=-1e6))
    kf = graycode_decode(code_full, min_contrast=min_contrast)
    col_g = Image(jnp.where(kf.data >= 0, (kf.data + 0.5) * w - 0.5, -1e6))
    col_p = Image((phi.data + jnp.pi) * P / (2 * jnp.pi) - 0.5)
    bad = jnp.isnan(ab.data)
    z = jnp.where(bad, jnp.nan, triangulate_column(col, rig).z)
    zg = jnp.where(kf.data < 0, jnp.nan, triangulate_column(col_g, rig).z)
    zp = triangulate_column(col_p, rig).z
    column = jnp.where(bad, jnp.nan, col.data)
    return dict(depth=z, depth_gray=zg, depth_phase=zp, column=column, k1=k1.data)
