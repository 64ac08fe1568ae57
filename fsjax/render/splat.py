"""Gaussian splat rasteriser in plain JAX/XLA: EWA projection, fixed-capacity tiles, compositing.

A differentiable renderer for :class:`fsjax.Gaussians` (the 3DGS parameterisation of Kerbl,
Kopanas, Leimkuehler & Drettakis 2023, "3D Gaussian Splatting for Real-Time Radiance Field
Rendering", ACM TOG 42(4)) that runs on any XLA backend (CPU included): no custom kernels.

Conventions (camera model of :mod:`fsjax.render.camera`):

* OpenCV camera frame (x right, y down, z forward), pose ``world_from_camera``; pixel
  centres on integers, ``u`` = column, ``v`` = row. Splatting uses the pinhole part of the
  camera only: a camera with non-zero distortion is refused eagerly (undistort the images).
* Splat ``i``: covariance ``Sigma = R(q) diag(exp(2 s)) R(q)^T`` (``q`` normalised at use),
  opacity ``sigmoid(opacity_logit)``, colour from spherical harmonics of degree 0-3
  (``K = 1, 4, 9, 16`` coefficients, real SH with the 3DGS sign convention, ``+0.5`` offset,
  clamped at 0) evaluated along the direction from the camera centre to the mean.
* Projection (EWA, Zwicker et al. 2002): ``Sigma_2d = J W Sigma W^T J^T + d I`` with
  ``W = R_cam^T`` and ``J`` the Jacobian of the pinhole map at the mean (``x/z``, ``y/z``
  clamped to 1.3 x the half field of view inside ``J`` only, as in 3DGS). The screen-space
  dilation ``d = dilation_px2`` (default **0.3 px^2** on the diagonal) is stated here once;
  opacity is not compensated for it.
* Near plane by extent: splat ``i`` with camera depth ``z`` and depth spread
  ``sigma_z = sqrt((W Sigma W^T)_zz)`` is culled only when its whole ``near_extent_sigma``
  (3) sigma extent lies in front of the camera's near plane, ``z + 3 sigma_z < near``. A
  splat whose centre is behind the near plane but whose extent crosses it (a ground splat
  under a low camera) is kept and drawn from the point of its ridge on the near plane,
  ``p + Sigma_c e_z (near - z) / Sigma_c,zz`` (the conditional mean at depth ``near``), with its
  peak opacity and the EWA Jacobian at that point: an approximation that covers the image
  where the splat's visible part is, instead of leaving a hole. Centre-only culling is the
  defect this avoids (tested here and by the browser viewer test).
* Per-pixel opacity ``alpha = min(alpha_max, o exp(-q/2))`` with ``q`` the Mahalanobis form
  of the 2-D conic; a splat contributes only where ``alpha >= alpha_min`` (1/255). That rule
  gives every splat an exact finite support: ``q <= r^2`` with ``r^2 = 2 ln(o / alpha_min)``,
  whose axis-aligned box ``(r sqrt(S_uu), r sqrt(S_vv))`` is what the tiler bins. Tiling is
  therefore exact -- the tiled and dense renderers agree to rounding when no tile overflows.
* Tiles of ``tile_size`` x ``tile_size`` pixels; each tile keeps at most ``capacity``
  splats (a static int), the nearest ones by centre depth. Splat-tile pairs beyond the
  capacity are dropped and counted in ``SplatRender.overflow`` (and ``overflow_tiles``):
  never a silent blank patch.
* Compositing front to back by centre depth: ``w_i = alpha_i T_i``, ``T_i = prod_{j<i}
  (1 - alpha_j)``, with early termination: splat ``i`` and all behind it are skipped once
  ``T_i (1 - alpha_i) < t_min`` (1e-4). In XLA the termination is a mask (exact, same
  numbers and gradients) rather than saved work.
* Outputs: colour (plus ``(1 - A) * background``), accumulated alpha ``A = sum w_i``,
  expected depth ``sum w_i z_i / A`` (0 where ``A = 0``: "no return"), median depth (the
  centre depth of the splat at which ``T`` first drops below 0.5; 0 where it never does),
  and the depth distortion ``sum_{i,j} w_i w_j |z_i - z_j|`` (2DGS, Huang et al. 2024),
  computed in one front-to-back pass with prefix sums ``2 sum_i w_i (z_i W_{<i} - S_{<i})``.

Differentiable (reverse mode) with respect to every Gaussian parameter and the camera's
``K``, ``R`` and ``t``; :func:`render_splats_dense` is the slow reference (every splat on every
pixel, one global depth sort) used by the tests.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ..types import Camera, Gaussians, is_concrete
from .camera import world_to_camera

__all__ = [
    "SplatRender",
    "ProjectedSplats",
    "project_gaussians",
    "render_splats",
    "render_splats_dense",
    "sh_to_rgb",
    "rgb_to_sh0",
    "SH_C0",
]

SH_C0 = 0.28209479177387814
_SH_C1 = 0.4886025119029199
_SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
          0.5462742152960396)
_SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
          -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


class ProjectedSplats(eqx.Module):
    """Screen-space splats: pixel mean ``uv (N, 2)``, conic ``(N, 3)`` = ``(a, b, c)`` of the
    inverse 2-D covariance, covariance ``cov2d (N, 3)`` = ``(S_uu, S_uv, S_vv)`` px^2, centre
    depth ``depth (N,)``, opacity ``(N,)``, colour ``rgb (N, 3)``, support half-extent
    ``extent (N, 2)`` px (``-1`` when culled), ``visible (N,)``, ``n_culled_near`` (count of
    valid splats culled by the near plane), ``n_degenerate`` (valid splats with a zero-length
    quaternion or non-finite parameters: culled and counted)."""

    uv: Float[Array, "N 2"]
    conic: Float[Array, "N 3"]
    cov2d: Float[Array, "N 3"]
    depth: Float[Array, " N"]
    opacity: Float[Array, " N"]
    rgb: Float[Array, "N 3"]
    extent: Float[Array, "N 2"]
    visible: Array
    n_culled_near: Int[Array, ""]
    n_degenerate: Int[Array, ""]


class SplatRender(eqx.Module):
    """Result of :func:`render_splats`: images ``(H, W[, 3])`` and tile statistics.

    ``color`` linear RGB; ``alpha`` accumulated opacity; ``depth`` expected depth (0 = no
    return); ``median_depth`` (0 = no return); ``distortion`` the 2DGS per-ray pairwise term;
    ``overflow`` splat-tile pairs dropped because a tile was full (0 for the dense renderer);
    ``overflow_tiles`` tiles that overflowed; ``max_tile_count`` the largest per-tile demand;
    ``projected`` the screen-space splats.
    """

    color: Float[Array, "H W 3"]
    alpha: Float[Array, "H W"]
    depth: Float[Array, "H W"]
    median_depth: Float[Array, "H W"]
    distortion: Float[Array, "H W"]
    overflow: Int[Array, ""]
    overflow_tiles: Int[Array, ""]
    max_tile_count: Int[Array, ""]
    projected: ProjectedSplats


# ---------------------------------------------------------------------------
# colour
# ---------------------------------------------------------------------------


def rgb_to_sh0(rgb):
    """DC spherical-harmonic coefficient of a view-independent colour: ``(rgb - 0.5) / C0``."""
    return (jnp.asarray(rgb) - 0.5) / SH_C0


def sh_to_rgb(colors, dirs):
    """Colour of SH coefficients ``colors (..., K, 3)`` along unit directions ``dirs (..., 3)``.

    Real spherical harmonics up to degree 3 (``K`` in 1, 4, 9, 16) with the 3DGS sign
    convention; result ``max(sum_k c_k Y_k(d) + 0.5, 0)``.

    Example:
        >>> c = fsjax.render.rgb_to_sh0(jnp.asarray([[0.2, 0.5, 0.9]]))[:, None, :]
        >>> [round(float(v), 12) for v in fsjax.render.sh_to_rgb(c, jnp.asarray([[0.0, 0.0, 1.0]]))[0]]
        [0.2, 0.5, 0.9]
    """
    colors = jnp.asarray(colors)
    K = colors.shape[-2]
    if K not in (1, 4, 9, 16):
        raise ValueError(f"sh_to_rgb(colors=...): K = {K} coefficients; expected 1, 4, 9 or 16 (degree 0-3)")
    sh = lambda k: colors[..., k, :]  # noqa: E731
    c = SH_C0 * sh(0)
    if K >= 4:
        x, y, z = (dirs[..., i : i + 1] for i in range(3))
        c = c - _SH_C1 * y * sh(1) + _SH_C1 * z * sh(2) - _SH_C1 * x * sh(3)
        if K >= 9:
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            c = (c + _SH_C2[0] * xy * sh(4) + _SH_C2[1] * yz * sh(5) + _SH_C2[2] * (2 * zz - xx - yy) * sh(6)
                 + _SH_C2[3] * xz * sh(7) + _SH_C2[4] * (xx - yy) * sh(8))
            if K >= 16:
                c = (c + _SH_C3[0] * y * (3 * xx - yy) * sh(9) + _SH_C3[1] * xy * z * sh(10)
                     + _SH_C3[2] * y * (4 * zz - xx - yy) * sh(11)
                     + _SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh(12)
                     + _SH_C3[4] * x * (4 * zz - xx - yy) * sh(13) + _SH_C3[5] * z * (xx - yy) * sh(14)
                     + _SH_C3[6] * x * (xx - 3 * yy) * sh(15))
    return jnp.maximum(c + 0.5, 0.0)


# ---------------------------------------------------------------------------
# projection
# ---------------------------------------------------------------------------


def _quat_to_rotmat(q):
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return jnp.stack([
        jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def _check(g, cam, fn, *, alpha_min, alpha_max, near, dilation_px2):
    if not isinstance(g, Gaussians):
        raise TypeError(f"{fn}(gaussians=...): expected Gaussians, got {type(g).__name__}")
    if g.batch_shape:
        raise ValueError(f"{fn}(gaussians=...): expected one set of splats, got batch shape {g.batch_shape}")
    if not isinstance(cam, Camera):
        raise TypeError(f"{fn}(camera=...): expected a Camera, got {type(cam).__name__}")
    if cam.batch_shape:
        raise ValueError(f"{fn}(camera=...): expected one camera, got batch shape {cam.batch_shape}; use jax.vmap")
    if is_concrete(cam.dist) and bool(np.any(np.asarray(cam.dist) != 0)):
        raise ValueError(f"{fn}(camera=...): splatting uses the pinhole model; the camera has non-zero "
                         "distortion (undistort the images first)")
    for name, v, lo, hi in (("alpha_min", alpha_min, 0.0, 1.0), ("alpha_max", alpha_max, 0.0, 1.0)):
        if is_concrete(v) and not (lo < float(v) < hi):
            raise ValueError(f"{fn}({name}=...): must be in ({lo}, {hi}), got {v}")
    if is_concrete(alpha_min) and is_concrete(alpha_max) and not float(alpha_min) < float(alpha_max):
        raise ValueError(f"{fn}(alpha_min=...): must be below alpha_max={alpha_max}, got {alpha_min}")
    if is_concrete(near) and not float(near) > 0:
        raise ValueError(f"{fn}(near=...): must be > 0, got {near}")
    if is_concrete(dilation_px2) and not float(dilation_px2) > 0:
        raise ValueError(f"{fn}(dilation_px2=...): must be > 0 (it keeps 2-D covariances invertible), "
                         f"got {dilation_px2}")


def project_gaussians(gaussians: Gaussians, camera: Camera, *, near: float = 0.01,
                      dilation_px2: float = 0.3, alpha_min: float = 1.0 / 255.0,
                      near_extent_sigma: float = 3.0, uv_offset=None) -> ProjectedSplats:
    """Project splats to screen space: EWA 2-D covariances, support extents, near-plane culling.

    See the module docstring for the maths. ``uv_offset (N, 2)`` is added to the projected
    means (zero by default); its gradient is the screen-space positional gradient used by
    densification.

    Example:
        >>> g = fsjax.Gaussians(jnp.asarray([[0.0, 0.0, 4.0]]), jnp.log(jnp.full((1, 3), 0.1)),
        ...                     jnp.asarray([[1.0, 0.0, 0.0, 0.0]]), jnp.asarray([2.0]), jnp.ones((1, 3)))
        >>> cam = fsjax.Camera.from_intrinsics(100.0, 100.0, 15.5, 11.5, width=32, height=24)
        >>> p = fsjax.render.project_gaussians(g, cam)
        >>> [round(float(v), 9) for v in p.uv[0]], round(float(p.cov2d[0, 0]), 9)  # (100*0.1/4)^2 + 0.3
        ([15.5, 11.5], 6.55)
    """
    _check(gaussians, camera, "project_gaussians", alpha_min=alpha_min, alpha_max=0.99, near=near,
           dilation_px2=dilation_px2)
    return _project(gaussians, camera, near, dilation_px2, alpha_min, near_extent_sigma, uv_offset)


@eqx.filter_jit
def _project(g, camera, near, dilation_px2, alpha_min, near_extent_sigma, uv_offset):
    dt = jnp.result_type(g.means.dtype, camera.K.dtype)
    K = camera.K.astype(dt)
    p = world_to_camera(camera, g.means.astype(dt))
    x, y, z = p[:, 0], p[:, 1], p[:, 2]

    qn = jnp.linalg.norm(g.quats, axis=-1)
    good_q = qn > 0
    q = g.quats / jnp.where(good_q, qn, 1.0)[:, None]
    Rq = _quat_to_rotmat(q.astype(dt))
    M = Rq * jnp.exp(g.log_scales.astype(dt))[:, None, :]
    Sw = M @ jnp.swapaxes(M, -1, -2)
    W = camera.R.astype(dt).T
    Sc = W[None] @ Sw @ W.T[None]
    sz = jnp.sqrt(jnp.maximum(Sc[:, 2, 2], 0.0))

    finite = (jnp.all(jnp.isfinite(g.means), -1) & jnp.all(jnp.isfinite(g.log_scales), -1)
              & jnp.isfinite(g.opacity_logits) & jnp.all(jnp.isfinite(g.colors), (-1, -2)))
    degenerate = g.valid & ~(good_q & finite)
    behind = z + near_extent_sigma * sz < near
    alive = g.valid & good_q & finite & ~behind

    # a splat straddling the near plane (centre behind it, extent in front) is drawn from the point
    # of its ridge at the near plane: p + Sigma e_z (near - z) / Sigma_zz (the conditional mean at
    # depth `near`), projected there with its peak opacity
    zp = jnp.maximum(z, near)
    szz = Sc[:, 2, 2]
    shift = jnp.where(z < near, (zp - z) / jnp.where(szz > 0, szz, 1.0), 0.0)
    x = x + Sc[:, 0, 2] * shift
    y = y + Sc[:, 1, 2] * shift
    fx, fy, sk, cx, cy = K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2]
    u = fx * x / zp + sk * y / zp + cx
    v = fy * y / zp + cy
    if uv_offset is not None:
        uv_offset = jnp.asarray(uv_offset, dt)
        u = u + uv_offset[:, 0]
        v = v + uv_offset[:, 1]
    # Jacobian with x/z, y/z clamped to 1.3 x the half field of view (only inside J)
    lim_x = 1.3 * (0.5 * camera.width) / fx
    lim_y = 1.3 * (0.5 * camera.height) / fy
    tx = jnp.clip(x / zp, -lim_x, lim_x) * zp
    ty = jnp.clip(y / zp, -lim_y, lim_y) * zp
    zero = jnp.zeros_like(zp)
    J = jnp.stack([
        jnp.stack([fx / zp, sk / zp, -(fx * tx + sk * ty) / zp**2], -1),
        jnp.stack([zero, fy / zp, -fy * ty / zp**2], -1),
    ], -2)
    S2 = J @ Sc @ jnp.swapaxes(J, -1, -2)
    a = S2[:, 0, 0] + dilation_px2
    b = S2[:, 0, 1]
    c = S2[:, 1, 1] + dilation_px2
    det = a * c - b * b
    det_ok = det > 0
    dets = jnp.where(det_ok, det, 1.0)
    conic = jnp.stack([c / dets, -b / dets, a / dets], -1)

    opacity = jax.nn.sigmoid(g.opacity_logits.astype(dt))
    r2 = 2.0 * jnp.log(jnp.maximum(opacity, alpha_min) / alpha_min)
    alive = alive & det_ok & (opacity > alpha_min)
    ext = jnp.stack([jnp.sqrt(r2 * jnp.maximum(a, 0.0)), jnp.sqrt(r2 * jnp.maximum(c, 0.0))], -1)
    ext = jnp.where(alive[:, None], ext, -1.0)

    cen = camera.t.astype(dt)
    d = g.means.astype(dt) - cen
    dn = jnp.linalg.norm(d, axis=-1, keepdims=True)
    dirs = d / jnp.where(dn > 0, dn, 1.0)
    rgb = sh_to_rgb(g.colors.astype(dt), dirs)

    return ProjectedSplats(
        uv=jnp.stack([u, v], -1),
        conic=conic,
        cov2d=jnp.stack([a, b, c], -1),
        depth=z,
        opacity=jnp.where(alive, opacity, 0.0),
        rgb=rgb,
        extent=ext,
        visible=alive,
        n_culled_near=jnp.sum(g.valid & good_q & finite & behind).astype(jnp.int32),
        n_degenerate=jnp.sum(degenerate).astype(jnp.int32),
    )


# ---------------------------------------------------------------------------
# compositing (shared by the tiled and the dense renderer)
# ---------------------------------------------------------------------------


def _alphas(px, uv, conic, opacity, alpha_min, alpha_max):
    """Per-pixel opacity ``(P, C)`` of splats ``(C, ...)`` at pixel centres ``px (P, 2)``."""
    dx = px[:, None, 0] - uv[None, :, 0]
    dy = px[:, None, 1] - uv[None, :, 1]
    q = conic[None, :, 0] * dx * dx + 2.0 * conic[None, :, 1] * dx * dy + conic[None, :, 2] * dy * dy
    al = jnp.minimum(alpha_max, opacity[None, :] * jnp.exp(-0.5 * jnp.maximum(q, 0.0)))
    return jnp.where(al >= alpha_min, al, 0.0)


def _composite(alpha, rgb, z, t_min, background):
    """Front-to-back compositing of ``alpha (P, C)`` (sorted by depth) with colours ``(C, 3)``."""
    # transmittance through prefix sums of log(1 - alpha) (alpha <= alpha_max < 1): cheaper than a
    # cumulative product, forward and backward, on CPU
    logt = jnp.cumsum(jnp.log1p(-alpha), axis=-1)
    T_incl = jnp.exp(logt)
    T_excl = jnp.exp(logt - jnp.log1p(-alpha))
    keep = T_incl >= t_min
    w = jnp.where(keep, alpha * T_excl, 0.0)
    A = jnp.sum(w, -1)
    color = w @ rgb + (1.0 - A)[:, None] * background[None, :]
    wz = jnp.sum(w * z[None, :], -1)
    has = A > 0
    depth = jnp.where(has, wz / jnp.where(has, A, 1.0), 0.0)
    crossed = keep & (T_incl < 0.5)
    any_c = jnp.any(crossed, -1)
    idx = jnp.argmax(crossed, -1)
    median = jnp.where(any_c, z[idx], 0.0)
    Wp = jnp.cumsum(w, -1) - w
    Sp = jnp.cumsum(w * z[None, :], -1) - w * z[None, :]
    distortion = 2.0 * jnp.sum(w * (z[None, :] * Wp - Sp), -1)
    return color, A, depth, median, distortion


def _defaults(proj, background):
    dt = proj.uv.dtype
    return jnp.zeros(3, dt) if background is None else jnp.broadcast_to(jnp.asarray(background, dt), (3,))


def render_splats(gaussians: Gaussians, camera: Camera, *, tile_size: int = 16, capacity: int = 256,
                  background=None, near: float = 0.01, dilation_px2: float = 0.3,
                  alpha_min: float = 1.0 / 255.0, alpha_max: float = 0.99, t_min: float = 1e-4,
                  near_extent_sigma: float = 3.0, uv_offset=None) -> SplatRender:
    """Render splats through a pinhole camera with fixed-capacity screen tiles.

    Each ``tile_size`` x ``tile_size`` tile keeps the ``capacity`` nearest splats (by centre
    depth) whose exact support box overlaps it, composites them front to back, and counts what
    did not fit in ``overflow``. Memory is ``O(tiles x capacity x tile_size^2)``.

    Args:
        gaussians: one set of splats (``N`` of them).
        camera: one pinhole :class:`fsjax.Camera` (zero distortion), image ``height x width``.
        tile_size: tile edge in pixels (static int).
        capacity: splats per tile (static int); overflow is counted, not hidden.
        background: RGB ``(3,)`` behind the splats (default black).
        near: near-plane depth (camera units); culling by extent (module docstring).
        dilation_px2: screen-space dilation added to the 2-D covariance diagonal (px^2).
        alpha_min, alpha_max: per-pixel opacity floor (defines the support) and clamp.
        t_min: early-termination transmittance.
        near_extent_sigma: the extent (in sigmas) used by near-plane culling.
        uv_offset: ``(N, 2)`` offset of the projected means (for screen-space gradients).

    Returns:
        :class:`SplatRender`. Agrees with :func:`render_splats_dense` to 1e-12 (float64, images
        and gradients) when ``overflow == 0`` (tested).

    Example:
        >>> g = fsjax.Gaussians(jnp.asarray([[0.0, 0.0, 4.0]]), jnp.log(jnp.full((1, 3), 0.1)),
        ...                     jnp.asarray([[1.0, 0.0, 0.0, 0.0]]), jnp.asarray([20.0]),
        ...                     fsjax.render.rgb_to_sh0(jnp.asarray([[1.0, 0.5, 0.25]])))
        >>> cam = fsjax.Camera.from_intrinsics(100.0, 100.0, 16.0, 12.0, width=32, height=24)
        >>> out = fsjax.render.render_splats(g, cam)  # centre pixel: alpha clamped at 0.99
        >>> round(float(out.alpha.max()), 9), round(float(out.depth.max()), 9), int(out.overflow)
        (0.99, 4.0, 0)
    """
    _check(gaussians, camera, "render_splats", alpha_min=alpha_min, alpha_max=alpha_max, near=near,
           dilation_px2=dilation_px2)
    for name, v in (("tile_size", tile_size), ("capacity", capacity)):
        if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < 1:
            raise ValueError(f"render_splats({name}=...): must be a static positive int, got {v!r}")
    return _render_tiled(gaussians, camera, background, near, dilation_px2, alpha_min, alpha_max, t_min,
                         near_extent_sigma, uv_offset, int(tile_size), int(capacity))


@eqx.filter_jit
def _render_tiled(gaussians, camera, background, near, dilation_px2, alpha_min, alpha_max, t_min,
                  near_extent_sigma, uv_offset, tile_size, capacity):
    proj = _project(gaussians, camera, near, dilation_px2, alpha_min, near_extent_sigma, uv_offset)
    bg = _defaults(proj, background)
    H, Wd, T, C = camera.height, camera.width, tile_size, capacity
    nty, ntx = -(-H // T), -(-Wd // T)
    N = proj.uv.shape[0]
    dt = proj.uv.dtype

    ty, tx = jnp.meshgrid(jnp.arange(nty), jnp.arange(ntx), indexing="ij")
    x0 = (tx.reshape(-1) * T).astype(dt)
    y0 = (ty.reshape(-1) * T).astype(dt)
    u, v = proj.uv[:, 0], proj.uv[:, 1]
    eu, ev = proj.extent[:, 0], proj.extent[:, 1]
    uu, vv = jax.lax.stop_gradient(u), jax.lax.stop_gradient(v)
    eu, ev = jax.lax.stop_gradient(eu), jax.lax.stop_gradient(ev)
    overlap = (proj.visible[None, :]
               & (uu[None, :] + eu[None, :] >= x0[:, None]) & (uu[None, :] - eu[None, :] <= x0[:, None] + T - 1)
               & (vv[None, :] + ev[None, :] >= y0[:, None]) & (vv[None, :] - ev[None, :] <= y0[:, None] + T - 1))
    counts = jnp.sum(overlap, -1)
    order = jnp.argsort(jnp.where(proj.visible, jax.lax.stop_gradient(proj.depth), jnp.inf))
    ov_sorted = overlap[:, order]
    pos = jnp.cumsum(ov_sorted, -1) - 1
    slot = jnp.where(ov_sorted & (pos < C), pos, C)
    ids = jnp.full((overlap.shape[0], C + 1), N, dtype=jnp.int32)
    ids = jax.vmap(lambda row, s: row.at[s].set(order.astype(jnp.int32), mode="drop"))(ids, slot)[:, :C]

    pad = lambda a, val: jnp.concatenate([a, jnp.full((1,) + a.shape[1:], val, a.dtype)], 0)  # noqa: E731
    uv_p = pad(proj.uv, 0.0)
    conic_p = pad(proj.conic, 0.0)
    op_p = pad(proj.opacity, 0.0)
    rgb_p = pad(proj.rgb, 0.0)
    z_p = pad(proj.depth, 0.0)

    ly, lx = jnp.meshgrid(jnp.arange(T, dtype=dt), jnp.arange(T, dtype=dt), indexing="ij")
    local = jnp.stack([lx.reshape(-1), ly.reshape(-1)], -1)

    def tile(ids_t, ox, oy):
        px = local + jnp.stack([ox, oy])
        al = _alphas(px, uv_p[ids_t], conic_p[ids_t], op_p[ids_t], alpha_min, alpha_max)
        return _composite(al, rgb_p[ids_t], z_p[ids_t], t_min, bg)

    col, A, dep, med, dist = jax.vmap(tile)(ids, x0, y0)

    def img(a):
        a = a.reshape((nty, ntx, T, T) + a.shape[2:])
        a = jnp.swapaxes(a, 1, 2).reshape((nty * T, ntx * T) + a.shape[4:])
        return a[:H, :Wd]

    over = jnp.maximum(counts - C, 0)
    return SplatRender(color=img(col), alpha=img(A), depth=img(dep), median_depth=img(med),
                       distortion=img(dist), overflow=jnp.sum(over).astype(jnp.int32),
                       overflow_tiles=jnp.sum(over > 0).astype(jnp.int32),
                       max_tile_count=jnp.max(counts).astype(jnp.int32), projected=proj)


def render_splats_dense(gaussians: Gaussians, camera: Camera, *, background=None, near: float = 0.01,
                        dilation_px2: float = 0.3, alpha_min: float = 1.0 / 255.0, alpha_max: float = 0.99,
                        t_min: float = 1e-4, near_extent_sigma: float = 3.0, uv_offset=None) -> SplatRender:
    """Slow reference renderer: every splat on every pixel, one global depth sort.

    Same projection, opacity rule and compositing as :func:`render_splats`, without tiles
    (memory ``O(H W N)``: small scenes only). ``overflow`` is always 0.

    Example:
        >>> g = fsjax.Gaussians(jnp.asarray([[0.0, 0.0, 4.0]]), jnp.log(jnp.full((1, 3), 0.1)),
        ...                     jnp.asarray([[1.0, 0.0, 0.0, 0.0]]), jnp.asarray([20.0]), jnp.ones((1, 3)))
        >>> cam = fsjax.Camera.from_intrinsics(100.0, 100.0, 15.5, 11.5, width=32, height=24)
        >>> a = fsjax.render.render_splats(g, cam).alpha
        >>> b = fsjax.render.render_splats_dense(g, cam).alpha
        >>> float(jnp.max(jnp.abs(a - b))) < 1e-12
        True
    """
    _check(gaussians, camera, "render_splats_dense", alpha_min=alpha_min, alpha_max=alpha_max, near=near,
           dilation_px2=dilation_px2)
    return _render_dense(gaussians, camera, background, near, dilation_px2, alpha_min, alpha_max, t_min,
                         near_extent_sigma, uv_offset)


@eqx.filter_jit
def _render_dense(gaussians, camera, background, near, dilation_px2, alpha_min, alpha_max, t_min,
                  near_extent_sigma, uv_offset):
    proj = _project(gaussians, camera, near, dilation_px2, alpha_min, near_extent_sigma, uv_offset)
    bg = _defaults(proj, background)
    H, Wd = camera.height, camera.width
    order = jnp.argsort(jnp.where(proj.visible, jax.lax.stop_gradient(proj.depth), jnp.inf))
    dt = proj.uv.dtype
    r, c = jnp.meshgrid(jnp.arange(H, dtype=dt), jnp.arange(Wd, dtype=dt), indexing="ij")
    px = jnp.stack([c.reshape(-1), r.reshape(-1)], -1)
    al = _alphas(px, proj.uv[order], proj.conic[order], proj.opacity[order], alpha_min, alpha_max)
    col, A, dep, med, dist = _composite(al, proj.rgb[order], proj.depth[order], t_min, bg)
    zero = jnp.zeros((), jnp.int32)
    return SplatRender(color=col.reshape(H, Wd, 3), alpha=A.reshape(H, Wd), depth=dep.reshape(H, Wd),
                       median_depth=med.reshape(H, Wd), distortion=dist.reshape(H, Wd), overflow=zero,
                       overflow_tiles=zero, max_tile_count=jnp.asarray(proj.uv.shape[0], jnp.int32),
                       projected=proj)

