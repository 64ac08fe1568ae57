"""Hessian-based 3-D filters: Frangi vesselness and blobness (``Volume -> Volume``).

Conventions:

* The Hessian is taken at scale ``sigma`` (physical units, spacing-aware) by Gaussian
  derivative filters, ``H_ab = d^2/dx_a dx_b (G_sigma * vol)`` in value per unit^2, each term
  equal to ``scipy.ndimage.gaussian_filter(x, s, order=e_a + e_b) / (spacing_a spacing_b)``
  with ``s = sigma / spacing`` (tested to 1e-12 in float64), then scale-normalised by
  ``sigma^2`` (Lindeberg's gamma = 2) so responses compare across scales.
* Eigenvalues per voxel by LAPACK-free Jacobi rotations (``fsjax._linalg.eigh_small``; the
  batched LAPACK kernels of jaxlib 0.10 can deadlock XLA:CPU, see tools/repro_xla_hang.py),
  ordered by magnitude ``|l1| <= |l2| <= |l3|``.
* **Vesselness** (Frangi et al. 1998): ``Ra = |l2| / |l3|`` (plate vs line), ``Rb = |l1| /
  sqrt(|l2 l3|)`` (blob vs line), ``S = sqrt(l1^2 + l2^2 + l3^2)`` (structure);
  ``V = (1 - exp(-Ra^2 / 2 alpha^2)) exp(-Rb^2 / 2 beta^2) (1 - exp(-S^2 / 2 c^2))`` where
  ``l2, l3`` have the sign of a bright tube (both negative; ``bright=False``: positive), else 0.
  ``c`` defaults to half the largest ``S`` in the volume (Frangi's rule).
* **Blobness**: the same structure with all three eigenvalues of the blob's sign,
  ``B = (1 - exp(-Rb'^2 / 2 beta^2)) (1 - exp(-S^2 / 2 c^2))`` with ``Rb' = |l1| / |l3|`` (1 for a
  sphere): bright (or dark) spheres, not tubes or plates.
* Outputs are in ``[0, 1]``; a flat volume gives 0, not NaN: a scale-normalised Hessian norm
  below twice what a constant volume of the same maximum produces (truncated second-derivative
  taps do not sum to zero) counts as no structure.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from ..._checks import check_positive, check_range
from ..._linalg import eigh_small
from ...registry import LogKnob, register
from ...types import Volume
from ..image._filters import _corr1d, _gaussian_taps
from ._filters3d import _AXES, _check_common, _order2_taps, _poison_sigma, _sigma_voxels

__all__ = ["vesselness3d", "blobness3d"]

_FRANGI = ("A. F. Frangi, W. J. Niessen, K. L. Vincken, M. A. Viergever, Multiscale vessel enhancement "
           "filtering, MICCAI 1998")
_LINDEBERG = "T. Lindeberg, Feature detection with automatic scale selection, IJCV 30(2), 1998"


def _order1_taps(sigma, radius: int, truncate: float, dtype):
    """First-derivative Gaussian taps ``-k / s^2 g[k]`` for correlation (SciPy's order-1 filter)."""
    g = _gaussian_taps(sigma, radius, truncate, dtype)
    k = jnp.arange(-radius, radius + 1, dtype=dtype)
    return -k / (jnp.asarray(sigma, dtype) ** 2) * g


def hessian3d_core(x, sig, radii, truncate: float, mode: str, spacing):
    """The six Hessian entries ``(zz, yy, xx, zy, zx, yx)`` in value per unit^2 (internal)."""
    out = {}
    for a in range(3):
        for b in range(a, 3):
            y = x
            for c, (ax, s, r) in enumerate(zip(_AXES, sig, radii)):
                order = (c == a) + (c == b)
                w = (_gaussian_taps(s, r, truncate, x.dtype) if order == 0 else
                     _order1_taps(s, r, truncate, x.dtype) if order == 1 else
                     _order2_taps(s, r, truncate, x.dtype))
                y = _corr1d(y, w, ax, mode)
            out[(a, b)] = y / (spacing[a] * spacing[b])
    return out


def _eigen_sorted(h, sigma):
    """Scale-normalised eigenvalues ordered by magnitude, ``(D, H, W, 3)``."""
    m = jnp.stack([jnp.stack([h[(0, 0)], h[(0, 1)], h[(0, 2)]], -1),
                   jnp.stack([h[(0, 1)], h[(1, 1)], h[(1, 2)]], -1),
                   jnp.stack([h[(0, 2)], h[(1, 2)], h[(2, 2)]], -1)], -2) * (sigma * sigma)
    w, _ = eigh_small(m.reshape(-1, 3, 3))
    order = jnp.argsort(jnp.abs(w), axis=-1)
    return jnp.take_along_axis(w, order, axis=-1).reshape(m.shape[:-1])


def _structure_term(s, c):
    cc = 0.5 * jnp.max(s) if c is None else c
    cc = jnp.maximum(cc, jnp.finfo(s.dtype).tiny)
    return 1.0 - jnp.exp(-(s * s) / (2.0 * cc * cc))


@functools.partial(jax.jit, static_argnames=("radii", "truncate", "mode", "spacing", "bright", "kind"))
def _hessian_filter_core(x, sz, sy, sx, sigma, alpha, beta, c, *, radii, truncate, mode, spacing, bright, kind):
    h = hessian3d_core(x, (sz, sy, sx), radii, truncate, mode, spacing)
    lam = _eigen_sorted(h, sigma)
    l1, l2, l3 = lam[..., 0], lam[..., 1], lam[..., 2]
    a1, a2, a3 = jnp.abs(l1), jnp.abs(l2), jnp.abs(l3)
    tiny = jnp.finfo(x.dtype).tiny
    s = jnp.sqrt(l1 * l1 + l2 * l2 + l3 * l3)
    st = _structure_term(s, c)
    sgn = -1.0 if bright else 1.0
    if kind == "vessel":
        ra = a2 / jnp.maximum(a3, tiny)
        rb = a1 / jnp.sqrt(jnp.maximum(a2 * a3, tiny))
        v = (1.0 - jnp.exp(-ra * ra / (2 * alpha * alpha))) * jnp.exp(-rb * rb / (2 * beta * beta)) * st
        ok = (sgn * l2 > 0) & (sgn * l3 > 0)
    else:
        rb = a1 / jnp.maximum(a3, tiny)
        v = (1.0 - jnp.exp(-rb * rb / (2 * beta * beta))) * st
        ok = (sgn * l1 > 0) & (sgn * l2 > 0) & (sgn * l3 > 0)
    # a Hessian at the level a flat volume gives is no structure: truncated second-derivative
    # taps do not sum to zero (as in SciPy), so a constant c has H_aa = c sum(taps_a) / dx_a^2;
    # without this floor, c = max(S) / 2 would scale that bias (or rounding) up to a response
    bias = jnp.max(jnp.stack([jnp.abs(jnp.sum(_order2_taps(s_, r, truncate, x.dtype))) / (d * d)
                              for s_, r, d in zip((sz, sy, sx), radii, spacing)]))
    floor = (2.0 * jnp.sqrt(3.0) * bias * sigma * sigma + 1e3 * jnp.finfo(x.dtype).eps) * jnp.max(jnp.abs(x))
    return jnp.where(ok & (s > floor), v, 0.0)


def _run(op, vol, sigma, alpha, beta, c, bright, truncate, mode, max_sigma, kind):
    _check_common(op, sigma, truncate, mode, max_sigma)
    check_range(op, "beta", beta, lo=0.0, lo_open=True)
    if kind == "vessel":
        check_range(op, "alpha", alpha, lo=0.0, lo_open=True)
    if c is not None:
        check_positive(op, "c", c)
    if not isinstance(bright, bool):
        raise TypeError(f"{op}: argument 'bright' must be True or False; got {bright!r}")
    sig, radii = _sigma_voxels(op, sigma, vol.spacing, float(truncate), float(max_sigma))
    out = _hessian_filter_core(vol.data, *sig, jnp.asarray(sigma, vol.data.dtype), alpha, beta,
                               None if c is None else jnp.asarray(c, vol.data.dtype), radii=radii,
                               truncate=float(truncate), mode=mode, spacing=vol.spacing, bright=bright, kind=kind)
    return _poison_sigma(Volume(out, vol.spacing, vol.unit), sig, truncate, radii, op)


@register(family="hessian3d", takes=Volume, gives=Volume, knobs={"sigma": LogKnob(0.5, 8.0)},
          differentiable=False, refs=[_FRANGI, _LINDEBERG])
def vesselness3d(vol: Volume, /, *, sigma: float = 1.0, alpha: float = 0.5, beta: float = 0.5,
                 c: float | None = None, bright: bool = True, truncate: float = 4.0, mode: str = "reflect",
                 max_sigma: float = 8.0) -> Volume:
    """Frangi vesselness at one scale: high on tubes of radius about ``sigma``, low on blobs and plates.

    Args:
      vol: ``Volume`` ``(D, H, W)``.
      sigma: scale in the volume's unit, > 0 (knob ``a``, log-mapped to [0.5, 8]); a tube of
        radius ``r`` responds most near ``sigma = r / sqrt(2)``.
      alpha: plate-vs-line sensitivity (default 0.5). beta: blob-vs-line sensitivity (0.5).
      c: structure threshold in scale-normalised Hessian units; default half the largest
        Hessian norm in the volume.
      bright: bright tubes on a dark background (default) or dark ones (False); static.
      truncate, mode, max_sigma: as for ``gaussian3d``.

    Returns:
      ``Volume`` in ``[0, 1]``.

    Example:
      A bright tube along x and a bright ball of the same radius: the tube's axis responds
      strongly, the ball's centre weakly (Frangi's blob term does not reach zero at beta 0.5):

      >>> import numpy as np, jax.numpy as jnp, fsjax
      >>> z, y, x = np.mgrid[:24, :24, :32].astype(float)
      >>> tube = np.exp(-((z - 7) ** 2 + (y - 7) ** 2) / 8.0)
      >>> ball = np.exp(-((z - 16) ** 2 + (y - 16) ** 2 + (x - 16) ** 2) / 8.0)
      >>> v = fsjax.ops.vesselness3d(fsjax.Volume(jnp.asarray(tube + ball)), sigma=2.0)
      >>> round(float(v.data[7, 7, 16]), 2), round(float(v.data[16, 16, 16]), 2)
      (0.75, 0.09)
    """
    return _run("vesselness3d", vol, sigma, alpha, beta, c, bright, truncate, mode, max_sigma, "vessel")


@register(family="hessian3d", takes=Volume, gives=Volume, knobs={"sigma": LogKnob(0.5, 8.0)},
          differentiable=False, refs=[_FRANGI, _LINDEBERG])
def blobness3d(vol: Volume, /, *, sigma: float = 1.0, beta: float = 0.5, c: float | None = None,
               bright: bool = True, truncate: float = 4.0, mode: str = "reflect", max_sigma: float = 8.0) -> Volume:
    """Hessian blobness at one scale: high at the centres of balls of radius about ``sigma``.

    Args:
      vol: ``Volume`` ``(D, H, W)``.
      sigma: scale in the volume's unit, > 0 (knob ``a``, log-mapped to [0.5, 8]).
      beta: isotropy sensitivity (default 0.5): ``|l1| / |l3|`` near 1 for a ball.
      c: structure threshold (default half the largest Hessian norm).
      bright: bright blobs (default) or dark ones (False); static.
      truncate, mode, max_sigma: as for ``gaussian3d``.

    Returns:
      ``Volume`` in ``[0, 1]``.

    Example:
      The ball responds at its centre, the tube along its axis does not:

      >>> import numpy as np, jax.numpy as jnp, fsjax
      >>> z, y, x = np.mgrid[:24, :24, :32].astype(float)
      >>> tube = np.exp(-((z - 7) ** 2 + (y - 7) ** 2) / 8.0)
      >>> ball = np.exp(-((z - 16) ** 2 + (y - 16) ** 2 + (x - 16) ** 2) / 8.0)
      >>> b = fsjax.ops.blobness3d(fsjax.Volume(jnp.asarray(tube + ball)), sigma=2.0)
      >>> bool(b.data[16, 16, 16] > 0.5), bool(b.data[7, 7, 16] < 0.05)
      (True, True)
    """
    return _run("blobness3d", vol, sigma, 0.5, beta, c, bright, truncate, mode, max_sigma, "blob")
