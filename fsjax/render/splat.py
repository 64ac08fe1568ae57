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
* Tiles of ``tile_size`` x ``tile_size`` pixels, binned by sorting (3DGS; gsplat): every
  visible splat emits one (tile, depth) pair per tile its support box touches, in global depth
  order, into a pair buffer of static size ``max_pairs``; one stable sort by tile gives each
  tile a contiguous depth-ordered range. The buffer is sized from the measured demand for an
  eager call (exact); under ``jit`` it is given, and pairs beyond it (the farthest splats')
  are dropped and counted in ``SplatRender.overflow`` (and ``overflow_tiles``), with the demand
  in ``SplatRender.pairs``: never a silent blank patch.
* Compositing front to back by centre depth: ``w_i = alpha_i T_i``, ``T_i = prod_{j<i}
  (1 - alpha_j)``, with early termination: splat ``i`` and all behind it are skipped once
  ``T_i (1 - alpha_i) < t_min`` (1e-4). Each tile's range is composited in chunks of ``chunk``
  splats by a ``lax.scan`` carrying the per-pixel state; a chunk whose tile has terminated at
  every pixel is skipped (``lax.cond``), so termination saves work as well as being exact.
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

from .._checks import check_positive, check_range, check_static_int
from .._linalg import quat_to_rotmat as _quat_to_rotmat
from ..types import Camera, Gaussians, is_concrete
from .camera import world_to_camera

__all__ = [
    "SplatRender",
    "ProjectedSplats",
    "project_gaussians",
    "render_splats",
    "render_splats_dense",
    "count_splat_pairs",
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
    ``overflow`` splat-tile pairs dropped because the pair buffer was full (0 for the dense
    renderer); ``overflow_tiles`` tiles that lost pairs; ``max_tile_count`` the largest per-tile
    demand; ``projected`` the screen-space splats; ``pairs`` the (splat, tile) pair demand of
    the view (grow ``max_pairs`` to at least this for an exact render).
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
    pairs: Int[Array, ""] = None


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
    for name, v in (("alpha_min", alpha_min), ("alpha_max", alpha_max)):
        check_range(fn, name, v, 0.0, 1.0, lo_open=True, hi_open=True)
    if is_concrete(alpha_min) and is_concrete(alpha_max) and not float(alpha_min) < float(alpha_max):
        raise ValueError(f"{fn}(alpha_min=...): must be below alpha_max={alpha_max}, got {alpha_min}")
    check_positive(fn, "near", near)
    check_positive(fn, "dilation_px2", dilation_px2)  # > 0 keeps the 2-D covariances invertible


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
    lg = jnp.log1p(-alpha)
    T_excl = jnp.exp(jnp.cumsum(lg, axis=-1) - lg)
    T_incl = T_excl * (1.0 - alpha)
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


_TRACED_PAIRS_PER_TILE = 256


def _bucket(n: int) -> int:
    """Buffer size for a measured demand ``n`` (splat-tile pairs here, triangle-pixel candidates in
    :mod:`fsjax.render.raster`): ``1.125 n`` rounded up to a quarter-octave step ``(4 + i) 2^k / 4``
    (at least 1,024), so the slack is at most ~40 % and a slowly growing demand recompiles
    O(log n) times (four per doubling), not every step."""
    need = max(1.125 * float(n), 1024.0)
    k = int(np.floor(np.log2(need))) - 2
    return int(-(-need // (1 << k)) * (1 << k))


def _slot_owner(start, k, B):
    """Segment holding each slot ``p < B`` of a buffer filled segment after segment (segment ``i``
    occupies ``[start_i, start_i + k_i)``): a scatter of the non-empty segments' indices at their
    starts and a running maximum. A per-slot binary search (``searchsorted``) measured ~40x slower
    on XLA:CPU for B = 2^19; ``lax.cummax`` runs ~4x slower than ``lax.associative_scan`` there
    (~7 ms at 2^19) but compiles in a quarter of the time (0.2 s vs 0.9 s of CPU per scan), and
    compile time is the larger cost at these sizes."""
    at = jnp.where((k > 0) & (start < B), start, B)
    owner = jnp.zeros((B,), jnp.int32).at[at].max(jnp.arange(k.shape[0], dtype=jnp.int32), mode="drop")
    return jax.lax.cummax(owner)


def _tile_boxes(proj, H, W, T):
    """Inclusive tile ranges ``tx0..tx1``, ``ty0..ty1`` of each splat's exact support box, the
    tiles per splat ``k`` and the grid size. A tile ``[x0, x0 + T - 1]`` is touched when
    ``u - e <= x0 + T - 1`` and ``u + e >= x0`` (same for rows)."""
    ntx, nty = -(-W // T), -(-H // T)
    u, v = (jax.lax.stop_gradient(proj.uv[:, i]) for i in (0, 1))
    eu, ev = (jax.lax.stop_gradient(proj.extent[:, i]) for i in (0, 1))
    big = 1e9
    fl = lambda a: jnp.clip(a, -big, big)  # noqa: E731
    tx0 = jnp.maximum(jnp.ceil((fl(u - eu) - (T - 1)) / T), 0.0).astype(jnp.int32)
    tx1 = jnp.minimum(jnp.floor(fl(u + eu) / T), ntx - 1).astype(jnp.int32)
    ty0 = jnp.maximum(jnp.ceil((fl(v - ev) - (T - 1)) / T), 0.0).astype(jnp.int32)
    ty1 = jnp.minimum(jnp.floor(fl(v + ev) / T), nty - 1).astype(jnp.int32)
    on = proj.visible & (tx1 >= tx0) & (ty1 >= ty0)
    wx = jnp.where(on, tx1 - tx0 + 1, 0)
    wy = jnp.where(on, ty1 - ty0 + 1, 0)
    return tx0, tx1, ty0, ty1, on, wx, wy, ntx, nty


@eqx.filter_jit
def _count_pairs(gaussians, camera, near, dilation_px2, alpha_min, near_extent_sigma, uv_offset, tile_size):
    proj = _project(gaussians, camera, near, dilation_px2, alpha_min, near_extent_sigma, uv_offset)
    *_, wx, wy, _, _ = _tile_boxes(proj, camera.height, camera.width, tile_size)
    return jnp.sum(wx * wy)


def count_splat_pairs(gaussians: Gaussians, camera: Camera, *, tile_size: int = 16, near: float = 0.01,
                      dilation_px2: float = 0.3, alpha_min: float = 1.0 / 255.0, near_extent_sigma: float = 3.0,
                      uv_offset=None) -> int:
    """Number of (splat, tile) pairs :func:`render_splats` needs for this view (eager, an int).

    Use it to size ``max_pairs`` for a jitted render; :func:`render_splats` called eagerly does
    this itself.

    Example:
        >>> g = fsjax.Gaussians(jnp.asarray([[0.0, 0.0, 4.0]]), jnp.log(jnp.full((1, 3), 0.1)),
        ...                     jnp.asarray([[1.0, 0.0, 0.0, 0.0]]), jnp.asarray([20.0]), jnp.ones((1, 3)))
        >>> cam = fsjax.Camera.from_intrinsics(100.0, 100.0, 16.0, 12.0, width=32, height=24)
        >>> fsjax.render.count_splat_pairs(g, cam)  # a centred splat touching all 2 x 2 tiles
        4
    """
    _check(gaussians, camera, "count_splat_pairs", alpha_min=alpha_min, alpha_max=0.99, near=near,
           dilation_px2=dilation_px2)
    return int(_count_pairs(gaussians, camera, near, dilation_px2, alpha_min, near_extent_sigma, uv_offset,
                            int(tile_size)))


def render_splats(gaussians: Gaussians, camera: Camera, *, tile_size: int = 16, capacity: int | None = None,
                  max_pairs: int | None = None, chunk: int = 64, background=None, near: float = 0.01,
                  dilation_px2: float = 0.3, alpha_min: float = 1.0 / 255.0, alpha_max: float = 0.99,
                  t_min: float = 1e-4, near_extent_sigma: float = 3.0, uv_offset=None,
                  distortion: bool = True) -> SplatRender:
    """Render splats through a pinhole camera by sort-based tile binning (3DGS / gsplat design).

    Each visible splat emits one (tile, depth) pair per ``tile_size`` x ``tile_size`` tile its
    exact support box touches; the pairs are emitted in depth order and sorted by tile (one
    global sort, stable), so each tile owns a contiguous, depth-ordered range. A sequential
    ``lax.scan`` composites every tile's range in chunks of ``chunk`` splats, front to back,
    carrying the per-pixel state (transmittance, colour, weight sums, distortion, median) from
    chunk to chunk; a chunk is skipped (``lax.cond``) once every pixel of its tile has
    terminated (``T < t_min``) and for unused buffer slots. Cost therefore follows the pairs
    that exist and the early termination, not a per-tile capacity: about
    ``pairs x tile_size^2`` opacity evaluations forward and twice that backward (the chunk
    body is rematerialised, so memory is ``O(pairs + tiles x tile_size^2)``).

    The pair buffer has a static size ``B``: ``max_pairs`` when given; otherwise, when the
    inputs are concrete (an eager call), the measured demand (:func:`count_splat_pairs`)
    rounded up to a power of two -- an eager render is then exact whatever ``capacity`` says;
    under ``jit``/``grad`` tracing, ``capacity x tiles`` (``capacity`` default 256). Pairs beyond ``B`` (the farthest splats')
    are dropped and **counted** in ``overflow``; ``pairs`` is the demand, so a caller can grow
    the buffer and re-render (as :func:`fsjax.fit.train_splats` does).

    Args:
        gaussians: one set of splats (``N`` of them).
        camera: one pinhole :class:`fsjax.Camera` (zero distortion), image ``height x width``.
        tile_size: tile edge in pixels (static int).
        capacity: pairs per tile used to size the buffer under tracing only (``B = capacity x
            tiles``) when ``max_pairs`` is not given (static int; kept from the fixed-capacity
            renderer this one replaced; default 256).
        max_pairs: static size of the global (splat, tile) pair buffer (see above).
        chunk: splats composited per step of the scan (static int).
        background: RGB ``(3,)`` behind the splats (default black).
        near: near-plane depth (camera units); culling by extent (module docstring).
        dilation_px2: screen-space dilation added to the 2-D covariance diagonal (px^2).
        alpha_min, alpha_max: per-pixel opacity floor (defines the support) and clamp.
        t_min: early-termination transmittance.
        near_extent_sigma: the extent (in sigmas) used by near-plane culling.
        uv_offset: ``(N, 2)`` offset of the projected means (for screen-space gradients).
        distortion: compute the 2DGS depth distortion (static bool, default True). False returns
            ``distortion = 0`` and saves two of the three prefix-sum products per chunk (about a
            third of the compositing time, forward and backward); training without the distortion
            loss passes False.

    Returns:
        :class:`SplatRender`. Agrees with :func:`render_splats_dense` to ~1e-15 (float64,
        images and gradients) when ``overflow == 0`` (tested).

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
    tile_size = check_static_int("render_splats", "tile_size", tile_size, lo=1)
    chunk = check_static_int("render_splats", "chunk", chunk, lo=1)
    if capacity is not None:
        capacity = check_static_int("render_splats", "capacity", capacity, lo=1)
    if max_pairs is not None:
        max_pairs = check_static_int("render_splats", "max_pairs", max_pairs, lo=1)
    T = int(tile_size)
    tiles = (-(-camera.height // T)) * (-(-camera.width // T))
    if max_pairs is None:
        leaves = jax.tree_util.tree_leaves((gaussians, camera, uv_offset))
        if all(is_concrete(x) for x in leaves if isinstance(x, (jax.Array, np.ndarray))):
            max_pairs = _bucket(int(_count_pairs(gaussians, camera, near, dilation_px2, alpha_min,
                                                 near_extent_sigma, uv_offset, T)))
        else:
            max_pairs = int(capacity or _TRACED_PAIRS_PER_TILE) * tiles
    return _render_tiled(gaussians, camera, background, near, dilation_px2, alpha_min, alpha_max, t_min,
                         near_extent_sigma, uv_offset, T, int(max_pairs), int(chunk), bool(distortion))


@eqx.filter_jit
def _render_tiled(gaussians, camera, background, near, dilation_px2, alpha_min, alpha_max, t_min,
                  near_extent_sigma, uv_offset, tile_size, max_pairs, chunk, distortion=True):
    proj = _project(gaussians, camera, near, dilation_px2, alpha_min, near_extent_sigma, uv_offset)
    bg = _defaults(proj, background)
    H, Wd, T, B, Cc = camera.height, camera.width, tile_size, max_pairs, chunk
    N = proj.uv.shape[0]
    dt = proj.uv.dtype
    tx0, tx1, ty0, ty1, on, wx, wy, ntx, nty = _tile_boxes(proj, H, Wd, T)
    NT = ntx * nty
    k = wx * wy

    # exact per-tile demand: 2-D difference array of the tile boxes
    one = on.astype(jnp.int32)
    diff = jnp.zeros((nty + 1, ntx + 1), jnp.int32)
    diff = diff.at[ty0, tx0].add(one).at[ty0, tx1 + 1].add(-one)
    diff = diff.at[ty1 + 1, tx0].add(-one).at[ty1 + 1, tx1 + 1].add(one)
    demand = jnp.cumsum(jnp.cumsum(diff, axis=0), axis=1)[:nty, :ntx].reshape(NT)

    # pairs emitted in depth order (the buffer keeps the nearest B), then one stable sort by tile
    order = jnp.argsort(jnp.where(on, jax.lax.stop_gradient(proj.depth), jnp.inf)).astype(jnp.int32)
    ko = k[order]
    end = jnp.cumsum(ko)
    total = end[-1]
    p = jnp.arange(B, dtype=jnp.int32)
    s = _slot_owner(end - ko, ko, B)
    sid = order[s]
    j = p - (end[s] - ko[s])
    wj = jnp.maximum(wx[sid], 1)
    key = jnp.where(p < total, (ty0[sid] + j // wj) * ntx + tx0[sid] + j % wj, NT)
    perm = jnp.argsort(key, stable=True)
    skey = key[perm]
    ssid = sid[perm]
    bounds = jnp.searchsorted(skey, jnp.arange(NT + 1, dtype=skey.dtype), side="left").astype(jnp.int32)
    start, cnt = bounds[:-1], bounds[1:] - bounds[:-1]

    # fixed-size chunks, each inside one tile's range
    nch = (cnt + Cc - 1) // Cc
    cend = jnp.cumsum(nch)
    NC = B // Cc + NT
    q = jnp.arange(NC, dtype=jnp.int32)
    tq = jnp.searchsorted(cend, q, side="right").astype(jnp.int32)
    okc = tq < NT
    tqc = jnp.minimum(tq, NT - 1)
    iq = q - (cend[tqc] - nch[tqc])
    pos = start[tqc, None] + iq[:, None] * Cc + jnp.arange(Cc, dtype=jnp.int32)[None, :]
    okp = okc[:, None] & (pos < (start[tqc] + cnt[tqc])[:, None])
    ids = jnp.where(okp, ssid[jnp.clip(pos, 0, B - 1)], N)
    first = okc & (iq == 0)

    pad = lambda a: jnp.concatenate([a, jnp.zeros((1,) + a.shape[1:], a.dtype)], 0)  # noqa: E731
    xs = (tq, first, okc, pad(proj.uv)[ids], pad(proj.conic)[ids], pad(proj.opacity)[ids], pad(proj.rgb)[ids],
          pad(proj.depth)[ids])
    ly, lx = jnp.meshgrid(jnp.arange(T, dtype=dt), jnp.arange(T, dtype=dt), indexing="ij")
    local = jnp.stack([lx.reshape(-1), ly.reshape(-1)], -1)
    P = T * T
    zP = jnp.zeros(P, dt)
    init = (zP, zP, zP, zP, jnp.zeros((P, 3), dt), zP, jnp.zeros(P, bool))
    t_min = jnp.asarray(t_min, dt)
    upper = jnp.triu(jnp.ones((Cc, Cc), dt), 1)

    def chunk_fn(carry, tqi, uv, conic, op, rgb, z):
        L0, W0, S0, D0, C0, med, found = carry
        ox = (tqi % ntx).astype(dt) * T
        oy = (tqi // ntx).astype(dt) * T
        al = _alphas(local + jnp.stack([ox, oy]), uv, conic, op, alpha_min, alpha_max)
        lg = jnp.log1p(-al)
        # exclusive prefix sums as one product with a strictly upper-triangular matrix of ones:
        # faster than cumsum on XLA:CPU for chunk-sized rows, same sums up to rounding order
        le = L0[:, None] + lg @ upper
        T_excl = jnp.exp(le)
        T_incl = T_excl * (1.0 - al)
        keep = T_incl >= t_min
        w = jnp.where(keep, al * T_excl, 0.0)
        wz = w * z[None, :]
        if distortion:
            pre = jnp.concatenate([w, wz], 0) @ upper
            Wp = W0[:, None] + pre[:P]
            Sp = S0[:, None] + pre[P:]
            D = D0 + 2.0 * jnp.sum(wz * Wp - w * Sp, -1)
        else:
            D = D0
        crossed = keep & (T_incl < 0.5)
        here = jnp.any(crossed, -1)
        zc = z[jnp.argmax(crossed, -1)]
        med = jnp.where(~found & here, zc, med)
        return (le[:, -1] + lg[:, -1], W0 + jnp.sum(w, -1), S0 + jnp.sum(wz, -1), D, C0 + w @ rgb, med,
                found | here)

    @jax.checkpoint
    def body(carry, x):
        tqi, fst, okq, uv, conic, op, rgb, z = x
        carry = jax.tree_util.tree_map(lambda c, i: jnp.where(fst, i, c), carry, init)
        skip = ~okq | jnp.all(jnp.exp(carry[0]) < t_min)
        carry = jax.lax.cond(skip, lambda c, *a: c, chunk_fn, carry, tqi, uv, conic, op, rgb, z)
        return carry, carry

    _, ys = jax.lax.scan(body, init, xs)
    lastc = jnp.clip(cend - 1, 0, NC - 1)
    has = (nch > 0)
    pick = lambda y, i: jnp.where(has.reshape((NT,) + (1,) * (y.ndim - 1)), y[lastc], i)  # noqa: E731
    L, Wsum, Ssum, D, Col, med, _ = jax.tree_util.tree_map(pick, ys, jax.tree_util.tree_map(
        lambda i: jnp.broadcast_to(i, (NT,) + i.shape), init))

    def img(a):
        a = a.reshape((nty, ntx, T, T) + a.shape[2:])
        a = jnp.swapaxes(a, 1, 2).reshape((nty * T, ntx * T) + a.shape[4:])
        return a[:H, :Wd]

    A = img(Wsum)
    color = img(Col) + (1.0 - A)[..., None] * bg
    hasA = A > 0
    depth = jnp.where(hasA, img(Ssum) / jnp.where(hasA, A, 1.0), 0.0)
    lost = demand - cnt
    return SplatRender(color=color, alpha=A, depth=depth, median_depth=img(med), distortion=img(D),
                       overflow=jnp.maximum(total - B, 0).astype(jnp.int32),
                       overflow_tiles=jnp.sum(lost > 0).astype(jnp.int32),
                       max_tile_count=jnp.max(demand).astype(jnp.int32), projected=proj,
                       pairs=total.astype(jnp.int32))


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
                       projected=proj, pairs=zero)

