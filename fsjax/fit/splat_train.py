"""Training Gaussian splats from posed images: L1 + SSIM through optimistix, densify and prune.

Pipeline (Kerbl et al. 2023, adapted to a fixed maximum count so XLA compiles once):

* Data: :func:`mesh_views` renders a real mesh (Spot, bunny) with fsjax's own mesh rasteriser
  (:func:`fsjax.render.rasterize` + :func:`fsjax.render.interpolate`) from ``n_views``
  cameras on a spiral around it, with vertex colours from the normals (and a position-based
  band pattern for texture); every ``holdout_every``-th view is held out.
* Model: :class:`fsjax.Gaussians` with a fixed capacity ``max_splats`` and a ``valid``
  mask, plain colours (``K = 1``). Initialised from ``n_init`` points sampled on the mesh
  surface with noise (standing in for the sparse SfM cloud a real capture gives).
* Loss: ``(1 - lam) L1 + lam (1 - SSIM)`` with ``lam = 0.2`` on one training view per step
  (SSIM: Gaussian window sigma 1.5 px, 11 taps, valid region, per channel; equals
  ``skimage.metrics.structural_similarity(gaussian_weights=True, use_sample_covariance=False)``
  to 1e-12, tested), plus an optional depth-distortion term ``dist_weight * mean(distortion)``
  (raw, or normalised per ray by ``A^2``).
* Optimiser: ``optimistix.OptaxMinimiser`` wrapping ``optax.adam`` with per-group learning
  rates (``optax.multi_transform``), advanced with optimistix's ``init``/``step`` interface so
  densification can change the model between steps. The screen-space positional gradient
  (for densification) is read from an extra ``uv_offset`` leaf whose optax transform is the
  identity: after a step, from zero, it holds exactly ``dL/d(uv)``.
* Densification every ``densify_every`` steps (until ``densify_until``): splats whose mean
  screen-space gradient exceeds ``grad_threshold`` (px units) are split (large: two samples
  from the Gaussian, scales / 1.6) or cloned (small), highest gradient first, into free slots
  only -- never beyond ``max_splats``. Pruning: opacity below ``prune_opacity``. Adam moments
  of changed slots are reset.
* Deterministic under ``key`` (initialisation, view order, split samples); a tqdm progress
  bar when ``progress=True``.

Metrics: PSNR and SSIM over the whole image, and coverage holes (fraction of pixels inside
the true object mask whose accumulated alpha is below ``alpha_threshold``), per image third
(top/middle/bottom): a texture metric and a coverage metric, reported separately.
"""

from __future__ import annotations

import time
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx

from ..ops import psnr as _psnr_op
from ..render.camera import intrinsics_from_fov, look_at
from ..render.splat import _bucket, count_splat_pairs, render_splats, rgb_to_sh0
from ..types import Camera, Gaussians, Image, Mesh
from ..types.results import FitResult, deprecated_name, reason_code

__all__ = ["MultiViewData", "mesh_views", "ssim_color", "coverage_holes", "init_from_mesh",
           "SplatTrainResult", "train_splats", "evaluate_splats"]


class MultiViewData(eqx.Module):
    """Posed images: ``images (V, H, W, 3)``, object ``masks (V, H, W)``, ``depths (V, H, W)``
    (0 = background), batched ``cameras`` (batch ``(V,)``), ``train``/``test`` index arrays,
    ``points`` (surface samples for initialisation) and the scene ``extent`` (radius)."""

    images: Any
    masks: Any
    depths: Any
    cameras: Camera
    train: np.ndarray = eqx.field(static=False)
    test: np.ndarray = eqx.field(static=False)
    points: Any
    extent: float = eqx.field(static=True, default=1.0)


def _face_normals(v, f):
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    vn = np.zeros_like(v)
    for i in range(3):
        np.add.at(vn, f[:, i], n)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)


def mesh_views(mesh: Mesh, *, n_views: int = 48, width: int = 128, height: int = 128, fov_deg: float = 40.0,
               holdout_every: int = 6, distance: float = 2.6, capacity: int = 2048, texture: bool = True,
               n_points: int = 20000, seed: int = 0) -> MultiViewData:
    """Render a multi-view dataset of ``mesh`` with fsjax's mesh rasteriser (see module docstring).

    The mesh is centred and scaled to unit bounding radius; cameras sit at ``distance`` on a
    spiral (elevation -35..65 degrees) looking at the centre, world up ``+y``.
    """
    from ..render.raster import interpolate, rasterize

    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces)
    v = v - 0.5 * (v.min(0) + v.max(0))
    v = v / np.max(np.linalg.norm(v, axis=1))
    vn = _face_normals(v, f)
    col = 0.55 + 0.35 * vn
    if texture:
        col = col * (0.75 + 0.25 * np.sign(np.sin(9.0 * v[:, 1:2] + 3.0 * v[:, 0:1])))
    col = np.clip(col, 0.0, 1.0)
    m = Mesh(jnp.asarray(v), jnp.asarray(f, jnp.int32))
    K = intrinsics_from_fov(width, height, fov_x_deg=fov_deg)
    i = np.arange(n_views)
    elev = np.radians(-35.0 + 100.0 * (i + 0.5) / n_views)
    azim = i * np.pi * (3.0 - np.sqrt(5.0))
    eyes = distance * np.stack([np.cos(elev) * np.sin(azim), np.sin(elev), np.cos(elev) * np.cos(azim)], 1)
    Rs, ts, imgs, masks, depths = [], [], [], [], []
    attr = jnp.asarray(col)
    for e in eyes:
        R, t = look_at(e, [0.0, 0.0, 0.0], up=[0.0, 1.0, 0.0])
        cam = Camera(K, width=width, height=height, R=R, t=t)
        r = rasterize(m, cam, capacity=capacity)
        if int(r.overflow):
            raise RuntimeError(f"mesh_views: mesh rasteriser overflow {int(r.overflow)}; raise capacity")
        imgs.append(np.asarray(interpolate(r, m, attr)))
        masks.append(np.asarray(r.alpha) > 0.5)
        depths.append(np.where(masks[-1], np.asarray(r.depth), 0.0))
        Rs.append(np.asarray(R))
        ts.append(np.asarray(t))
    cams = Camera(jnp.broadcast_to(K, (n_views, 3, 3)), width=width, height=height, R=jnp.asarray(np.stack(Rs)),
                  t=jnp.asarray(np.stack(ts)))
    test = i[i % holdout_every == holdout_every // 2]
    train = np.setdiff1d(i, test)
    # surface samples (area-weighted) for initialisation
    rng = np.random.default_rng(seed)
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    fi = rng.choice(len(f), size=n_points, p=area / area.sum())
    b = rng.dirichlet(np.ones(3), size=n_points)
    pts = np.einsum("nk,nkd->nd", b, v[f[fi]])
    pcol = np.einsum("nk,nkd->nd", b, col[f[fi]])
    return MultiViewData(images=jnp.asarray(np.stack(imgs)), masks=jnp.asarray(np.stack(masks)),
                         depths=jnp.asarray(np.stack(depths)), cameras=cams, train=train, test=test,
                         points=(pts, pcol), extent=1.0)


# ---------------------------------------------------------------------------
# metrics
# ---------------------------------------------------------------------------


def _gauss_taps(sigma=1.5, radius=5):
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    w = np.exp(-0.5 * (x / sigma) ** 2)
    return w / w.sum()


def _valid_blur_matrix(n_in: int, taps) -> np.ndarray:
    """``(n_in - len(taps) + 1, n_in)`` banded matrix of valid-mode correlation with ``taps``."""
    n = len(taps)
    M = np.zeros((n_in - n + 1, n_in))
    for k in range(n):
        M[np.arange(n_in - n + 1), np.arange(n_in - n + 1) + k] = taps[k]
    return M


def _valid_blur(x, taps):
    """Separable valid-mode filtering of ``(..., H, W)``: two products with banded matrices.

    On XLA:CPU this is ~100x faster than shift-and-add of 2 x 11 slices (whose gradient is 22
    pads), and compiles in a fraction of the time; the sums are the same up to rounding order."""
    H, W = x.shape[-2], x.shape[-1]
    Mh = jnp.asarray(_valid_blur_matrix(H, taps), x.dtype)
    Mw = jnp.asarray(_valid_blur_matrix(W, taps), x.dtype)
    return jnp.einsum("ih,...hw,jw->...ij", Mh, x, Mw)


def ssim_color(a, b, *, data_range: float = 1.0):
    """Mean SSIM of two ``(H, W, 3)`` images (Wang et al. 2004), channels averaged.

    Gaussian window sigma 1.5 px truncated at 5 px (11 taps), constants ``K1 = 0.01``,
    ``K2 = 0.03``, population covariances, mean over the valid region: this is
    ``skimage.metrics.structural_similarity(..., gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, channel_axis=-1)`` (tested to 1e-12). Differentiable.

    Example:
        >>> from fsjax.fit import ssim_color
        >>> x = jnp.asarray(np.random.default_rng(0).uniform(size=(16, 16, 3)))
        >>> round(float(ssim_color(x, x)), 12)
        1.0
    """
    a = jnp.moveaxis(jnp.asarray(a), -1, 0)
    b = jnp.moveaxis(jnp.asarray(b), -1, 0)
    t = _gauss_taps()
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    ma, mb, eaa, ebb, eab = _valid_blur(jnp.stack([a, b, a * a, b * b, a * b]), t)
    saa = eaa - ma * ma
    sbb = ebb - mb * mb
    sab = eab - ma * mb
    s = ((2 * ma * mb + c1) * (2 * sab + c2)) / ((ma * ma + mb * mb + c1) * (saa + sbb + c2))
    return jnp.mean(s)


def _psnr(a, b, *, data_range: float = 1.0):
    """:func:`fsjax.ops.psnr` of two same-shape arrays of any rank (colour images included).

    The op's mean squared error runs over every pixel; an ``(H, W, 3)`` image is passed as the
    ``(H, 3 W)`` grey image of the same values, which has the same mean.
    """
    a, b = jnp.asarray(a), jnp.asarray(b)
    flat = (a.shape[0], -1) if a.ndim >= 2 else (1, -1)
    return _psnr_op(Image(a.reshape(flat)), Image(b.reshape(flat)), data_range=data_range).value


def __getattr__(name):
    if name == "psnr":
        deprecated_name("fsjax.fit.splat_train.psnr", "fsjax.ops.psnr")
        return _psnr
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def coverage_holes(alpha, mask, *, alpha_threshold: float = 0.5) -> dict:
    """Fraction of true-object pixels (``mask``) with accumulated ``alpha`` below the threshold.

    Returns ``{"all", "top", "middle", "bottom"}`` (image thirds by row); NaN for a region
    that holds no object pixel.
    """
    alpha, mask = np.asarray(alpha), np.asarray(mask, bool)
    H = alpha.shape[-2]
    out = {}
    for name, sl in (("all", slice(0, H)), ("top", slice(0, H // 3)), ("middle", slice(H // 3, 2 * H // 3)),
                     ("bottom", slice(2 * H // 3, H))):
        m = mask[..., sl, :]
        hole = (alpha[..., sl, :] < alpha_threshold) & m
        out[name] = float(hole.sum() / m.sum()) if m.sum() else float("nan")
    return out


# ---------------------------------------------------------------------------
# model
# ---------------------------------------------------------------------------


def init_from_mesh(key, data: MultiViewData, n_init: int, max_splats: int, *, dtype=jnp.float32) -> Gaussians:
    """``max_splats`` slots, the first ``n_init`` valid: surface samples + noise, isotropic
    scales from the mean spacing, opacity 0.1, colour of the sample."""
    pts, pcol = data.points
    if n_init > max_splats:
        raise ValueError(f"init_from_mesh: argument 'n_init' must be <= max_splats ({max_splats}), got {n_init}")
    k1, k2 = jax.random.split(key)
    idx = np.asarray(jax.random.choice(k1, len(pts), (n_init,), replace=n_init > len(pts)))
    spacing = data.extent * np.sqrt(4 * np.pi / n_init) * 0.5
    means = np.zeros((max_splats, 3))
    means[:n_init] = pts[idx] + np.asarray(jax.random.normal(k2, (n_init, 3))) * 0.25 * spacing
    cols = np.zeros((max_splats, 1, 3))
    cols[:n_init, 0] = np.asarray(rgb_to_sh0(pcol[idx]))
    valid = np.arange(max_splats) < n_init
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (max_splats, 1))
    return Gaussians(jnp.asarray(means, dtype), jnp.full((max_splats, 3), np.log(spacing), dtype),
                     jnp.asarray(quats, dtype), jnp.full((max_splats,), np.log(0.1 / 0.9), dtype),
                     jnp.asarray(cols, dtype), valid=jnp.asarray(valid))


class SplatTrainResult(FitResult):
    """Trained ``gaussians``; per-step ``loss``; ``n_splats`` after each densification;
    ``overflow`` per step (splat-tile pairs dropped); ``step_seconds`` median wall time of a
    step (steps that compiled excluded); ``compile_seconds`` (first step plus every step that
    grew the pair buffer), and ``compile_cpu_seconds`` the process CPU time of those steps (less
    sensitive to other load on the machine than the wall time); ``step_cpu_seconds`` the median
    process CPU time (all threads) of a step that did not compile, roughly an upper bound of the
    step's wall time on an idle machine; ``converged`` (the optimiser's Cauchy test never fires in a
    fixed-length run, so this reports whether the final loss is finite); ``pairs`` the
    rasteriser's (splat, tile) pair demand per step; ``max_pairs`` the final buffer size.

    Base fields: ``reason`` is ``ok`` or ``invalid_input`` (a non-finite final loss),
    ``iterations`` the optimiser steps run (``len(loss)``). No residual with a unit: the
    objective is the unitless photometric loss (L1 and D-SSIM mix), reported per step in
    ``loss``; image quality is measured by :func:`evaluate_splats` (PSNR, SSIM)."""

    gaussians: Gaussians
    loss: np.ndarray
    n_splats: np.ndarray
    overflow: np.ndarray
    step_seconds: float
    compile_seconds: float
    converged: bool
    pairs: np.ndarray = None
    max_pairs: int = 0
    compile_cpu_seconds: float = float("nan")
    step_cpu_seconds: float = float("nan")

    @property
    def reason(self):
        return np.int32(reason_code("ok") if self.converged else reason_code("invalid_input"))

    @property
    def iterations(self):
        return np.int32(len(self.loss))


_FIELDS = ("means", "log_scales", "quats", "opacity_logits", "colors")


def _loss_fn(y, args):
    img, cam, valid, bg, lam, dist_w, dist_norm, tile, max_pairs, chunk = args
    g = Gaussians(y["means"], y["log_scales"], y["quats"], y["opacity_logits"], y["colors"], valid=valid)
    use_dist = not (isinstance(dist_w, (int, float)) and dist_w == 0)
    out = render_splats(g, cam, tile_size=tile, max_pairs=max_pairs, chunk=chunk, background=bg,
                        uv_offset=y["uv_offset"], distortion=use_dist)
    l1 = jnp.mean(jnp.abs(out.color - img))
    loss = (1 - lam) * l1 + lam * (1 - ssim_color(out.color, img))
    if use_dist:
        d = out.distortion
        if dist_norm:
            has = out.alpha > 1e-3
            d = jnp.where(has, d / jnp.where(has, out.alpha**2, 1.0), 0.0)
        loss = loss + dist_w * jnp.mean(d)
    return loss, (out.projected.visible, out.overflow, out.pairs)


# Compile events seen in this process (JAX's backend compiles and persistent-cache loads): a
# training step during which the count changes is a compiling step, reported apart.
_COMPILES = [0]
_LISTENING = []


def _count_compiles(name, *_a, **_kw):
    if name in ("/jax/core/compile/backend_compile_duration", "/jax/compilation_cache/cache_hits"):
        _COMPILES[0] += 1


def _listen_for_compiles():
    if not _LISTENING:
        jax.monitoring.register_event_duration_secs_listener(_count_compiles)
        jax.monitoring.register_event_listener(_count_compiles)
        _LISTENING.append(True)


@eqx.filter_jit
def _train_step(solver, y, state, images, cams, bg, view, valid_j, B, statics):
    """One optimiser step on training view ``view``. Module level and free of closures, so a
    second :func:`train_splats` on data of the same shapes reuses the compiled program (the
    step was a closure over the call's arrays and compiled again on every call: 5.7 s)."""
    lam, dist_weight, dist_normalise, tile_size, chunk = statics
    cam = jax.tree_util.tree_map(lambda a: a[view], cams)
    y = dict(y, uv_offset=jnp.zeros_like(y["uv_offset"]))
    args = (images[view], cam, valid_j, bg, lam, dist_weight, dist_normalise, tile_size, B, chunk)
    y2, state2, aux = solver.step(_loss_fn, y, args, {}, state, frozenset())
    return y2, state2, aux, state2.f


def train_splats(key, data: MultiViewData, *, n_init: int = 2000, max_splats: int = 8000,
                 iterations: int = 2000, densify_every: int = 100, densify_from: int = 100,
                 densify_until: int | None = None, grad_threshold: float | None = None,
                 prune_opacity: float = 0.005, lam: float = 0.2, dist_weight: float = 0.0,
                 dist_normalise: bool = False, tile_size: int = 8, capacity: int | None = None,
                 max_pairs: int | None = None, chunk: int = 64,
                 lr_means: float = 1.6e-3, lr_means_final: float = 1.6e-5, lr_scales: float = 5e-3,
                 lr_quats: float = 1e-3, lr_opacity: float = 0.05, lr_colors: float = 2.5e-3,
                 progress: bool = True, dtype=jnp.float32, init: Gaussians | None = None) -> SplatTrainResult:
    """Train splats on ``data.train`` views (see the module docstring for the method).

    Args:
        key: PRNG key (initialisation, view order, splits).
        data: a :class:`MultiViewData`.
        n_init, max_splats: initial and maximum (fixed capacity) splat counts.
        iterations: optimiser steps (one training view each).
        densify_every, densify_from, densify_until: densification schedule in steps
            (``densify_until`` default ``iterations // 2``).
        grad_threshold: mean screen-space gradient norm (per px) that triggers densification
            (default ``0.0002 / (W / 2)``, the 3DGS NDC threshold in pixels).
        prune_opacity: opacity below which splats are removed.
        lam: SSIM weight; dist_weight, dist_normalise: depth-distortion term.
        tile_size, chunk: rasteriser tiles and compositing chunk (:func:`fsjax.render.render_splats`).
            ``tile_size`` defaults to 8 px (the renderer's default is 16): at 128 x 128 with 50k small
            splats, 8 px tiles cost 1.4x the pairs but a quarter of the pixels per pair, and the step
            measured 2.5x faster (``python benchmarks/bench_splat.py --tiles 16,8``); tiling is exact,
            so the images and gradients are the same to rounding.
        max_pairs: initial size of the rasteriser's (splat, tile) pair buffer (default: measured on
            the first training view; ``capacity x tiles`` when the legacy ``capacity`` is given).
            Every step returns the demand; a step whose demand exceeds the buffer is re-run with
            the buffer grown to the next power of two of 1.125 x the demand (one recompile per
            growth), so no step trains on an incomplete render. ``overflow`` records what the
            accepted step dropped (0 unless growth failed).
        lr_*: Adam learning rates (``lr_means`` in units of the scene extent, decayed
            exponentially to ``lr_means_final``).
        progress: show a tqdm bar.
        init: initial splats (e.g. :func:`fsjax.sfm.splat.init_from_points` of an SfM cloud) instead of
            :func:`init_from_mesh` of ``data.points``; its slot count is the capacity (``n_init`` and
            ``max_splats`` are then unused).

    Returns:
        :class:`SplatTrainResult`.
    """
    if iterations < 1:
        raise ValueError(f"train_splats: argument 'iterations' must be >= 1, got {iterations}")
    W = data.cameras.width
    if grad_threshold is None:
        grad_threshold = 0.0002 / (0.5 * W)
    if densify_until is None:
        densify_until = iterations // 2
    kinit, kview, ksplit = jax.random.split(key, 3)
    if init is None:
        g = init_from_mesh(kinit, data, n_init, max_splats, dtype=dtype)
    else:
        if not isinstance(init, Gaussians) or init.batch_shape or init.colors.shape[-2] != 1:
            raise ValueError("train_splats: argument 'init' must be one set of Gaussians with degree-0 colours")
        g = jax.tree_util.tree_map(lambda a: a.astype(dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a, init)
    N = g.means.shape[0]
    y = {f: getattr(g, f) for f in _FIELDS}
    y["uv_offset"] = jnp.zeros((N, 2), dtype)
    valid = np.asarray(g.valid).copy()
    ext = data.extent
    lrs = {"means": lr_means * ext, "log_scales": lr_scales, "quats": lr_quats, "opacity_logits": lr_opacity,
           "colors": lr_colors, "uv_offset": 0.0}
    tx = _grouped_adam(lrs, decay={"means": (lr_means_final / lr_means, iterations)}, dtype=dtype)
    solver = optx.OptaxMinimiser(tx, rtol=0.0, atol=0.0)
    images = data.images.astype(dtype)
    cams = jax.tree_util.tree_map(lambda a: a.astype(dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a,
                                  data.cameras)
    bg = jnp.zeros(3, dtype)
    def cam_of(view):
        return jax.tree_util.tree_map(lambda a: a[view], cams)

    def args_for(view, valid_j, B):
        return (images[view], cam_of(view), valid_j, bg, lam, dist_weight, dist_normalise, tile_size, B, chunk)

    if max_pairs is not None:
        B = int(max_pairs)
    elif capacity is not None:
        B = int(capacity) * (-(-data.cameras.height // tile_size)) * (-(-data.cameras.width // tile_size))
    else:
        B = _bucket(count_splat_pairs(g, cam_of(int(data.train[0])), tile_size=tile_size))
    a0 = args_for(int(data.train[0]), jnp.asarray(valid), B)
    f_struct = jax.ShapeDtypeStruct((), dtype)
    aux_struct = None
    state = solver.init(_loss_fn, y, a0, {}, f_struct, aux_struct, frozenset())

    statics = (lam, dist_weight, dist_normalise, tile_size, chunk)

    order = np.asarray(jax.random.permutation(kview, np.tile(data.train, iterations // len(data.train) + 1)))
    losses, overflows, counts, times, demand, cpu_times = [], [], [], [], [], []
    gacc = np.zeros(N)
    gden = np.zeros(N)
    rng_split = np.random.default_rng(np.asarray(jax.random.key_data(ksplit)).ravel()[-1].item())
    _listen_for_compiles()
    it = range(iterations)
    if progress:
        from tqdm.auto import tqdm
        it = tqdm(it, desc="splat train", leave=False)
    compile_s = compile_cpu = 0.0
    for s in it:
        t0 = time.perf_counter()
        c0 = time.process_time()
        fresh = False
        while True:
            n_compiles = _COMPILES[0]
            y1, state1, (vis, ov, npairs), f = _train_step(solver, y, state, images, cams, bg,
                                                           jnp.asarray(order[s]), jnp.asarray(valid), B,
                                                           statics)
            fresh = fresh or _COMPILES[0] != n_compiles
            if int(npairs) <= B:
                break
            B = _bucket(int(npairs))  # grow the pair buffer and re-run this step
        y, state = y1, state1
        f = float(f)
        dt_s = time.perf_counter() - t0
        if fresh:
            compile_s += dt_s
            compile_cpu += time.process_time() - c0
        else:
            times.append(dt_s)
            cpu_times.append(time.process_time() - c0)
        demand.append(int(npairs))
        losses.append(f)
        overflows.append(int(ov))
        vis = np.asarray(vis)
        gn = np.linalg.norm(np.asarray(y["uv_offset"], np.float64), axis=1)
        gacc += np.where(vis, gn, 0.0)
        gden += vis
        if densify_from <= s + 1 <= densify_until and (s + 1) % densify_every == 0:
            y, state, valid = _densify_prune(y, state, valid, gacc / np.maximum(gden, 1), grad_threshold,
                                             prune_opacity, 0.01 * ext, rng_split)
            gacc[:] = 0
            gden[:] = 0
            counts.append(int(valid.sum()))
        if progress:
            it.set_postfix(loss=f"{f:.4f}", n=int(valid.sum()))
    gfin = Gaussians(*(y[k] for k in _FIELDS), valid=jnp.asarray(valid))
    return SplatTrainResult(gaussians=gfin, loss=np.asarray(losses), n_splats=np.asarray(counts, int),
                            overflow=np.asarray(overflows), step_seconds=float(np.median(times)) if times else
                            float("nan"), compile_seconds=compile_s, converged=bool(np.isfinite(losses[-1])),
                            pairs=np.asarray(demand), max_pairs=B, compile_cpu_seconds=compile_cpu,
                            step_cpu_seconds=float(np.median(cpu_times)) if cpu_times else float("nan"))


class _GroupedAdamState(eqx.Module):
    count: Any
    mu: Any
    nu: Any


class _GroupedAdamInit(eqx.Module):
    def __call__(self, params):
        z = {k: jnp.zeros_like(v) for k, v in params.items()}
        return _GroupedAdamState(jnp.zeros((), jnp.int32), z, dict(z))


class _GroupedAdamUpdate(eqx.Module):
    """The update of :func:`_grouped_adam`: learning rates and decay as arrays (traced, so a new
    rate does not recompile the training step), the raw-gradient keys static."""

    lrs: dict
    decay: dict
    raw: tuple = eqx.field(static=True)
    b1: float = eqx.field(static=True, default=0.9)
    b2: float = eqx.field(static=True, default=0.999)
    eps: float = eqx.field(static=True, default=1e-15)

    def __call__(self, grads, state, params=None, **extra):
        b1, b2 = self.b1, self.b2
        c = state.count + 1
        mu = {k: b1 * state.mu[k] + (1 - b1) * g for k, g in grads.items()}
        nu = {k: b2 * state.nu[k] + (1 - b2) * g * g for k, g in grads.items()}
        out = {}
        for k, g in grads.items():
            if k in self.raw:
                out[k] = g
                continue
            lr = self.lrs[k]
            if k in self.decay:
                ratio, steps = self.decay[k]
                lr = lr * ratio ** (jnp.minimum(c, steps) / steps)
            mhat = mu[k] / (1 - b1**c)
            vhat = nu[k] / (1 - b2**c)
            out[k] = (-lr * mhat / (jnp.sqrt(vhat) + self.eps)).astype(g.dtype)
        return out, _GroupedAdamState(c, mu, nu)


def _grouped_adam(lrs: dict, *, decay: dict, b1: float = 0.9, b2: float = 0.999, eps: float = 1e-15,
                  dtype=jnp.float32):
    """Adam with one learning rate per top-level key of a dict of arrays (optional exponential
    decay ``lr * ratio^(t / steps)``); a key with ``lr == 0`` passes its raw gradient through
    (the ``uv_offset`` read-out of the screen-space gradient). Written as a plain
    ``optax.GradientTransformation`` (``optax.multi_transform`` closures cannot be converted by
    ``OptaxMinimiser``) whose two functions are equinox modules: equal hyperparameters give an
    equal (hashable) transformation, so the jitted training step is not compiled again."""
    raw = tuple(k for k, v in lrs.items() if v == 0.0)
    arr = {k: jnp.asarray(v, dtype) for k, v in lrs.items() if k not in raw}
    dec = {k: (jnp.asarray(r, dtype), jnp.asarray(n, jnp.int32)) for k, (r, n) in decay.items()}
    return optax.GradientTransformation(_GroupedAdamInit(), _GroupedAdamUpdate(arr, dec, raw, b1, b2, eps))


def _densify_prune(y, state, valid, grad, thr, prune_opacity, big_scale, rng):
    """Split/clone high-gradient splats into free slots, prune transparent ones; reset moments."""
    ynp = {k: np.array(v) for k, v in y.items()}
    N = valid.size
    changed = np.zeros(N, bool)
    op = 1 / (1 + np.exp(-ynp["opacity_logits"].astype(np.float64)))
    cand = np.flatnonzero(valid & (grad > thr))
    cand = cand[np.argsort(-grad[cand])]
    free = np.flatnonzero(~valid)
    cand = cand[: len(free)]
    slots = free[: len(cand)]
    scales = np.exp(ynp["log_scales"][cand].astype(np.float64))
    big = scales.max(1) > big_scale
    for k in _FIELDS:
        ynp[k][slots] = ynp[k][cand]
    # split: two samples from the Gaussian, scales / 1.6
    sp, sl = cand[big], slots[big]
    if sp.size:
        q = ynp["quats"][sp].astype(np.float64)
        q = q / np.linalg.norm(q, axis=1, keepdims=True)
        w, x, yy, z = q.T
        R = np.stack([
            np.stack([1 - 2 * (yy * yy + z * z), 2 * (x * yy - w * z), 2 * (x * z + w * yy)], -1),
            np.stack([2 * (x * yy + w * z), 1 - 2 * (x * x + z * z), 2 * (yy * z - w * x)], -1),
            np.stack([2 * (x * z - w * yy), 2 * (yy * z + w * x), 1 - 2 * (x * x + yy * yy)], -1)], -2)
        sc = np.exp(ynp["log_scales"][sp].astype(np.float64))
        base = ynp["means"][sp].astype(np.float64)
        for idx in (sp, sl):
            off = np.einsum("nij,nj->ni", R, rng.normal(size=(sp.size, 3)) * sc)
            ynp["means"][idx] = base + off
        ynp["log_scales"][sp] -= np.log(1.6)
        ynp["log_scales"][sl] = ynp["log_scales"][sp]
    valid = valid.copy()
    valid[slots] = True
    changed[slots] = True
    changed[cand] = True
    prune = valid & (op < prune_opacity)
    valid[prune] = False
    changed[prune] = True
    ynp["uv_offset"][:] = 0
    y = {k: jnp.asarray(v, y[k].dtype) for k, v in ynp.items()}
    ch = jnp.asarray(changed)

    def reset(leaf):
        if isinstance(leaf, jax.Array) and leaf.ndim >= 1 and leaf.shape[0] == N and jnp.issubdtype(
                leaf.dtype, jnp.floating):
            return jnp.where(ch.reshape((N,) + (1,) * (leaf.ndim - 1)), 0.0, leaf).astype(leaf.dtype)
        return leaf

    state = eqx.tree_at(lambda s: s.opt_state, state, jax.tree_util.tree_map(reset, state.opt_state))
    return y, state, valid


def evaluate_splats(g: Gaussians, data: MultiViewData, views=None, *, tile_size: int = 16,
                    capacity: int | None = None,
                    alpha_threshold: float = 0.5) -> dict:
    """Held-out metrics (means over ``views``, default ``data.test``).

    ``psnr``, ``ssim`` (colour clipped to [0, 1]); ``holes`` (coverage, per image third);
    ``thickness``: per object pixel, the weight-normalised mean pairwise depth separation of
    the composited splats, ``distortion / A^2`` (0 for a single sheet, larger for a thick
    cloud), averaged; ``median_depth_error``: mean ``|median depth - true depth|`` over
    object pixels; ``overflow``: total splat-tile pairs dropped (0 with the default
    ``capacity=None``: each eager render sizes its pair buffer from the measured demand)."""
    views = data.test if views is None else views
    ps, ss, holes, thick, mde, ov = [], [], [], [], [], 0
    for vi in views:
        cam = jax.tree_util.tree_map(lambda a, vi=vi: a[vi], data.cameras)
        cam = jax.tree_util.tree_map(lambda a: a.astype(g.means.dtype) if jnp.issubdtype(a.dtype, jnp.floating)
                                     else a, cam)
        out = render_splats(g, cam, tile_size=tile_size, capacity=capacity)
        img = data.images[vi].astype(out.color.dtype)
        ps.append(float(_psnr(jnp.clip(out.color, 0, 1), img)))
        ss.append(float(ssim_color(jnp.clip(out.color, 0, 1), img)))
        holes.append(coverage_holes(out.alpha, data.masks[vi], alpha_threshold=alpha_threshold))
        m = np.asarray(data.masks[vi])
        dtrue = np.asarray(data.depths[vi])
        med = np.asarray(out.median_depth)
        A = np.asarray(out.alpha)
        ok = m & (A > 1e-3)
        thick.append(float(np.mean(np.asarray(out.distortion)[ok] / A[ok] ** 2)))
        mde.append(float(np.mean(np.abs(med[ok & (med > 0)] - dtrue[ok & (med > 0)]))))
        ov += int(out.overflow)
    keys = holes[0].keys()
    return {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss)),
            "holes": {k: float(np.nanmean([h[k] for h in holes])) for k in keys},
            "thickness": float(np.mean(thick)), "median_depth_error": float(np.mean(mde)), "overflow": ov}
